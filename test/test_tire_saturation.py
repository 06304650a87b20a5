"""The tire's saturation, measured from the innovations (issue #10, the linear range): ``ekf.saturation_prior``.

On a tire mu Fz tanh(C alpha / (mu Fz)) a linear tire model reads the secant stiffness. The filter
propagates the bias a tire at ``ekf.min_friction`` would cause and that bias's signature in the
innovations (adaptation.propagate_tire_bias); a least-squares fit of the innovations to the signature
measures the saturation a (1: a tire at min_friction, 0: a linear tire), and Cf, Cr take a's posterior
mode (prior N(0, saturation_prior^2), a >= 0) times the bias (adaptation.saturation_share).

Every figure is measured on the project's simulator (test/drives.py: 2 m/s, 5 Hz, 120 s, +-15 deg sine
of 6 s unless a drive says otherwise) over seeds 0-9 with the defaults, against its small-slip truth
Cf = 8000, Cr = 10000 N/rad. mu 0.3 is a wet field; "off" is ``ekf.saturation_prior: 0``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import pytest
from drives import TRUE_CF, TRUE_CR, Run, median_and_worst, pooled_coverage, run_drive, sine_drive
from independent_sim import independent_drive
from test_validity import epochs_of, validity

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions
from transplanter_ident.ekf.adaptation import SATURATION_REACH_SIGMAS
from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.ekf.layout import (
    O_CF,
    O_CF_STD,
    O_CHANGE,
    O_CR,
    O_CR_STD,
    O_SATURATION,
    O_SATURATION_STD,
    O_TIRE_BIAS_F,
    O_TIRE_BIAS_R,
)
from transplanter_ident.evaluation.convergence_report import convergence_report
from transplanter_ident.sim.signals import StiffnessSchedule, sine_steering
from transplanter_ident.sim.simulator import SensorNoise, simulate

SEEDS = range(10)
WET = {"tire": "saturating", "friction": 0.3}
DRIVES = {
    "linear 15 deg": {},
    "linear 25 deg": {"steering": sine_steering(math.radians(25.0), 6.0)},
    "wet 3 m/s": {**WET, "speed": 3.0},  # ~40 % of the epochs beyond the slip / lateral acceleration limits
    "wet 25 deg": {**WET, "steering": sine_steering(math.radians(25.0), 6.0)},
}
OFF = EstimatorConfig(options=FilterOptions(saturation_prior=0.0))
PRIOR = FilterOptions().saturation_prior


@functools.cache
def runs(drive: str, measured: bool = True) -> tuple[Run, ...]:
    config = None if measured else OFF
    return tuple(run_drive(sine_drive(seed, **DRIVES[drive]), config) for seed in SEEDS)


def final_errors(drive: str, measured: bool = True) -> list[float]:
    return [e for r in runs(drive, measured) for e in r.final_errors()]


def test_slip_beyond_the_linear_range_is_identified_by_the_small_slip_stiffness() -> None:
    """Wet field at 3 m/s, the tires well past their linear range: every final error <= 5 % (off: > 10 %).

    From 30 s on, +-2 sigma covers the truth in >= 90 % of epochs, with and without the measure.
    """
    errors = final_errors("wet 3 m/s")
    assert median_and_worst(errors)[1] <= 0.05, errors
    assert median_and_worst(final_errors("wet 3 m/s", measured=False))[0] > 0.10  # the test has teeth
    for measured in (True, False):
        front, rear = pooled_coverage(list(runs("wet 3 m/s", measured)), 30.0)
        assert front >= 0.90 and rear >= 0.90, (measured, front, rear)


def test_a_wet_field_at_25_deg_halves_the_error_and_keeps_the_band_honest() -> None:
    """Wet field, +-25 deg at 2 m/s: median final error <= 5 % and at most half of the unmeasured one (~9.5 %).

    The band still covers the truth in >= 90 % of epochs after 30 s (it keeps the bias left to a tire at
    min_friction, the measure's variance and half the correction).
    """
    measured, off = median_and_worst(final_errors("wet 25 deg")), median_and_worst(final_errors("wet 25 deg", False))
    assert measured[0] <= 0.05 and measured[0] <= 0.5 * off[0], (measured, off)
    front, rear = pooled_coverage(list(runs("wet 25 deg")), 30.0)
    assert front >= 0.90 and rear >= 0.90, (front, rear)


@pytest.mark.parametrize("drive", ["linear 15 deg", "linear 25 deg"])
def test_a_linear_tire_measures_no_saturation_and_stays_accurate(drive: str) -> None:
    """Linear tires: the measured a is within 3 std of 0 on >= 9 of 10 seeds; median error <= 2 %, worst <= 5 %.

    Every final error is within +-2 sigma: the correction's own uncertainty is in the std.
    """
    seeds = runs(drive)
    within = [abs(r.outputs[-1, O_SATURATION]) <= 3.0 * r.outputs[-1, O_SATURATION_STD] for r in seeds]
    assert sum(within) >= 9, [(r.outputs[-1, O_SATURATION], r.outputs[-1, O_SATURATION_STD]) for r in seeds]
    median, worst = median_and_worst(final_errors(drive))
    assert median <= 0.02 and worst <= 0.05, (median, worst)
    for r in seeds:
        assert all(abs(e) <= 2.0 * std for e, std in zip(r.final_errors(), r.final_rel_std(), strict=True))


def slow_share(a: float, a_std: float, prior: float) -> tuple[float, float]:
    """The posterior of a, written out: N(a, a_std^2) times the prior N(0, prior^2), its mode where a >= 0.

    The std keeps what is left to the reach, the posterior variance and half the share. The reach is a
    tire at min_friction (a = 1), or max(a, 0) + SATURATION_REACH_SIGMAS a_std where that is less: the data
    exclude such a tire.
    """
    if a_std == 0.0:
        return 0.0, 1.0
    variance = 1.0 / (1.0 / a_std**2 + 1.0 / prior**2)
    share = max(variance / a_std**2 * a, 0.0)
    reach = min(1.0, max(a, 0.0) + SATURATION_REACH_SIGMAS * a_std)
    return share, max(reach - share, 0.0) ** 2 + variance + (0.5 * share) ** 2


@pytest.mark.parametrize("grippy", [False, True])
def test_the_compiled_correction_is_the_posterior_written_out(grippy: bool) -> None:
    """The default run equals the run with the measure off, corrected in Python from the published a and std.

    The measure does not feed back into the filter, so the off run's Cf, Cr, P and bias are the same. A
    wet drive (the reach stays 1) and a grippy one of the independent simulator (the reach falls below 1).
    """
    result = (independent_drive(0, speed=2.5, amplitude_deg=18.0, duration=90.0, friction=0.8, gnss_rate=10.0)
              if grippy else simulate(sine_drive(3, **DRIVES["wet 25 deg"])))
    on, off = run_drive(result).outputs, run_drive(result, OFF).outputs
    assert np.max(on[:, O_SATURATION_STD]) > 0.0
    reach = np.minimum(1.0, np.maximum(on[:, O_SATURATION], 0.0) + SATURATION_REACH_SIGMAS * on[:, O_SATURATION_STD])
    assert np.any((reach < 0.5) & (on[:, O_SATURATION_STD] > 0.0)) == grippy
    for row_on, row_off in zip(on, off, strict=True):
        share, unpinned = slow_share(row_on[O_SATURATION], row_on[O_SATURATION_STD], PRIOR)
        for c, std, bias in ((O_CF, O_CF_STD, O_TIRE_BIAS_F), (O_CR, O_CR_STD, O_TIRE_BIAS_R)):
            c_off = row_off[c]
            assert row_on[c] == pytest.approx(c_off * (1.0 + share * row_off[bias]), rel=1e-9)
            p_part = row_off[std] ** 2 - (c_off * row_off[bias]) ** 2
            assert row_on[std] == pytest.approx(math.sqrt(p_part + unpinned * (c_off * row_off[bias]) ** 2),
                                                rel=1e-7)


def test_large_slips_that_stay_linear_release_the_bias_of_a_slippery_tire() -> None:
    """Grippy Magic Formula tires (mu 0.8, the independent simulator) at +-18 deg, 2.5 m/s, 10 Hz, 150 s, seeds 0-5.

    A tire at ekf.min_friction (0.3) would saturate visibly at these slips; the measure reads a ~ 0 with a
    std of ~0.15, so the band keeps the bias up to max(a, 0) + 1 std only, not the whole bias at min_friction
    (13 % of Cf). Valid from 30 s on in 97 % of the epochs (80 % with the reach at 2 std, 0-3 % when the
    band kept that whole bias), none of them outside +-2 sigma; every final error within +-2 sigma.
    """
    kept = missed = epochs = 0
    for seed in range(6):
        result = independent_drive(seed, speed=2.5, amplitude_deg=18.0, period=6.0, duration=150.0, friction=0.8,
                                   gnss_rate=10.0)
        run = run_drive(result)
        assert run.outputs[-1, O_SATURATION] + 2.0 * run.outputs[-1, O_SATURATION_STD] < 1.0  # a tire at 0.3 excluded
        after = run.t >= 30.0
        valid = validity(run, epochs_of(result)) & after
        front, rear = run.covered()
        kept, missed, epochs = kept + int(valid.sum()), missed + int((valid & ~(front & rear)).sum()), epochs + int(
            after.sum())
        assert all(abs(e) <= 2.0 * std for e, std in zip(run.final_errors(), run.final_rel_std(), strict=True))
    assert kept >= 0.85 * epochs and missed <= 0.05 * kept, (kept, missed, epochs)


def test_a_surface_change_restarts_the_measure() -> None:
    """At a change alarm (a 40 % drop at 60 s) a's information restarts: its std jumps above 5x the one before.

    Only the first alarm after the measure started: a second one seconds later finds it restarted already.
    """
    drop = StiffnessSchedule(times=(0.0, 60.0), front=(TRUE_CF, 0.6 * TRUE_CF), rear=(TRUE_CR, 0.6 * TRUE_CR),
                             transition=0.0)
    outputs = run_drive(sine_drive(0, duration=90.0, stiffness=drop)).outputs
    alarms = np.nonzero((outputs[:, O_CHANGE] > 0.5) & (np.arange(len(outputs)) > 0))[0]
    alarms = [k for k in alarms if outputs[k - 1, O_SATURATION_STD] > 0.0]
    assert alarms, "no alarm after the measure started"
    k = alarms[0]
    assert outputs[k, O_SATURATION_STD] > 5.0 * outputs[k - 1, O_SATURATION_STD]


def cramer_rao_ln_stiffness(friction_known: bool) -> float:
    """1-sigma of ln Cf on the gentle wet drive from the noise-free response's sensitivities (output error)."""
    base = replace(sine_drive(0, **WET), noise=SensorNoise(0.0, 0.0, 0.0))
    noise = SensorNoise()

    def response(ln_cf: float, ln_cr: float, inv_mu2: float) -> np.ndarray:
        stiffness = StiffnessSchedule(front=(math.exp(ln_cf),), rear=(math.exp(ln_cr),))
        truth = simulate(replace(base, stiffness=stiffness, friction=1.0 / math.sqrt(inv_mu2)))
        return np.concatenate([truth.truth_vy / noise.velocity, truth.truth_heading / noise.heading])

    point = np.array([math.log(TRUE_CF), math.log(TRUE_CR), 1.0 / 0.3**2])
    steps = (1.0e-3, 1.0e-3, 0.05 * point[2])
    columns = []
    for k, h in enumerate(steps):
        dp = np.zeros(3)
        dp[k] = h
        columns.append((response(*(point + dp)) - response(*(point - dp))) / (2.0 * h))
    jacobian = np.array(columns).T
    information = jacobian.T @ jacobian
    if friction_known:
        information = information[:2, :2]
    return float(math.sqrt(np.linalg.inv(information)[0, 0]))


def test_a_gentle_wet_drive_does_not_pin_the_friction() -> None:
    """Why the +-15 deg wet drive keeps a 6-7 % worst case: no estimator can tell its friction from its stiffness.

    Its Cramer-Rao bound on ln Cf (the truth model, its sensor noise, 120 s) is > 3 % with mu unknown
    and < 1.5 % with mu known: the tire stays at a third of its friction limit, where tanh is too
    close to linear. The measure's final std of a there is > 0.5, so the correction leans on the prior.
    """
    assert cramer_rao_ln_stiffness(friction_known=False) > 0.03
    assert cramer_rao_ln_stiffness(friction_known=True) < 0.015
    gentle = [run_drive(sine_drive(seed, **WET)) for seed in SEEDS[:3]]
    assert all(r.outputs[-1, O_SATURATION_STD] > 0.5 for r in gentle)


@pytest.mark.parametrize("steer_deg", [15.0, 25.0])
def test_a_wet_field_is_not_valid_and_wrong(steer_deg: float) -> None:
    """Wet field, +-15 and +-25 deg: of the epochs the validity passes (after 30 s), <= 7.5 % miss the truth.

    A 2-sigma band claims 5 %; over seeds 0-9 it is 5.1 % (+-15 deg, the surface at ekf.min_friction, the
    edge the band is built for) and 0 of ~500 (+-25 deg). Before the band kept the bias left to a tire at
    min_friction, the +-25 deg drive passed the validity with 28 % of its valid epochs missed (5 seeds).
    """
    kept = missed = 0
    for seed in SEEDS:
        result = simulate(sine_drive(seed, **WET, steering=sine_steering(math.radians(steer_deg), 6.0)))
        run = run_drive(result)
        valid = validity(run, epochs_of(result)) & (run.t >= 30.0)
        front, rear = run.covered()
        kept += int(valid.sum())
        missed += int((valid & ~(front & rear)).sum())
    assert missed <= 0.075 * max(kept, 1), (missed, kept)


def test_the_measure_reaches_diagnostics() -> None:
    """/diagnostics "convergence" shows a and its std (`tire_saturation`) as the last estimate holds them."""
    run = runs("wet 3 m/s")[0]
    estimate = Estimate.from_row(float(run.t[-1]), run.outputs[-1])
    a, a_std = estimate.saturation
    assert a_std > 0.0 and a == run.outputs[-1, O_SATURATION]
    values = dict(convergence_report("estimator", estimate, updates=len(run.t), limit=0.05).values)
    assert values["tire_saturation"] == f"{a:.3f} {a_std:.3f}"
