"""Re-linearisation at the start: the first epochs filtered again from the stiffness they led to.

The EKF (paper eqs. 9-14) linearises each step at the estimate it holds. Started at the
configured stiffness (1000 N/rad, the paper's, ~8x below a real tire), its first steps are
linearised far from the truth, and with the steering offset as a state their information
narrows the covariance along directions the wrong Jacobians chose: on gentle steering the
estimate then creeps towards the truth for minutes (±5° sine at 2 m/s, noise-free: Cf -11 % at
30 s, -6 % at 60 s; with a 1° offset -31 % and -20 %) while its band says ~5 %.

So during the first ``ekf.relinearization_window`` s of stiffness updates, every
:data:`CHECK_PERIOD` s of them, when Cf or Cr has moved more than
``ekf.relinearization_threshold`` (relative, |Δ ln C|) and :data:`MOVE_SIGMAS` std from where the
filter's pass started, a new pass is tried: the configured state and covariance with the
parameter states (θf, θr, b) held now, over the epochs since the start, the prior of θf, θr no
wider than :data:`PRIOR_SIGMAS` of their std now (a trust region: with P0's std of 2 in ln C, the
first seconds of a drive that starts straight threw Cf from the truth to a 14th of it in 2 s, and a
new pass from anywhere went the same way; field work, 52 s: Cf 41 % low at 8 std, the maximum
likelihood 3 % low, with ekf.change_scale 4). It replaces the pass in
force only if its innovations make those epochs more likely (the mean Gaussian NLL of the
innovations, the tuner's objective, :func:`epoch_nll`): a Gauss-Newton step of the
whole start-up, as an iterated EKF takes for one update, kept only when it is a step downhill.
The outputs already published stay; the state goes on from the pass in force. Window 0: the
filter of the paper (one pass).

:class:`RelinearizationSchedule` decides (:meth:`~RelinearizationSchedule.step`, after each
epoch); :func:`run_relinearized` is the offline run and
:class:`~transplanter_ident.ekf.joint_ekf.JointEKF` the node's, so online and offline outputs are
identical. The tuner's objective runs one pass (its kernel).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from transplanter_ident.ekf.layout import (
    DIVERGENCE_PENALTY,
    M_CORRELATION_LAG,
    M_CORRELATION_SPAN,
    M_NOISE_SETTLED,
    M_NOISE_VY,
    N_MEMO,
    N_MODEL,
    N_OUTPUTS,
    O_DT,
    O_NIS,
    O_S00,
    O_S01,
    O_S11,
    O_STATUS,
    PARAMETER_STATES,
    X_THETA_F,
    X_THETA_R,
    StepStatus,
)

#: s of stiffness updates between two checks
CHECK_PERIOD = 5.0
CHECK_PERIOD_US = round(CHECK_PERIOD * 1e6)
#: a move smaller than this many of the current std tries no new pass (it is the data's noise)
MOVE_SIGMAS = 3.0
#: a new pass's prior of θf, θr: centred where the pass in force is, at most this many of its std wide
PRIOR_SIGMAS = 5.0
#: the memo slots of the noise the innovations show (adaptation.learn_noise_scales), and whether it was restarted
#: once the model was near (noise_correlation.restart_noise_when_near)
SENSOR_NOISE = slice(M_NOISE_VY, M_NOISE_SETTLED + 1)
#: ... and of their correlation in time (noise_correlation.learn_noise_correlation), not the last pair
NOISE_CORRELATION = slice(M_CORRELATION_LAG, M_CORRELATION_SPAN + 1)
#: epochs kept for a new pass at most (a start-up spent standing still ends the window)
MAX_BUFFER = 20000

#: the compiled filter over rows from (x, p, model, memo), in place, into output rows (entries.run_kernel)
Run = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray], None]
#: the statuses whose innovation the NLL counts, and those that make a pass score DIVERGENCE_PENALTY
COUNTED = (StepStatus.UPDATED, StepStatus.GATED, StepStatus.NONLINEAR)
FAILED = (StepStatus.DIVERGED, StepStatus.RESTARTED)


def epoch_nll(outputs: np.ndarray) -> np.ndarray:
    """Per output row: its innovation's Gaussian NLL (objective NLL); NaN if not counted, inf if it fails the pass.

    What ``sequence.objective_n`` sums (test_relinearization checks the two agree).
    """
    outputs = np.atleast_2d(outputs)
    status = outputs[:, O_STATUS].astype(int)
    det = outputs[:, O_S00] * outputs[:, O_S11] - outputs[:, O_S01] ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        value = 0.5 * (outputs[:, O_NIS] + np.log(np.where(det > 0.0, det, 1.0))) + math.log(2.0 * math.pi)
    value = np.where(np.isin(status, COUNTED), np.where(det > 0.0, value, math.inf), math.nan)
    return np.where(np.isin(status, FAILED), math.inf, value)


def mean_nll(values: np.ndarray) -> float:
    """The pass's objective from its epochs' :func:`epoch_nll`: their mean, DIVERGENCE_PENALTY at most."""
    counted = values[~np.isnan(values)]
    if len(counted) == 0:
        return DIVERGENCE_PENALTY
    mean = float(np.mean(counted))
    return min(mean, DIVERGENCE_PENALTY) if math.isfinite(mean) else DIVERGENCE_PENALTY


def log_stiffness(state: np.ndarray, log_state: bool) -> tuple[float, float]:
    """(ln Cf, ln Cr) of a state vector (θ is ln C in log mode, C in linear mode)."""
    front, rear = float(state[X_THETA_F]), float(state[X_THETA_R])
    if log_state:
        return front, rear
    return (math.log(front) if front > 0.0 else -math.inf), (math.log(rear) if rear > 0.0 else -math.inf)


@dataclass
class FilterState:
    """Everything the compiled step carries from one epoch to the next."""

    x: np.ndarray
    p: np.ndarray
    model: np.ndarray = field(default_factory=lambda: np.zeros(N_MODEL))
    memo: np.ndarray = field(default_factory=lambda: np.zeros(N_MEMO))

    @classmethod
    def start(cls, x0: np.ndarray, p0: np.ndarray) -> FilterState:
        """A filter's start at (x0, P0) (copies)."""
        return cls(x0.copy(), p0.copy())


