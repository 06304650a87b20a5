"""What the recent data pin: the published band of (ln Cf, ln Cr) along directions they do not (issues #10, #11).

The EKF's covariance can narrow along a direction the data hardly inform: on the paper's slow
held step (1 m/s) Cf moves the yaw rate only through the understeer term, the linearisation
points wander, and the band ends far from the truth. So every ``ekf.identifiability_period`` of
data the Fisher information of the recent epochs (the last ``ekf.identifiability_memory`` s, at
most ``ekf.identifiability_max_epochs``) is summed at the current estimate
(:func:`.information.output_error_information`), the steering offset and gain error taken as nuisances
where the filter estimates them (n: those of b, g):

    J = I_ss - I_sn I_nn^-1 I_ns          (2 x 2, ln Cf and ln Cr; I_ss alone without either state)

It is evaluated only at epochs whose wheel angle is at least ``ekf.identifiability_min_steering``
(on a straight the data add next to no information, so the last bound is held), and only every
``RELAXED_PERIODS`` periods while J pins every direction with a wide margin. Along each
eigenvector v of J whose Cramér-Rao 1-sigma 1 / sqrt(lambda) exceeds ``ekf.max_identifiable_rel_std``,
the published covariance is at least the initial one:

    P_pub = P + sum_v max(0, v^T P0 v - v^T P v) v v^T

so the band says "the recent data do not tell" instead of a narrow, wrong number. The bound is
evaluated at one estimate over the whole window: summing information at the estimates the
filter held along the way overstates it about tenfold on the slow step, which is the EKF's own
inconsistency. The filter's state and covariance are untouched; only the published std and
correlation change, online (:meth:`IdentifiabilityGuard.step`) and offline
(:meth:`IdentifiabilityGuard.run`) alike.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions
from transplanter_ident.ekf.information import output_error_information
from transplanter_ident.ekf.layout import (
    E_STEERING,
    E_T,
    EULER,
    EXACT,
    I_GAIN,
    I_OFFSET,
    N_INFORMATION,
    O_CF,
    O_CF_STD,
    O_CORRELATION,
    O_CR,
    O_CR_STD,
    O_NOISE_CORRELATION_SECOND,
    O_NOISE_CORRELATION_VY,
    O_NOISE_SCALE_SECOND,
    O_NOISE_SCALE_VY,
    O_OFFSET,
    O_STATUS,
    O_STEERING_GAIN,
    X_THETA_F,
    X_THETA_R,
    StepStatus,
)
from transplanter_ident.ekf.model import vehicle_array, work_buffer
from transplanter_ident.ekf.noise_correlation import widening

#: s: the open-loop model restarts from the measured state this often (multiple shooting)
SEGMENT = 10.0
#: while the recent data pin every direction this many times tighter than the limit, the bound is
#: re-evaluated RELAXED_PERIODS periods later instead of one (it costs ~2 us per epoch of the window)
RELAXED_MARGIN = 4.0
RELAXED_PERIODS = 10
#: statuses whose epoch the filter did not take: they add no information and publish nothing
SKIPPED = frozenset({StepStatus.REJECTED_INVALID, StepStatus.REJECTED_STAMP, StepStatus.DIVERGED})
_SKIPPED_CODES = np.array(sorted(int(status) for status in SKIPPED), dtype=np.float64)  # as O_STATUS holds them


def window_information(config: EstimatorConfig, rows: np.ndarray, theta: np.ndarray, segment: float = SEGMENT,
                       noise_factors: tuple[float, float] = (1.0, 1.0)) -> tuple[np.ndarray, int]:
    """(4, 4) Fisher information of (ln Cf, ln Cr, b, g) of the epochs ``rows`` at ``theta``, and the epochs used.

    ``noise_factors``: what the filter's R is above the configured one (layout.O_NOISE_SCALE_* times the
    widening of O_NOISE_CORRELATION_*), so the information is that of the measurements as noisy, and as
    correlated in time, as the innovations show them.
    """
    options = config.options
    information = np.zeros((N_INFORMATION, N_INFORMATION))
    r_noise = np.array(config.noise.measurement_noise, dtype=np.float64) * np.maximum(noise_factors, 1.0)
    used = output_error_information(np.ascontiguousarray(rows), np.asarray(theta, dtype=np.float64),
                                    vehicle_array(config.vehicle, options.course), config.vehicle.antenna_x, r_noise, segment,
                                    options.min_speed, options.max_interval,
                                    EXACT if options.discretization == "exact" else EULER,
                                    options.measurement_noise_from_covariance, work_buffer(), information)
    return information, int(used)


def nuisances(options: FilterOptions) -> tuple[int, ...]:
    """The information's indices (layout.I_*) of the filter's estimated nuisance parameters: b, g."""
    return tuple(index for index, estimated in ((I_OFFSET, options.estimate_steering_offset),
                                                (I_GAIN, options.estimate_steering_gain)) if estimated)


def stiffness_information(information: np.ndarray, nuisance: tuple[int, ...]) -> np.ndarray:
    """(2, 2) information of (ln Cf, ln Cr) from (4, 4), the ``nuisance`` parameters (:func:`nuisances`) taken out.

    A nuisance the data do not inform at all (zero information) adds nothing to take out.
    """
    if not np.all(np.isfinite(information)):  # bad input reached the sum: nothing is known
        return np.full((I_OFFSET, I_OFFSET), np.nan)
    stiffness = information[:I_OFFSET, :I_OFFSET].copy()
    informed = [k for k in nuisance if information[k, k] > 0.0]
    if informed:
        cross = information[:I_OFFSET, informed]
        stiffness -= cross @ np.linalg.pinv(information[np.ix_(informed, informed)]) @ cross.T
    return 0.5 * (stiffness + stiffness.T)


def weak_directions(information: np.ndarray, nuisance: tuple[int, ...], limit: float) -> np.ndarray:
    """(k, 2) unit vectors in (ln Cf, ln Cr) whose Cramér-Rao 1-sigma exceeds ``limit`` (k = 0, 1 or 2)."""
    pinned = stiffness_information(information, nuisance)
    if not np.all(np.isfinite(pinned)):
        return np.eye(2)
    values, vectors = np.linalg.eigh(pinned)
    return vectors[:, values < 1.0 / (limit * limit)].T.copy()


def published_covariance(covariance: np.ndarray, weak: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """(n, 2, 2): ``covariance`` (n, 2, 2) raised to ``prior`` (2, 2) along each of the ``weak`` directions."""
    published = covariance.copy()
    for v in weak:
        own = v[0] * v[0] * covariance[:, 0, 0] + 2.0 * v[0] * v[1] * covariance[:, 0, 1] + v[1] * v[1] * covariance[:, 1, 1]
        target = v[0] * v[0] * prior[0, 0] + 2.0 * v[0] * v[1] * prior[0, 1] + v[1] * v[1] * prior[1, 1]
        add = np.maximum(target - own, 0.0)
        published[:, 0, 0] += add * v[0] * v[0]
        published[:, 0, 1] += add * v[0] * v[1]
        published[:, 1, 0] += add * v[0] * v[1]
        published[:, 1, 1] += add * v[1] * v[1]
    return published


class IdentifiabilityGuard:
    """The recent epochs, the bound they give, and the band published from them (see the module docstring)."""

    def __init__(self, config: EstimatorConfig, initial_state: np.ndarray, initial_covariance: np.ndarray,
                 log_state: bool) -> None:
        options = config.options
        self.enabled = options.identifiability_check and options.heading_state
        self._config = config
        self._prior = _relative_prior(initial_state, initial_covariance, log_state)
        self.reset()

    def reset(self) -> None:
        """Forget the recent epochs (a filter reset): until the next evaluation every direction is weak."""
        self._rows: deque[np.ndarray] = deque(maxlen=self._config.options.identifiability_max_epochs)
        self._next = -math.inf
        self.information = np.zeros((N_INFORMATION, N_INFORMATION))  # at the last evaluation
        self._weak = np.eye(2)

    def trust_restored(self) -> None:
        """A learned state was restored (persistence): its own, inflated covariance stands until the next bound."""
        self._weak = np.zeros((0, 2))

    def set_config(self, config: EstimatorConfig) -> None:
        """New R (run time): used from the next evaluation."""
        self._config = config

    def step(self, row: np.ndarray, out: np.ndarray) -> None:
        """One epoch (kernel input row, its output row): the node's path; ``out`` is published in place."""
        if not self.enabled or not _taken(out[None, :])[0]:
            return
        options = self._config.options
        t = float(row[E_T])
        self._rows.append(np.array(row, dtype=np.float64))
        while self._rows[0][E_T] < t - options.identifiability_memory:
            self._rows.popleft()
        if t >= self._next and _turning(row[None, :], out[None, :], options.identifiability_min_steering)[0]:
            self._evaluate(np.array(self._rows), out, t)
        out[:] = _published(out[None, :], self._weak, self._prior)[0]

    def run(self, rows: np.ndarray, outputs: np.ndarray) -> None:
        """A whole sequence (kernel input, output rows): replay's path, the same numbers as :meth:`step`."""
        if not self.enabled or len(rows) == 0:
            return
        options = self._config.options
        taken = np.nonzero(_taken(outputs))[0]
        times = rows[taken, E_T]
        turning = _turning(rows[taken], outputs[taken], options.identifiability_min_steering)
        start = 0
        for position in np.nonzero(turning)[0]:  # the bound is (re-)evaluated only at turning epochs
            if times[position] < self._next:
                continue
            low = max(int(np.searchsorted(times, times[position] - options.identifiability_memory, "left")),
                      position + 1 - options.identifiability_max_epochs)
            if position > start:  # publish the epochs since the last evaluation with its directions
                outputs[taken[start:position]] = _published(outputs[taken[start:position]], self._weak, self._prior)
            self._evaluate(rows[taken[low:position + 1]], outputs[taken[position]], float(times[position]))
            start = position
        outputs[taken[start:]] = _published(outputs[taken[start:]], self._weak, self._prior)

    def _evaluate(self, rows: np.ndarray, out: np.ndarray, t: float) -> None:
        options = self._config.options
        theta = np.array([math.log(out[O_CF]), math.log(out[O_CR]), out[O_OFFSET], out[O_STEERING_GAIN]])
        widen = getattr(widening, "py_func", widening)  # the kernel's formula in Python: nothing to compile
        factors = (float(out[O_NOISE_SCALE_VY] * widen(out[O_NOISE_CORRELATION_VY])),
                   float(out[O_NOISE_SCALE_SECOND] * widen(out[O_NOISE_CORRELATION_SECOND])))
        self.information, _ = window_information(self._config, rows, theta, noise_factors=factors)
        limit = options.max_identifiable_rel_std
        self._weak = weak_directions(self.information, nuisances(options), limit)
        firm = len(weak_directions(self.information, nuisances(options), limit / RELAXED_MARGIN)) == 0
        self._next = t + options.identifiability_period * (RELAXED_PERIODS if firm else 1)


