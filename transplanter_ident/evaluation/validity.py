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
for ``hold_off`` s (at once for the plausibility and bound checks; :mod:`.hysteresis`). The window checks run every
RECHECK s of data (the same epochs online and offline), with the kernels of :mod:`.window_checks`
that the batch decision (:mod:`.validity_batch`) runs too; this module words their verdicts.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
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
from transplanter_ident.evaluation.epoch_checks import (
    change_suspected,
    consistency_nis,
    noisier,
    pinned,
    relative_stds,
    unconverged,
)
from transplanter_ident.evaluation.hysteresis import hysteresis_step, initial_state
from transplanter_ident.evaluation.model_errors import MODEL_ERRORS, Measure, measures_of, misalignment_note
from transplanter_ident.evaluation.validity_batch import decide_batch
from transplanter_ident.evaluation.window_checks import (
    PREDICTED,
    WindowColumns,
    drift_checks,
    plausibility_checks,
    soft_checks,
    window_columns,
    window_limits,
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
    nis_measured: float  # against R as the innovations show it (O_NIS; epoch_checks.consistency_nis)
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
        self._hysteresis_state = initial_state()
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
            self._window_hard, self._window_soft = self._window_checks(list(self._window))
        hard = self._bounds(sample) + self._window_hard
        soft = self._epoch_checks(sample) + self._window_soft + list(self.setup)
        self.last = self._hysteresis(sample.t, hard, soft)
        return self.last

    def _hysteresis(self, t: float, hard: list[str], soft: list[str]) -> Decision:
        s = self.settings
        valid = hysteresis_step(self._hysteresis_state, float(t), bool(hard), bool(hard or soft), float(s.hold_on),
                                float(s.hold_off))
        return Decision(valid, tuple(hard + soft), bool(hard))

    def _bounds(self, sample: Sample) -> list[str]:
        return [f"{name} pinned at a stiffness bound ({value:.0f} N/rad): a wrong frame, lever arm or steering sign?"
                for name, value in (("Cf", sample.cf), ("Cr", sample.cr)) if pinned(value, self.bounds)]

    def _epoch_checks(self, sample: Sample) -> list[str]:
        reasons = []
        if sample.status not in PREDICTED:
            reasons.append(f"epoch status {sample.status.name}")
        front, rear, worst = relative_stds(sample.cf, sample.cr, sample.cf_std, sample.cr_std)
        relative = (front, rear)
        if unconverged(worst, self.settings):
            reasons.append(f"not converged (relative 1-sigma {float(worst):.3f} > {self.settings.max_rel_std:g})")
        for error, measure in zip(MODEL_ERRORS, sample.measures, strict=False):  # a GNSS delay, a relaxation, a gain
            reason = error.reason(measure, relative, self.settings)
            if reason is not None:
                reasons.append(reason)
        if noisier(*sample.noise_factors, self.settings):
            reasons.append("GNSS noisier than ekf.measurement_noise: the innovations show {:.2f} x its variance "
                           "(velocity), {:.2f} x (heading), beyond validity.max_noise_factor {:g}; set "
                           "ekf.measurement_noise, or tune it".format(*sample.noise_factors,
                                                                      self.settings.max_noise_factor)
                           + misalignment_note(sample.measures))
        if change_suspected(sample.change_evidence, self.settings):
            reasons.append(f"a stiffness change suspected: the directional change test stands at "
                           f"{100 * sample.change_evidence:.0f} % of its alarm level (the estimate may lag a new surface)")
        return reasons

    def _window_checks(self, window: list[Sample]) -> tuple[list[str], list[str]]:
        """(hard, soft) reasons of the window checks (window_checks.py: the batch's kernels, on this window)."""
        limits = window_limits(self.settings, RECHECK, self.course)
        c = self._columns(window)
        hard = _plausibility_reasons(*plausibility_checks(0, len(c.plaus), c.sideslip, c.rate, c.yaw_rate, c.plaus,
                                                          c.r_sq, c.vy_sq, c.steady_sq, limits))
        soft = _soft_reasons(*soft_checks(0, len(window) - 1, 0, len(c.consist), c.t, c.nonlinear, c.steering,
                                          c.yaw_rate, c.suspect, c.nis, c.whitened, limits),
                             window=len(window), rejected=sum(w.rejected for w in window))
        updates = np.array([(f, r) for _, f, r in self._updates], dtype=np.float64).reshape(-1, 2)
        return hard, soft + _drift_reasons(*drift_checks(0, len(updates) - 1, updates, limits))

    def _columns(self, window: list[Sample]) -> WindowColumns:
        """The window checks' terms of the window, as validity_batch builds them of a whole replay."""
        t, speed, vy, yaw_rate, steering, cr, nis_measured, nis, whitened, factor_vy, factor_second = np.array(
            [(w.t, w.speed, w.antenna_lateral_velocity, w.yaw_rate, w.steering, w.cr, w.nis_measured, w.nis,
              w.whitened_vy, *w.noise_factors) for w in window], dtype=np.float64).reshape(-1, 11).T.copy()
        status = np.array([int(w.status) for w in window], dtype=np.int64)
        suspect = np.array([w.rejected != 0 or w.status in DISTRUSTED for w in window], dtype=np.bool_)
        return window_columns(t, status, speed, vy, yaw_rate, steering, cr,
                              consistency_nis(factor_vy, factor_second, nis_measured, nis, self.settings),
                              whitened, suspect, (self.lever, self.rear_slip_gain, self.antenna_x))

    def _keep_updates(self, sample: Sample) -> None:
        if sample.change:
            self._updates.clear()
        if sample.updates != (0.0, 0.0):
            self._updates.append((sample.t, *sample.updates))
        while self._updates and self._updates[0][0] < sample.t - self.settings.drift_window:
            self._updates.popleft()


def _plausibility_reasons(median: float, too_large: bool, mixed: bool, course: bool) -> list[str]:
    """The words of window_checks.plausibility_checks' verdicts."""
    reasons = []
    if too_large:
        reasons.append(f"implausible sideslip (median |vy/vx| {median:.2f}): GNSS velocity and heading "
                       "disagree; check frames.velocity / frames.heading (ENU or NED)")
    if mixed:
        reasons.append("the GNSS velocity turns against the heading (its direction changes at -r): "
                       "check frames.velocity / frames.heading (ENU or NED)")
    if course:
        reasons.append("the heading looks like a course over ground (vy stays ~0 while the vehicle "
                       "turns): use a dual-antenna heading, or ekf.measurement course for one antenna")
    return reasons


def _soft_reasons(suspects: int, suspect_fails: bool, too_little: bool, nonlinear: float, too_nonlinear: bool,  # noqa: PLR0913
                  unexcited: bool, mean_nis: float, nis_fails: bool, rho: float, rho_fails: bool, *, window: int,
                  rejected: int) -> list[str]:
    """The words of window_checks.soft_checks' verdicts (``window`` epochs, ``rejected`` samples rejected)."""
    reasons = []
    if suspect_fails:
        reasons.append(f"input suspect: {suspects} of the window's {window} epochs follow a rejected sample or were "
                       f"gated or rolled back ({rejected} samples rejected; see the input lines of /diagnostics)")
    if too_little:
        return [*reasons, "too little data in the window"]
    if too_nonlinear:
        reasons.append(f"the tires left their linear range in {100 * nonlinear:.0f} % of the window: the "
                       "linear stiffness does not describe them")
    if unexcited:
        reasons.append("too little excitation (steering and yaw rate nearly constant)")
    if nis_fails:
        reasons.append(f"innovations inconsistent with R and Q (mean NIS {mean_nis:.1f}, expected 2)")
    if rho_fails:
        reasons.append(f"innovations correlated in time (lag-1 {rho:.2f}): an unconfigured GNSS delay "
                       "(gnss.delay) or lever arm, or GNSS errors correlated in time (a receiver smoothing "
                       "its velocity or heading), which the filter takes as white?")
    return reasons


def _drift_reasons(count: int, total_f: float, total_r: float, drift_f: bool, drift_r: bool) -> list[str]:
    """The words of window_checks.drift_checks' verdicts."""
    root = math.sqrt(count)
    return [f"{name} keeps moving {'up' if total > 0.0 else 'down'} (its last {count} updates sum to "
            f"{total / root:+.1f} sqrt(n) of their std): the stiffness drifts faster than "
            "ekf.process_noise lets the estimate follow (a changing surface or load), so the band lags it"
            for name, total, fails in (("Cf", total_f, drift_f), ("Cr", total_r, drift_r)) if fails]


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


def warm_up(config: EstimatorConfig, settings: ValiditySettings) -> None:
    """Run the window checks once (load or compile their kernels): the node's first check then waits for none."""
    monitor_for(config, settings).step(Sample(
        t=0.0, status=StepStatus.UPDATED, cf=1.0e4, cr=1.0e4, cf_std=1.0, cr_std=1.0,
        steering=0.0, yaw_rate=0.0, speed=1.0, antenna_lateral_velocity=0.0, nis=2.0, nis_measured=2.0,
        noise_factors=(1.0, 1.0), whitened_vy=0.0))


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
