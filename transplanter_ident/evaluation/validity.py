"""Whether each estimate can be trusted: the validity decision of every epoch (DESIGN.md section 7).

A precise-looking number that is wrong is the worst output, so an estimate is valid only when all
of these hold over a window of data time (the same decision online and offline):

* converged: the relative 1-sigma of Cf and Cr is small, and neither is pinned at a bound;
* no model error left out (:mod:`.model_errors`): a GNSS delay, a tire relaxation length, a steering
  gain (or yaw inertia) that the filter measures from its innovations is not 3 std from zero, nor does
  it (its lower 1-sigma bound) move Cf or Cr beyond their reported std;
* excited: the steering and the yaw rate varied enough (a held step identifies little);
* consistent: the normalised innovation squared (NIS, chi^2 with 2 dof per epoch when the
  filter's model and R are right) passes a windowed chi^2 test, and the whitened innovations are
  not autocorrelated (an unconfigured GNSS delay, a wrong lever arm or a wrong R show there); over
  the epochs whose measurement the filter used (a gated outlier counts as suspect input instead);
* plausible: a heading is not a course over ground (then vy is zero by construction while the
  vehicle turns: the antenna's vy stays well below what a steady turn gives there, (lr + antenna_x) r
  less the rear axle's slip at the estimated Cr), and the GNSS velocity agrees with the heading (an
  ENU/NED mix-up implies a sideslip at the CG no transplanter has, or a course that turns against
  the heading; an antenna ahead of the CG adds antenna_x r to its vy, which is no sideslip);
* following: the stiffness updates since the last change alarm, over ``drift_window`` s, each
  normalised by its std (layout.O_UPDATE_F/R, N(0, 1) while the stiffness holds still), do not sum
  beyond ``max_drift_sigmas`` sqrt(n): a stiffness that drifts (a changing surface or load) faster
  than the random walk lets the estimate follow keeps pushing them one way, and the band lags it;
  nor has the directional change test gathered ``max_change_evidence`` of its alarm level
  (layout.O_CHANGE_EVIDENCE): a new surface is suspected, and the estimate lags it until the alarm;
* trusted input (issue #14): at most ``max_suspect_fraction`` of the window's epochs follow a rejected
  input sample (:attr:`Sample.rejected`, in processing order: the same online and offline) or were gated,
  rejected or rolled back by the filter;
* a set-up the data can vouch for (:func:`setup_reasons`): one antenna's course cannot show a timing error.

Hysteresis: valid only after every check held for ``hold_on`` s; invalid once any has failed
for ``hold_off`` s (at once for the plausibility and bound checks). The window checks run every
RECHECK s of data (the same epochs online and offline).
"""

from __future__ import annotations

import functools
import math
import operator
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig, ValiditySettings
from transplanter_ident.ekf.layout import (
    O_CF,
    O_CF_STD,
    O_CHANGE,
    O_CHANGE_EVIDENCE,
    O_CR,
    O_CR_STD,
    O_E0,
    O_NIS,
    O_NIS_CONFIGURED,
    O_NOISE_SCALE_SECOND,
    O_NOISE_SCALE_VY,
    O_S00,
    O_STATUS,
    O_UPDATE_F,
    O_UPDATE_R,
    StepStatus,
)
from transplanter_ident.epochs.epoch import Epoch, EpochArrays
from transplanter_ident.evaluation.model_errors import MODEL_ERRORS, Measure, measures_of, misalignment_note
from transplanter_ident.evaluation.validity_batch import (
    MIN_DRIFT_UPDATES,
    PREDICTED,
    USED,
    consistency_nis,
    decide_batch,
    steady_antenna_vy,
)

#: s of data between two evaluations of the window checks
RECHECK = 1.0
#: statuses of an epoch whose measurement the filter did not trust
DISTRUSTED = frozenset({StepStatus.GATED, StepStatus.REINITIALISED, StepStatus.REJECTED_INVALID,
                        StepStatus.REJECTED_STAMP, StepStatus.DIVERGED, StepStatus.RESTARTED})