@dataclass
class RelinearizationSchedule:
    """When to try a new pass, and where the pass in force started.

    ``window`` s of stiffness updates (0: never), ``threshold`` relative move of Cf or Cr.
    """

    window: float
    threshold: float
    log_state: bool
    origin: np.ndarray  # the state vector the pass in force started from
    progress: int = 0  # us of epochs that updated the stiffness, since the filter's start (whole us: the
    next_check: int = CHECK_PERIOD_US  # node's stamps differ from replay's by ~1e-9 s, and must check alike)
    passes: int = 1  # passes tried, the first included
    kept: int = 0  # new passes that replaced the one in force
    in_force: list[np.ndarray] = field(default_factory=list)  # output rows of the pass in force (scored at checks)

    def close(self) -> None:
        """No new pass from now on (a restored learned state)."""
        self.window = 0.0
        self.in_force = []

    @property
    def open(self) -> bool:
        """Whether a new pass may still start."""
        return self.window > 0.0 and self.progress <= self.window * 1e6

    def due(self, out: np.ndarray, buffered: int) -> bool:
        """Count one epoch's output row; True at a check (every CHECK_PERIOD s of stiffness updates)."""
        if not self.open:
            return False
        if buffered > MAX_BUFFER:
            self.close()  # too long a start-up to keep: the filter goes on in one pass
            return False
        if int(out[O_STATUS]) == StepStatus.UPDATED and math.isfinite(out[O_DT]):
            self.progress += round(float(out[O_DT]) * 1e6)
        if self.progress < self.next_check or not self.open:
            return False
        self.next_check = (self.progress // CHECK_PERIOD_US + 1) * CHECK_PERIOD_US
        return True

    def moved(self, state: FilterState) -> bool:
        """Whether Cf or Cr is more than ``threshold`` and MOVE_SIGMAS std from the pass's origin."""
        now = log_stiffness(state.x, self.log_state)
        origin = log_stiffness(self.origin, self.log_state)
        for k, index in enumerate((X_THETA_F, X_THETA_R)):
            variance = float(state.p[index, index])
            std = math.sqrt(variance) if variance > 0.0 else 0.0
            if not self.log_state:
                std = std / float(state.x[index]) if state.x[index] > 0.0 else math.inf
            move = abs(now[k] - origin[k])
            if math.isfinite(move) and move > self.threshold and move > MOVE_SIGMAS * std:
                return True
        return False

    def step(self, rows: np.ndarray | Sequence[np.ndarray], out: np.ndarray, state: FilterState, x0: np.ndarray,
             p0: np.ndarray, run: Run) -> FilterState:
        """After the epoch ``rows[-1]`` (its output ``out``): the state to go on from.

        ``rows`` are the epochs since the start (a table, or the node's list of rows); (x0, P0) the
        configured start. At a check, when the estimate has moved, the pass from (x0 with ``state``'s
        parameter states, P0 with the variances of θf, θr at most PRIOR_SIGMAS² times ``state``'s) is
        run over ``rows``; it is returned if its mean NLL is below that of
        the pass in force over the same epochs.
        """
        if not self.open:
            self.in_force = []  # the window is over: nothing to score any more
            return state
        self.in_force.append(out.copy())  # scored only at a check: the node's epochs stay cheap
        if not (self.due(out, len(rows)) and self.moved(state)):
            return state
        rows = np.asarray(rows)  # the node's list of rows becomes a table only here
        self.passes += 1
        candidate = FilterState.start(x0, p0)
        candidate.x[PARAMETER_STATES] = state.x[PARAMETER_STATES]
        for index in (X_THETA_F, X_THETA_R):
            candidate.p[index, index] = min(p0[index, index], PRIOR_SIGMAS ** 2 * state.p[index, index])
        # the sensors' noise as measured so far describes the sensors, not the linearisation: kept
        candidate.memo[SENSOR_NOISE] = state.memo[SENSOR_NOISE]
        candidate.memo[NOISE_CORRELATION] = state.memo[NOISE_CORRELATION]
        origin = candidate.x.copy()
        outputs = np.zeros((len(rows), N_OUTPUTS))
        run(rows, candidate.x, candidate.p, candidate.model, candidate.memo, outputs)
        if not mean_nll(epoch_nll(outputs)) < mean_nll(epoch_nll(np.array(self.in_force))):
            return state
        self.origin, self.in_force = origin, list(outputs)
        self.kept += 1
        return candidate


def schedule_for(window: float, threshold: float, log_state: bool, x0: np.ndarray) -> RelinearizationSchedule:
    """The schedule of a filter that starts at ``x0``."""
    return RelinearizationSchedule(window, threshold, log_state, x0.copy())


def run_relinearized(rows: np.ndarray, x0: np.ndarray, p0: np.ndarray, schedule: RelinearizationSchedule,
                     run: Run, outputs: np.ndarray) -> None:
    """The filter over ``rows`` (N, N_EPOCH_COLUMNS) into ``outputs`` (N, N_OUTPUTS), with new passes.

    ``run(rows, x, p, model, memo, outputs)`` runs the compiled filter in place (``entries.run_kernel``
    with the vehicle, settings, Q and R bound). Epoch by epoch while the window is open, as the
    node; the rest in one call.
    """
    state = FilterState.start(x0, p0)
    taken = 0
    while taken < len(rows) and schedule.open:
        run(rows[taken:taken + 1], state.x, state.p, state.model, state.memo, outputs[taken:taken + 1])
        taken += 1
        state = schedule.step(rows[:taken], outputs[taken - 1], state, x0, p0, run)
    if taken < len(rows):
        run(rows[taken:], state.x, state.p, state.model, state.memo, outputs[taken:])