def _turning(rows: np.ndarray, outputs: np.ndarray, min_steering: float) -> np.ndarray:
    """Per epoch: whether it can inform the stiffness, the wheels turned (straight driving adds ~nothing)."""
    return np.abs(rows[:, E_STEERING] - outputs[:, O_OFFSET]) >= min_steering


def _taken(outputs: np.ndarray) -> np.ndarray:
    """Per output row: whether the filter took its epoch (and it has a stiffness)."""
    skipped = (outputs[:, O_STATUS, None] == _SKIPPED_CODES).any(axis=1)  # np.isin costs the node ~40 us an epoch
    return ~skipped & (outputs[:, O_CF] > 0.0) & (outputs[:, O_CR] > 0.0)


def _published(rows: np.ndarray, weak: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Output ``rows`` with their std and correlation raised along the ``weak`` directions."""
    outputs = rows.copy()
    if len(weak) == 0 or len(outputs) == 0:
        return outputs
    front, rear = outputs[:, O_CF_STD] / outputs[:, O_CF], outputs[:, O_CR_STD] / outputs[:, O_CR]
    cross = outputs[:, O_CORRELATION] * front * rear
    covariance = np.empty((len(outputs), 2, 2))
    covariance[:, 0, 0], covariance[:, 0, 1], covariance[:, 1, 0], covariance[:, 1, 1] = \
        front * front, cross, cross, rear * rear
    published = published_covariance(covariance, weak, prior)
    new_front, new_rear = np.sqrt(published[:, 0, 0]), np.sqrt(published[:, 1, 1])
    denominator = new_front * new_rear
    outputs[:, O_CF_STD] = outputs[:, O_CF] * new_front
    outputs[:, O_CR_STD] = outputs[:, O_CR] * new_rear
    outputs[:, O_CORRELATION] = np.where(denominator > 0.0, published[:, 0, 1] / np.where(denominator > 0.0,
                                                                                             denominator, 1.0), 0.0)
    return outputs


def _relative_prior(initial_state: np.ndarray, initial_covariance: np.ndarray, log_state: bool) -> np.ndarray:
    """P0 of (ln Cf, ln Cr): the state's own in log mode, divided by C0^2 in linear mode."""
    index = [X_THETA_F, X_THETA_R]
    block = np.asarray(initial_covariance, dtype=np.float64)[np.ix_(index, index)]
    if log_state:
        return block
    scale = np.asarray(initial_state, dtype=np.float64)[index]
    return block / np.outer(scale, scale)