@dataclass(frozen=True)
class Sample:
    """What the decision reads of one epoch."""

    t: float
    status: StepStatus
    cf: float
    cr: float
    cf_std: float
    cr_std: float
    steering: float
    yaw_rate: float
    speed: float
    antenna_lateral_velocity: float
    nis: float  # against the configured R (layout.O_NIS_CONFIGURED)
    nis_measured: float  # against R as the innovations show it (O_NIS; validity_batch.consistency_nis)
    noise_factors: tuple[float, float]  # on R (variance) as the innovations show it: velocity, heading (or r)
    whitened_vy: float  # e0 / sqrt(S00)
    rejected: int = 0  # input samples (and epochs) rejected since the previous epoch
    measures: tuple[Measure, ...] = ()  # the filter's measures of model errors left out (model_errors.MODEL_ERRORS)
    updates: tuple[float, float] = (0.0, 0.0)  # the normalised stiffness updates (O_UPDATE_F/R; 0: none)
    change: bool = False  # a surface-change alarm at this epoch (O_CHANGE): the drift test starts again
    change_evidence: float = 0.0  # the directional change test's CUSUM over its alarm level (O_CHANGE_EVIDENCE)


@dataclass(frozen=True)
class Decision:
    """Valid or not, and why (the failing checks, most severe first)."""

    valid: bool
    reasons: tuple[str, ...]
    hard: bool  # a plausibility or bound failure (an ERROR in /diagnostics)


