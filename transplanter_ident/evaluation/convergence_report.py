"""The /diagnostics "convergence" status: the published band of Cf and Cr, and what it pins.

Converged when both relative 1-sigma bands are within ``diagnostics.converged_rel_std``. The
values add the band's scale / ratio decomposition and weak direction
(:class:`.identifiability.Identifiability`), the tire-saturation bias carried in the band
(``ekf.min_friction``), the factors on R the innovations have shown (``ekf.noise_adaptation``) and
how far Cf and Cr move per ms of GNSS delay left out of ``gnss.delay`` (relative, first order), and
that delay as the innovations show it (ms, and its std; std 0: not measured yet); likewise a tire
relaxation length left out of ``vehicle.relaxation_length`` (m) and Cf, Cr's move per cm of it, and
a steering gain left out of ``vehicle.steering_scale`` (%; a yaw inertia off ``vehicle.iz`` looks alike).
:func:`model_errors_line` is replay's summary of the measures.
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.evaluation.health_report import OK, WARN, HealthReport
from transplanter_ident.evaluation.identifiability import Identifiability


def convergence_report(node: str, estimate: Estimate | None, updates: int, limit: float) -> HealthReport:
    """The ``<node>: convergence`` status from the latest published estimate after ``updates`` stiffness updates."""
    name = f"{node}: convergence"
    if estimate is None:
        return HealthReport(name, WARN, "no estimate yet", (("converged", "false"),))
    cf, cr = estimate.cornering_stiffness_front, estimate.cornering_stiffness_rear
    rel_f = estimate.cornering_stiffness_front_std / cf if cf > 0.0 else math.inf
    rel_r = estimate.cornering_stiffness_rear_std / cr if cr > 0.0 else math.inf
    converged = updates > 0 and rel_f <= limit and rel_r <= limit
    known = Identifiability.of(rel_f, rel_r, estimate.stiffness_correlation)
    values = (("converged", str(converged).lower()), ("cf", f"{cf:.1f}"), ("cr", f"{cr:.1f}"),
              ("cf_rel_std", f"{rel_f:.4f}"), ("cr_rel_std", f"{rel_r:.4f}"), ("threshold", f"{limit:g}"),
              ("updates", str(updates)), ("correlation", f"{estimate.stiffness_correlation:.5f}"),
              ("scale_rel_std", f"{known.scale_std:.4g}"), ("ratio_rel_std", f"{known.ratio_std:.4g}"),
              ("weak_direction", f"{known.weak_direction[0]:+.3f} {known.weak_direction[1]:+.3f}"),
              ("weak_rel_std", f"{known.weak_std:.4g}"), ("identifiability", known.describe()),
              ("tire_saturation_bias", "{:.4f} {:.4f}".format(*estimate.tire_bias)),
              ("tire_saturation", "{:.3f} {:.3f}".format(*estimate.saturation)),
              ("noise_factors", "{:.3f} {:.3f}".format(*estimate.noise_factors)),
              ("innovation_correlation", "{:.3f} {:.3f}".format(*estimate.noise_correlations)),
              ("delay_sensitivity_per_ms", "{:+.4f} {:+.4f}".format(*(1.0e-3 * v for v in estimate.delay_sensitivity))),
              ("delay_estimate_ms", "{:+.1f} {:.1f}".format(*(1.0e3 * v for v in estimate.delay_estimate))),
              ("relaxation_estimate_m", "{:+.3f} {:.3f}".format(*estimate.relaxation_estimate)),
              ("relaxation_sensitivity_per_cm", "{:+.4f} {:+.4f}".format(*(0.01 * v for v in estimate.relaxation_sensitivity))),
              ("steering_gain_estimate_percent", "{:+.2f} {:.2f}".format(*(100 * v for v in estimate.steering_gain_estimate))),
              ("scale_sensitivity_per_percent", "{:+.4f} {:+.4f}".format(*(0.01 * v for v in estimate.scale_sensitivity))),
              ("heading_misalignment_deg", "{:+.2f} {:.2f}".format(*map(math.degrees, estimate.heading_misalignment))),
              ("steering_play_estimate_deg", "{:+.3f} {:.3f}".format(*map(math.degrees, estimate.steering_play_estimate))),
              ("play_sensitivity_per_deg", "{:+.4f} {:+.4f}".format(*(math.radians(1.0) * v
                                                                      for v in estimate.play_sensitivity))),
              ("change_evidence", f"{estimate.change_evidence:.2f}"))
    if converged:
        return HealthReport(name, OK, f"converged: Cf {cf:.0f} +- {100 * rel_f:.1f} %, "
                            f"Cr {cr:.0f} +- {100 * rel_r:.1f} %", values)
    if updates == 0:
        return HealthReport(name, WARN, "no stiffness update yet", values)
    return HealthReport(name, WARN, f"not converged: relative std Cf {100 * rel_f:.1f} %, Cr {100 * rel_r:.1f} % "
                        f"(threshold {100 * limit:g} %); {known.describe()}", values)


def model_errors_line(estimate: Estimate, relaxation_length: float) -> str:
    """What the innovations show of the GNSS delay, the tire relaxation, the steering gain, the heading and the play left out (replay)."""
    delay, delay_std = estimate.delay_estimate
    lag, lag_std = estimate.relaxation_estimate
    gain, gain_std = estimate.steering_gain_estimate
    heading, heading_std = estimate.heading_misalignment
    play, play_std = estimate.steering_play_estimate
    if not (delay_std > 0.0 or lag_std > 0.0):
        return "Model errors the innovations show: not measured (too few updates)"
    return (f"Model errors the innovations show (final): GNSS delay not in gnss.delay {1e3 * delay:+.1f} +- "
            f"{1e3 * delay_std:.1f} ms; tire relaxation beyond vehicle.relaxation_length ({relaxation_length:g} m) "
            f"{lag:+.3f} +- {lag_std:.3f} m; steering gain off vehicle.steering_scale (or Iz off vehicle.iz) "
            f"{100 * gain:+.2f} +- {100 * gain_std:.2f} %; heading off the vehicle beyond vehicle.heading_offset "
            f"{math.degrees(heading):+.2f} +- {math.degrees(heading_std):.2f} deg; steering play beyond "
            f"vehicle.steering_play {math.degrees(play):+.3f} +- {math.degrees(play_std):.3f} deg")
