"""The validity decision's window checks (DESIGN.md section 7): one implementation, online and offline.

:class:`~.validity.ValidityMonitor` runs them on its window every RECHECK s of data and words the
reasons; :func:`~.validity_batch.decide_batch` runs them over a whole replay at once. Both build the
per-epoch terms with :func:`window_columns` and evaluate them with the kernels here, so both decide
alike, bit for bit, on any Python (the sums run in plain loops, never compensated).
``test/test_window_checks.py`` holds each kernel against a slow, obvious version.

* :func:`plausibility_checks` (hard): the median sideslip at the CG, |vy - antenna_x r| / vx; the
  antenna's sideslip turning at about -2 r (swapped east and north, or a reversed heading sense);
  a heading that is a course over ground (vy well below a steady turn's at the antenna,
  :func:`steady_antenna_vy`, eq. 4 in steady state);
* :func:`soft_checks`: the input's suspect share; enough data; the tires within their linear range;
  the excitation (steering and yaw-rate std); the windowed chi^2 test of the NIS (2 dof per epoch);
  the lag-1 autocorrelation of the whitened vy innovations;
* :func:`drift_checks`: the sum of the normalised stiffness updates since the last change alarm.

Matrices and vectors, n epochs in the window (or the replay), p plausibility epochs, c consistency epochs:

* t, steering, yaw_rate (n,) float; nonlinear, suspect (n,) bool;
* plaus (p,) int64 indices into the n epochs; sideslip, rate, r_sq, vy_sq, steady_sq (p,) float;
* consist (c,) int64 indices; nis, whitened (c,) float;
* updates (n, 2) float: the normalised stiffness updates, Cf and Cr (0, 0: none at that epoch);
* limits (N_LIMITS,) float: :func:`window_limits`, indexed by layout.L_*.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import NamedTuple

import numpy as np

from transplanter_ident.config.parameters import ValiditySettings
from transplanter_ident.ekf.layout import (
    L_COURSE_RATIO,
    L_DRIFT_WINDOW,
    L_HOLD_OFF,
    L_HOLD_ON,
    L_MAX_AUTOCORRELATION,
    L_MAX_DRIFT_SIGMAS,
    L_MAX_NONLINEAR,
    L_MAX_SIDESLIP,
    L_MAX_SUSPECT,
    L_MIN_DRIFT_UPDATES,
    L_MIN_STEERING_STD,
    L_MIN_YAW_RATE_STD,
    L_MIXED_FLOOR,
    L_NIS_SIGMAS,
    L_RECHECK,
    L_WINDOW,
    N_LIMITS,
    StepStatus,
)
from transplanter_ident.jit import entry_kernel, inline_kernel

#: statuses whose innovation is a proper one-step prediction error (the plausibility checks' epochs)
PREDICTED = frozenset({StepStatus.UPDATED, StepStatus.NONLINEAR, StepStatus.GATED})
#: of those, the ones whose measurement the filter used: the consistency test's. A gated outlier (one
#: sample with a wrong stamp: a NIS of hundreds) is the suspect check's; in the NIS sum it failed the
#: whole window for its length (10 s) while the estimate had not taken it
USED = frozenset({StepStatus.UPDATED, StepStatus.NONLINEAR})
#: fewer stiffness updates in the drift test's span: no verdict
MIN_DRIFT_UPDATES = 10
#: rad/s: the rms yaw rate below which the frame and course checks see no turn to judge by
MIN_TURN_RATE = 0.05


class WindowColumns(NamedTuple):
    """The per-epoch terms of the window checks (shapes in the module docstring)."""

    t: np.ndarray
    nonlinear: np.ndarray
    steering: np.ndarray
    yaw_rate: np.ndarray
    suspect: np.ndarray
    plaus: np.ndarray
    sideslip: np.ndarray
    rate: np.ndarray
    r_sq: np.ndarray
    vy_sq: np.ndarray
    steady_sq: np.ndarray
    consist: np.ndarray
    nis: np.ndarray
    whitened: np.ndarray


def steady_antenna_vy(lever: float, rear_slip_gain: float, speed: float, cr: float, yaw_rate: float) -> float:
    """The antenna's vy in a steady turn at ``yaw_rate``: (lr + antenna_x) r less the rear tires' slip.

    The rear axle slides out by vx alpha_r = m lf vx^2 r / (2 (lf + lr) Cr) (eq. 4 in steady state);
    ``rear_slip_gain`` is m lf / (2 (lf + lr)), ``cr`` the estimated Cr. An antenna just behind the
    CG, where that slip cancels the kinematic (lr + antenna_x) r, sees a vy near zero with a true heading.
    """
    return (lever - rear_slip_gain * speed * speed / cr) * yaw_rate


def _table(statuses: Iterable[StepStatus]) -> np.ndarray:
    """Indexed by a StepStatus code: whether it is one of ``statuses`` (np.isin's answer, at a fraction of its cost)."""
    table = np.zeros(max(StepStatus) + 1, dtype=np.bool_)
    table[[int(s) for s in statuses]] = True
    table.setflags(write=False)
    return table


_PREDICTED, _USED = _table(PREDICTED), _table(USED)


def window_columns(t: np.ndarray, status: np.ndarray, speed: np.ndarray, vy: np.ndarray, yaw_rate: np.ndarray,
                   steering: np.ndarray, cr: np.ndarray, nis: np.ndarray, whitened: np.ndarray, suspect: np.ndarray,
                   geometry: tuple[float, float, float]) -> WindowColumns:
    """The window checks' terms of n epochs (all arrays (n,), ``status`` int64 StepStatus codes, all valid).

    ``nis``: the NIS the consistency test takes (epoch_checks.consistency_nis); ``whitened``: the vy
    innovation over its std (0 where it has none); ``suspect``: after a rejected sample, or distrusted;
    ``geometry``: (lr + antenna_x, m lf / (2 (lf + lr)), antenna_x). Python's ``math`` where the
    terms are scalar functions (atan2, remainder, squares), so any caller gets the same bits.
    """
    plaus = np.flatnonzero(_PREDICTED[status] & (speed > 0.0))
    consist = np.flatnonzero(_USED[status] & np.isfinite(nis))
    lever, rear_slip_gain, antenna_x = geometry
    speed_p, vy_p, r_p = speed[plaus], vy[plaus], yaw_rate[plaus]
    with np.errstate(invalid="ignore"):
        sideslip = np.abs(vy_p - antenna_x * r_p) / speed_p  # at the CG
    beta = list(map(math.atan2, vy_p.tolist(), speed_p.tolist()))
    tp, rp = t[plaus].tolist(), r_p.tolist()
    rate = np.zeros(len(plaus))  # the antenna sideslip's rate from the previous plausibility epoch to this one
    rate[1:] = [math.remainder(b1 - b0, 2.0 * math.pi) / (t1 - t0)
                for b0, b1, t0, t1 in zip(beta, beta[1:], tp, tp[1:], strict=False)]
    steady = [steady_antenna_vy(lever, rear_slip_gain, v, c, x)
              for v, c, x in zip(speed_p.tolist(), cr[plaus].tolist(), rp, strict=True)]
    return WindowColumns(
        t=np.ascontiguousarray(t, dtype=np.float64), nonlinear=status == int(StepStatus.NONLINEAR),
        steering=np.ascontiguousarray(steering, dtype=np.float64),
        yaw_rate=np.ascontiguousarray(yaw_rate, dtype=np.float64), suspect=np.asarray(suspect, dtype=np.bool_),
        plaus=plaus, sideslip=np.ascontiguousarray(sideslip, dtype=np.float64), rate=rate,
        r_sq=np.array([x ** 2 for x in rp], dtype=np.float64),
        vy_sq=np.array([x ** 2 for x in vy_p.tolist()], dtype=np.float64),
        steady_sq=np.array([x ** 2 for x in steady], dtype=np.float64), consist=consist,
        nis=np.ascontiguousarray(nis[consist], dtype=np.float64),
        whitened=np.ascontiguousarray(whitened[consist], dtype=np.float64))


def window_limits(settings: ValiditySettings, recheck: float, course: bool) -> np.ndarray:
    """The checks' thresholds, indexed by layout.L_* (``course``: the filter measures a course, so that check is off)."""
    limits = np.zeros(N_LIMITS)
    s = settings
    for index, value in ((L_WINDOW, s.window), (L_RECHECK, recheck), (L_MAX_SIDESLIP, s.max_sideslip),
                         (L_MIXED_FLOOR, MIN_TURN_RATE ** 2), (L_COURSE_RATIO, 0.0 if course else s.course_ratio),
                         (L_MAX_NONLINEAR, s.max_nonlinear_fraction), (L_MIN_STEERING_STD, s.min_steering_std),
                         (L_MIN_YAW_RATE_STD, s.min_yaw_rate_std), (L_NIS_SIGMAS, s.nis_quantile_sigmas),
                         (L_MAX_AUTOCORRELATION, s.max_autocorrelation), (L_HOLD_ON, s.hold_on),
                         (L_HOLD_OFF, s.hold_off), (L_MAX_SUSPECT, s.max_suspect_fraction),
                         (L_DRIFT_WINDOW, s.drift_window), (L_MAX_DRIFT_SIGMAS, s.max_drift_sigmas),
                         (L_MIN_DRIFT_UPDATES, MIN_DRIFT_UPDATES)):
        limits[index] = value
    return limits


@entry_kernel
def plausibility_checks(a, b, sideslip, rate, yaw_rate, plaus, r_sq, vy_sq, steady_sq, limits):  # noqa: ANN001, ANN201, PLR0913
    """Over plausibility epochs a..b-1: (median sideslip, sideslip fails, frames mixed, course over ground).

    Fewer than 5 epochs: (NaN, False, False, False). Frames mixed is only judged when the sideslip passes.
    """
    count = b - a
    if count < 5:
        return np.nan, False, False, False
    median = np.sort(sideslip[a:b])[count // 2]
    too_large = median > limits[L_MAX_SIDESLIP]
    num = 0.0
    den = 0.0
    for j in range(a + 1, b):  # the course's change rate against the yaw rate: a slope near 0 with right frames
        r = yaw_rate[plaus[j]]
        num += rate[j] * r
        den += r * r
    mixed = not too_large and den > limits[L_MIXED_FLOOR] * count and num / den < -1.0
    sum_r = 0.0
    sum_vy = 0.0
    sum_steady = 0.0
    for j in range(a, b):
        sum_r += r_sq[j]
        sum_vy += vy_sq[j]
        sum_steady += steady_sq[j]
    rms_r = np.sqrt(sum_r / count)
    course = rms_r > MIN_TURN_RATE and np.sqrt(sum_vy / count) < limits[L_COURSE_RATIO] * np.sqrt(sum_steady / count)
    return median, too_large, mixed, course


@inline_kernel
def population_std(values):  # noqa: ANN001, ANN201
    """The population standard deviation, summed in order."""
    total = 0.0
    for v in values:
        total += v
    mean = total / len(values)
    square = 0.0
    for v in values:
        square += (v - mean) * (v - mean)
    return np.sqrt(square / len(values))


@entry_kernel
def soft_checks(lo, i, a, b, t, nonlinear, steering, yaw_rate, suspect, nis, whitened, limits):  # noqa: ANN001, ANN201, PLR0913
    """The suspect, data, linear range, excitation, NIS and autocorrelation checks over epochs lo..i.

    a..b-1: the consistency epochs among them (``consist``'s indices, as ``nis`` and ``whitened``).
    Returns (suspect count, suspect fails, too little data, nonlinear fraction, nonlinear fails,
    unexcited, mean NIS, NIS fails, lag-1 autocorrelation, autocorrelation fails). With too little
    data the others are not judged (0, False; NaN for the NIS and the autocorrelation), nor the NIS
    and autocorrelation with fewer than 5 consistency epochs. Counted in loops: numba's array
    ``sum`` and ``searchsorted`` would cost the node ~14 MB to load.
    """
    count = i - lo + 1
    suspects = 0
    nonlinears = 0
    for j in range(lo, i + 1):
        suspects += suspect[j]
        nonlinears += nonlinear[j]
    suspect_fails = suspects > limits[L_MAX_SUSPECT] * count
    if count < 5 or t[i] - t[lo] < 0.5 * limits[L_WINDOW]:
        return suspects, suspect_fails, True, 0.0, False, False, np.nan, False, np.nan, False
    fraction = nonlinears / count
    unexcited = population_std(steering[lo:i + 1]) < limits[L_MIN_STEERING_STD] and \
        population_std(yaw_rate[lo:i + 1]) < limits[L_MIN_YAW_RATE_STD]
    m = b - a
    mean_nis, rho = np.nan, np.nan
    nis_fails = rho_fails = False
    if m >= 5:
        total = 0.0
        for j in range(a, b):
            total += nis[j]
        dof = 2 * m
        mean_nis = total / m
        nis_fails = total > dof + limits[L_NIS_SIGMAS] * np.sqrt(2.0 * dof)
        rho = _lag1_autocorrelation(whitened[a:b])
        rho_fails = rho > limits[L_MAX_AUTOCORRELATION]
    return (suspects, suspect_fails, False, fraction, fraction > limits[L_MAX_NONLINEAR], unexcited, mean_nis,
            nis_fails, rho, rho_fails)


@inline_kernel
def _lag1_autocorrelation(values):  # noqa: ANN001, ANN201
    """The lag-1 autocorrelation of ``values`` about their mean, summed in order; 0 without variance."""
    m = len(values)
    mean = 0.0
    for v in values:
        mean += v
    mean = mean / m
    power = 0.0
    for v in values:
        power += (v - mean) * (v - mean)
    if power <= 0.0:
        return 0.0
    lag = 0.0
    for j in range(1, m):
        lag += (values[j - 1] - mean) * (values[j] - mean)
    return lag / power


@entry_kernel
def drift_checks(lo, i, updates, limits):  # noqa: ANN001, ANN201
    """Over the updates of epochs lo..i (rows not both 0): (count, Cf's sum, Cr's sum, Cf fails, Cr fails).

    Off (``drift_window`` 0) or fewer than MIN_DRIFT_UPDATES: no verdict (False, False).
    """
    count = 0
    total_f = 0.0
    total_r = 0.0
    for j in range(lo, i + 1):
        if updates[j, 0] != 0.0 or updates[j, 1] != 0.0:
            count += 1
            total_f += updates[j, 0]
            total_r += updates[j, 1]
    if limits[L_DRIFT_WINDOW] <= 0.0 or count < limits[L_MIN_DRIFT_UPDATES]:
        return count, total_f, total_r, False, False
    limit = limits[L_MAX_DRIFT_SIGMAS] * np.sqrt(count)
    return count, total_f, total_r, abs(total_f) > limit, abs(total_r) > limit