class ValidityMonitor:
    """Feed every epoch in order with :meth:`step`; returns the decision for that epoch.

    The per-epoch checks (status, convergence, bounds) run every epoch; the window checks
    (excitation, consistency, plausibility) every RECHECK s of data, which keeps a replay linear in
    its length at any GNSS rate.
    """

    def __init__(self, settings: ValiditySettings, bounds: tuple[float, float], lever: float,
                 antenna_x: float = 0.0, rear_slip_gain: float = 0.0, course: bool = False,
                 setup: tuple[str, ...] = ()) -> None:
        self.settings = settings
        self.course = course  # ekf.measurement course: a course over ground is what the filter is told it measures
        self.setup = setup  # reasons the set-up alone gives (setup_reasons), in every epoch
        self.bounds = bounds
        self.lever = lever  # lr + antenna_x: how far behind the antenna the rear axle is
        self.antenna_x = antenna_x  # m, the antenna ahead of the CG: its vy holds antenna_x r besides the sideslip
        self.rear_slip_gain = rear_slip_gain  # kg m, m lf / (2 (lf + lr)): the rear axle's slip (steady_antenna_vy)
        self.reset()

    def reset(self) -> None:
        self._window: deque[Sample] = deque()
        self._updates: deque[tuple[float, float, float]] = deque()  # (t, update_f, update_r) of the drift test
        self._valid = False
        self._good_since: float | None = None
        self._bad_since: float | None = None
        self._checked_at = -math.inf
        self._window_hard: list[str] = []
        self._window_soft: list[str] = []
        self.last = Decision(False, ("no estimate yet",), False)

    def step(self, sample: Sample) -> Decision:
        """Add one epoch and decide."""
        if self._window and sample.t <= self._window[-1].t:
            self.reset()  # time went back (a replayed bag restarted)
        self._window.append(sample)
        while self._window[0].t < sample.t - self.settings.window:
            self._window.popleft()
        self._keep_updates(sample)
        if sample.t - self._checked_at >= RECHECK:
            self._checked_at = sample.t
            window = list(self._window)
            self._window_hard = self._plausibility(window)
            self._window_soft = self._suspect(window) + self._consistency(window) + self._drift()
        hard = self._bounds(sample) + self._window_hard
        soft = self._epoch_checks(sample) + self._window_soft + list(self.setup)
        self.last = self._hysteresis(sample.t, hard, soft)
        return self.last

    def _hysteresis(self, t: float, hard: list[str], soft: list[str]) -> Decision:
        s = self.settings
        if hard or soft:
            self._good_since = None
            self._bad_since = t if self._bad_since is None else self._bad_since
            if hard or t - self._bad_since >= s.hold_off:
                self._valid = False
        else:
            self._bad_since = None
            self._good_since = t if self._good_since is None else self._good_since
            if t - self._good_since >= s.hold_on:
                self._valid = True
        return Decision(self._valid, tuple(hard + soft), bool(hard))

    def _bounds(self, sample: Sample) -> list[str]:
        low, high = self.bounds
        return [f"{name} pinned at a stiffness bound ({value:.0f} N/rad): a wrong frame, lever arm or steering sign?"
                for name, value in (("Cf", sample.cf), ("Cr", sample.cr)) if value <= low * 1.01 or value >= high / 1.01]

    def _epoch_checks(self, sample: Sample) -> list[str]:
        reasons = []
        if sample.status not in PREDICTED:
            reasons.append(f"epoch status {sample.status.name}")
        relative = (sample.cf_std / sample.cf, sample.cr_std / sample.cr)
        worst = max(relative)
        if not worst <= self.settings.max_rel_std:
            reasons.append(f"not converged (relative 1-sigma {worst:.3f} > {self.settings.max_rel_std:g})")
        for error, measure in zip(MODEL_ERRORS, sample.measures, strict=False):  # a GNSS delay, a relaxation, a gain
            reason = error.reason(measure, relative, self.settings)
            if reason is not None:
                reasons.append(reason)
        if np.maximum(*sample.noise_factors) > self.settings.max_noise_factor:  # as validity_batch.noise_factor
            reasons.append("GNSS noisier than ekf.measurement_noise: the innovations show {:.2f} x its variance "
                           "(velocity), {:.2f} x (heading), beyond validity.max_noise_factor {:g}; set "
                           "ekf.measurement_noise, or tune it".format(*sample.noise_factors,
                                                                      self.settings.max_noise_factor)
                           + misalignment_note(sample.measures))
        if sample.change_evidence > self.settings.max_change_evidence:  # as validity_batch
            reasons.append(f"a stiffness change suspected: the directional change test stands at "
                           f"{100 * sample.change_evidence:.0f} % of its alarm level (the estimate may lag a new surface)")
        return reasons

    def _plausibility(self, window: list[Sample]) -> list[str]:
        reasons = []
        predicted = [w for w in window if w.status in PREDICTED and w.speed > 0.0]
        if len(predicted) >= 5:
            sideslip = sorted(abs(w.antenna_lateral_velocity - self.antenna_x * w.yaw_rate) / w.speed
                              for w in predicted)[len(predicted) // 2]  # at the CG
            if sideslip > self.settings.max_sideslip:
                reasons.append(f"implausible sideslip (median |vy/vx| {sideslip:.2f}): GNSS velocity and heading "
                               "disagree; check frames.velocity / frames.heading (ENU or NED)")
            elif _frames_mixed(predicted):
                reasons.append("the GNSS velocity turns against the heading (its direction changes at -r): "
                               "check frames.velocity / frames.heading (ENU or NED)")
            if not self.course and self._course_over_ground(predicted):
                reasons.append("the heading looks like a course over ground (vy stays ~0 while the vehicle "
                               "turns): use a dual-antenna heading, or ekf.measurement course for one antenna")
        return reasons

    def _course_over_ground(self, window: list[Sample]) -> bool:
        """Whether vy stays well below what a steady turn gives at the antenna, while the vehicle turns."""
        rms_r = math.sqrt(_ordered_sum(w.yaw_rate ** 2 for w in window) / len(window))
        rms_vy = math.sqrt(_ordered_sum(w.antenna_lateral_velocity ** 2 for w in window) / len(window))
        steady = _ordered_sum(steady_antenna_vy(self.lever, self.rear_slip_gain, w.speed, w.cr, w.yaw_rate) ** 2 for w in window)
        return rms_r > 0.05 and rms_vy < self.settings.course_ratio * math.sqrt(steady / len(window))

    def _suspect(self, window: list[Sample]) -> list[str]:
        suspect = sum(1 for w in window if w.rejected or w.status in DISTRUSTED)
        if suspect <= self.settings.max_suspect_fraction * len(window):
            return []
        rejected = sum(w.rejected for w in window)
        return [f"input suspect: {suspect} of the window's {len(window)} epochs follow a rejected sample or were "
                f"gated or rolled back ({rejected} samples rejected; see the input lines of /diagnostics)"]

    def _keep_updates(self, sample: Sample) -> None:
        if sample.change:
            self._updates.clear()
        if sample.updates != (0.0, 0.0):
            self._updates.append((sample.t, *sample.updates))
        while self._updates and self._updates[0][0] < sample.t - self.settings.drift_window:
            self._updates.popleft()

    def _drift(self) -> list[str]:
        n = len(self._updates)
        if self.settings.drift_window <= 0.0 or n < MIN_DRIFT_UPDATES:
            return []
        total_f = total_r = 0.0
        for _, update_f, update_r in self._updates:  # in order: validity_batch sums alike
            total_f += update_f
            total_r += update_r
        limit = self.settings.max_drift_sigmas * math.sqrt(n)
        return [f"{name} keeps moving {'up' if total > 0.0 else 'down'} (its last {n} updates sum to "
                f"{total / math.sqrt(n):+.1f} sqrt(n) of their std): the stiffness drifts faster than "
                "ekf.process_noise lets the estimate follow (a changing surface or load), so the band lags it"
                for name, total in (("Cf", total_f), ("Cr", total_r)) if abs(total) > limit]

    def _consistency(self, window: list[Sample]) -> list[str]:
        s = self.settings
        if len(window) < 5 or window[-1].t - window[0].t < 0.5 * s.window:
            return ["too little data in the window"]
        reasons = []
        nonlinear = sum(w.status is StepStatus.NONLINEAR for w in window) / len(window)
        if nonlinear > s.max_nonlinear_fraction:
            reasons.append(f"the tires left their linear range in {100 * nonlinear:.0f} % of the window: the "
                           "linear stiffness does not describe them")
        if _std([w.steering for w in window]) < s.min_steering_std and \
                _std([w.yaw_rate for w in window]) < s.min_yaw_rate_std:
            reasons.append("too little excitation (steering and yaw rate nearly constant)")
        nis = [float(consistency_nis(np.maximum(*w.noise_factors), w.nis_measured, w.nis, s.max_noise_factor))
               for w in window]
        used = [(w, x) for w, x in zip(window, nis, strict=True) if w.status in USED and math.isfinite(x)]
        if len(used) >= 5:
            total, dof = _ordered_sum(x for _, x in used), 2 * len(used)
            if total > dof + s.nis_quantile_sigmas * math.sqrt(2.0 * dof):
                reasons.append(f"innovations inconsistent with R and Q (mean NIS {total / len(used):.1f}, "
                               "expected 2)")
            rho = _lag1_autocorrelation([w.whitened_vy for w, _ in used])
            if rho > s.max_autocorrelation:
                reasons.append(f"innovations correlated in time (lag-1 {rho:.2f}): an unconfigured GNSS delay "
                               "(gnss.delay) or lever arm, or GNSS errors correlated in time (a receiver smoothing "
                               "its velocity or heading), which the filter takes as white?")
        return reasons


def _frames_mixed(window: list[Sample]) -> bool:
    """Whether the antenna's sideslip turns at about -2 r, so that the course changes at -r.

    That is what swapped east and north (or a reversed heading sense) look like; right frames give a
    slope near 0.
    """
    num = den = 0.0
    for a, b in zip(window, window[1:], strict=False):
        dt = b.t - a.t
        if dt <= 0.0:
            continue
        beta_a = math.atan2(a.antenna_lateral_velocity, a.speed)
        beta_b = math.atan2(b.antenna_lateral_velocity, b.speed)
        rate = math.remainder(beta_b - beta_a, 2.0 * math.pi) / dt
        num += rate * b.yaw_rate
        den += b.yaw_rate * b.yaw_rate
    return den > 0.05 ** 2 * len(window) and num / den < -1.0


def _ordered_sum(values: Iterable[float]) -> float:
    """0.0 plus each value in order, as validity_batch's loops add (Python 3.12's ``sum`` compensates)."""
    return functools.reduce(operator.add, values, 0.0)


def _std(values: list[float]) -> float:
    mean = _ordered_sum(values) / len(values)
    return math.sqrt(_ordered_sum((v - mean) * (v - mean) for v in values) / len(values))  # a product, as validity_batch


def _lag1_autocorrelation(values: list[float]) -> float:
    mean = _ordered_sum(values) / len(values)
    centred = [v - mean for v in values]
    power = _ordered_sum(c * c for c in centred)
    if power <= 0.0:
        return 0.0
    return _ordered_sum(a * b for a, b in zip(centred, centred[1:], strict=False)) / power


def sample_of(epoch: Epoch, row: np.ndarray, rejected: int = 0) -> Sample:
    """The decision's view of one epoch, its kernel output row (layout.O_*) and the samples rejected before it."""
    s00 = row[O_S00]
    return Sample(t=epoch.t, status=StepStatus(int(row[O_STATUS])), cf=float(row[O_CF]), cr=float(row[O_CR]),
                  cf_std=float(row[O_CF_STD]), cr_std=float(row[O_CR_STD]), steering=epoch.steering,
                  yaw_rate=epoch.yaw_rate, speed=epoch.speed,
                  antenna_lateral_velocity=float(epoch.antenna_lateral_velocity), nis=float(row[O_NIS_CONFIGURED]),
                  nis_measured=float(row[O_NIS]),
                  noise_factors=(float(row[O_NOISE_SCALE_VY]), float(row[O_NOISE_SCALE_SECOND])),
                  whitened_vy=float(row[O_E0]) / math.sqrt(s00) if s00 > 0.0 else 0.0, rejected=int(rejected),
                  measures=measures_of(row), updates=(float(row[O_UPDATE_F]), float(row[O_UPDATE_R])),
                  change=bool(row[O_CHANGE] > 0.0), change_evidence=float(row[O_CHANGE_EVIDENCE]))


def monitor_for(config: EstimatorConfig, settings: ValiditySettings) -> ValidityMonitor:
    """A monitor with the filter's stiffness bounds, the lever arm of the rear axle to the antenna and its slip."""
    vehicle = config.vehicle
    rear_slip_gain = vehicle.mass * vehicle.lf / (2.0 * (vehicle.lf + vehicle.lr))
    return ValidityMonitor(settings, config.options.stiffness_bounds, vehicle.lr + vehicle.antenna_x, vehicle.antenna_x,
                           rear_slip_gain, config.options.course, setup_reasons(config))


def setup_reasons(config: EstimatorConfig) -> tuple[str, ...]:
    """What the set-up alone rules out: a single antenna's course cannot show a GNSS timing error."""
    if config.options.course and not config.options.delay_uncertainty > 0.0:
        return ("one antenna's course cannot show a GNSS timing error, which moves the stiffness ~1.3 % per ms: set "
                "gnss.delay, and ekf.delay_uncertainty to its 1-sigma (s)",)
    return ()


def decide_sequence(config: EstimatorConfig, settings: ValiditySettings, epochs: EpochArrays,
                    outputs: np.ndarray, rejected: Sequence[int] | None = None) -> np.ndarray:
    """The validity of every epoch of an offline run (replay), as the node decides it online.

    ``rejected``: per epoch, the input samples rejected since the previous one (bags.BagData.rejected).
    Computed at once (:mod:`.validity_batch`, the same decisions) unless the times do not strictly increase.
    """
    monitor = monitor_for(config, settings)
    counts = rejected if rejected is not None else [0] * len(epochs)
    valid = decide_batch(settings, monitor.bounds, monitor.lever, RECHECK, epochs, outputs, counts, DISTRUSTED,
                         monitor.antenna_x, monitor.rear_slip_gain, monitor.course, bool(monitor.setup))
    if valid is not None:
        return valid
    return np.array([monitor.step(sample_of(epochs[i], outputs[i], counts[i])).valid for i in range(len(epochs))],
                    dtype=bool)
