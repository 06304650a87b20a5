"""The validity decision of a whole replay at once: :class:`~.validity.ValidityMonitor`'s, bit for bit.

Feeding 72k epochs one by one through the monitor costs about a second of Python, most of it in
the window checks that run every RECHECK s over ~10 s of data. Offline every epoch is known, so
the per-epoch terms are computed as columns (with the monitor's own operations; ``math`` where it
uses ``math``: atan2, remainder and the squares of r and vy, which it takes with ``**``), and a
compiled kernel runs the monitor's sequence: the window bounds, the window checks with sums in the
monitor's order, and the hysteresis. Sequences whose times do not strictly increase (the monitor
would reset) return None, and the caller runs the monitor.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from transplanter_ident.config.parameters import ValiditySettings
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
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.model_errors import MODEL_ERRORS
from transplanter_ident.jit import entry_kernel

#: statuses whose innovation is a proper one-step prediction error (the plausibility checks' epochs)
PREDICTED = frozenset({StepStatus.UPDATED, StepStatus.NONLINEAR, StepStatus.GATED})
#: of those, the ones whose measurement the filter used: the consistency test's. A gated outlier (one
#: sample with a wrong stamp: a NIS of hundreds) is the suspect check's; in the NIS sum it failed the
#: whole window for its length (10 s) while the estimate had not taken it
USED = frozenset({StepStatus.UPDATED, StepStatus.NONLINEAR})
#: fewer stiffness updates in the drift test's span: no verdict (ValidityMonitor._drift, _drifting)
MIN_DRIFT_UPDATES = 10


def steady_antenna_vy(lever: float, rear_slip_gain: float, speed: float, cr: float, yaw_rate: float) -> float:
    """The antenna's vy in a steady turn at ``yaw_rate``: (lr + antenna_x) r less the rear tires' slip.

    The rear axle slides out by vx alpha_r = m lf vx^2 r / (2 (lf + lr) Cr) (eq. 4 in steady state);
    ``rear_slip_gain`` is m lf / (2 (lf + lr)), ``cr`` the estimated Cr. An antenna just behind the
    CG, where that slip cancels the kinematic (lr + antenna_x) r, sees a vy near zero with a true heading.
    """
    return (lever - rear_slip_gain * speed * speed / cr) * yaw_rate


def noise_factor(outputs: np.ndarray) -> np.ndarray:
    """The larger factor on R (variance) the innovations show, velocity's or heading's (ekf.noise_adaptation), per row."""
    return np.maximum(outputs[..., O_NOISE_SCALE_VY], outputs[..., O_NOISE_SCALE_SECOND])


def consistency_nis(factor: np.ndarray | float, measured: np.ndarray | float, configured: np.ndarray | float,
                    max_noise_factor: float) -> np.ndarray:
    """The NIS the consistency test takes (the monitor's per sample, the batch's per row).

    Against R as the innovations show it (layout.O_NIS, ``measured``) where the noise ``factor`` is within
    ``max_noise_factor``, else against the configured R (O_NIS_CONFIGURED, ``configured``).
    """
    return np.where(np.asarray(factor) <= max_noise_factor, measured, configured)


def decide_batch(settings: ValiditySettings, bounds: tuple[float, float], lever: float, recheck: float,
                 epochs: EpochArrays, outputs: np.ndarray, rejected: Sequence[int],
                 distrusted: Iterable[StepStatus], antenna_x: float = 0.0,
                 rear_slip_gain: float = 0.0, course: bool = False, setup: bool = False) -> np.ndarray | None:
    """The monitor's ``valid`` for every epoch, or None when the times do not strictly increase.

    ``rejected``: per epoch, the samples rejected since the previous one (Sample.rejected);
    ``distrusted``: the statuses that make an epoch suspect (validity.DISTRUSTED); ``antenna_x``: the
    antenna ahead of the CG (the sideslip check takes vy at the CG, ValidityMonitor.antenna_x);
    ``rear_slip_gain``: the course-over-ground check's (:func:`steady_antenna_vy`, ValidityMonitor.rear_slip_gain);
    ``course``: the filter measures a course (ekf.measurement course), so that check is off; ``setup``: the set-up
    alone rules every epoch out (validity.setup_reasons).
    """
    t = np.ascontiguousarray(epochs.t, dtype=np.float64)
    n = len(t)
    if n == 0 or not np.all(np.diff(t) > 0.0):
        return None if n else np.zeros(0, dtype=bool)
    if not np.isfinite(outputs[:, O_STATUS]).all():
        return None
    status = outputs[:, O_STATUS].astype(np.int64)
    if not np.all(outputs[:, O_STATUS] == status) or not np.isin(status, [int(s) for s in StepStatus]).all():
        return None
    predicted = np.isin(status, [int(s) for s in PREDICTED])
    used = np.isin(status, [int(s) for s in USED])
    suspect = (np.asarray(rejected, dtype=np.int64).reshape(-1) != 0) | np.isin(status, [int(s) for s in distrusted])
    if len(suspect) != n:
        return None
    speed = np.ascontiguousarray(epochs.speed, dtype=np.float64)
    vy = np.ascontiguousarray(epochs.antenna_lateral_velocity, dtype=np.float64)
    r = np.ascontiguousarray(epochs.yaw_rate, dtype=np.float64)
    cf, cr, cf_std, cr_std = (outputs[:, i] for i in (O_CF, O_CR, O_CF_STD, O_CR_STD))
    low, high = bounds
    with np.errstate(divide="ignore", invalid="ignore"):
        hard = (cf <= low * 1.01) | (cf >= high / 1.01) | (cr <= low * 1.01) | (cr >= high / 1.01)
        front, rear = cf_std / cf, cr_std / cr
        worst = np.where(rear > front, rear, front)  # max(front, rear), NaN as Python's max treats it
        soft = ~predicted | ~(worst <= settings.max_rel_std) | setup
        for error in MODEL_ERRORS:  # a GNSS delay, a relaxation length, a steering gain left out (model_errors.py)
            soft |= error.fails(outputs, front, rear, settings)
        soft |= noise_factor(outputs) > settings.max_noise_factor
        soft |= outputs[:, O_CHANGE_EVIDENCE] > settings.max_change_evidence
        s00 = outputs[:, O_S00]
        whitened = np.divide(outputs[:, O_E0], np.sqrt(np.where(s00 > 0.0, s00, 1.0)), where=s00 > 0.0,
                             out=np.zeros(n))
        sideslip = np.abs(vy - antenna_x * r) / speed  # at the CG
    nis = np.ascontiguousarray(consistency_nis(noise_factor(outputs), outputs[:, O_NIS], outputs[:, O_NIS_CONFIGURED],
                                               settings.max_noise_factor), dtype=np.float64)
    plaus = np.flatnonzero(predicted & (speed > 0.0))  # the plausibility checks' epochs
    consist = np.flatnonzero(used & np.isfinite(nis))  # the NIS and autocorrelation checks' epochs
    beta = list(map(math.atan2, vy[plaus].tolist(), speed[plaus].tolist()))
    tp, rp = t[plaus].tolist(), r[plaus].tolist()
    rate = np.zeros(len(plaus))  # course change rate from the previous plausibility epoch to this one
    rate[1:] = [math.remainder(b1 - b0, 2.0 * math.pi) / (t1 - t0)
                for b0, b1, t0, t1 in zip(beta, beta[1:], tp, tp[1:], strict=False)]
    r_sq = np.array([x ** 2 for x in rp])
    vy_sq = np.array([x ** 2 for x in vy[plaus].tolist()])
    steady_sq = np.array([steady_antenna_vy(lever, rear_slip_gain, v, c, x) ** 2
                          for v, c, x in zip(speed[plaus].tolist(), cr[plaus].tolist(), rp, strict=True)])
    s = settings
    limits = np.array([s.window, recheck, s.max_sideslip, 0.05 ** 2, 0.0 if course else s.course_ratio,
                       s.max_nonlinear_fraction, s.min_steering_std, s.min_yaw_rate_std, s.nis_quantile_sigmas,
                       s.max_autocorrelation, s.hold_on, s.hold_off, s.max_suspect_fraction, s.drift_window,
                       s.max_drift_sigmas, MIN_DRIFT_UPDATES])
    updates = np.ascontiguousarray(outputs[:, [O_UPDATE_F, O_UPDATE_R]], dtype=np.float64)
    return _decide_kernel(t, status == int(StepStatus.NONLINEAR), hard, soft, np.ascontiguousarray(epochs.steering),
                          r, plaus, sideslip[plaus], rate, r_sq, vy_sq, steady_sq, consist, nis[consist],
                          whitened[consist], suspect, updates, outputs[:, O_CHANGE] > 0.0, limits)


@entry_kernel
def _decide_kernel(t, nonlinear, epoch_hard, epoch_soft, steering, r, plaus, sideslip, rate, r_sq, vy_sq,  # noqa: ANN001, ANN201, PLR0913
                   steady_sq, consist, nis, whitened, suspect, updates, change, limits):
    """ValidityMonitor.step over the sequence (times strictly increasing): the valid flag of every epoch."""
    window, recheck, max_sideslip, mixed_floor, course_ratio = limits[0], limits[1], limits[2], limits[3], limits[4]
    max_nonlinear, min_steering_std, min_yaw_rate_std = limits[5], limits[6], limits[7]
    sigmas, max_rho, hold_on, hold_off, max_suspect = limits[8], limits[9], limits[10], limits[11], limits[12]
    drift_window = limits[13]
    n = len(t)
    valid_out = np.zeros(n, dtype=np.bool_)
    lo = 0
    drift_lo = 0  # the drift test's span: from the last change alarm, and drift_window s
    checked_at = -np.inf
    window_hard = False
    window_soft = False
    valid = False
    good, bad = False, False  # whether good_since / bad_since are set
    good_since = bad_since = 0.0
    for i in range(n):
        while t[lo] < t[i] - window:
            lo += 1
        if change[i]:
            drift_lo = i
        while drift_lo < i and t[drift_lo] < t[i] - drift_window:
            drift_lo += 1
        if t[i] - checked_at >= recheck:
            checked_at = t[i]
            a = np.searchsorted(plaus, lo)
            b = np.searchsorted(plaus, i, side="right")
            window_hard = _plausible_not(a, b, sideslip, rate, r, plaus, r_sq, vy_sq, steady_sq, max_sideslip,
                                         mixed_floor, course_ratio)
            window_soft = suspect[lo:i + 1].sum() > max_suspect * (i - lo + 1) or _inconsistent(
                lo, i, t, window, nonlinear, steering, r, consist, nis, whitened, max_nonlinear, min_steering_std,
                min_yaw_rate_std, sigmas, max_rho) or _drifting(drift_lo, i, updates, limits)
        hard = epoch_hard[i] or window_hard
        if hard or epoch_soft[i] or window_soft:
            good = False
            if not bad:
                bad, bad_since = True, t[i]
            if hard or t[i] - bad_since >= hold_off:
                valid = False
        else:
            bad = False
            if not good:
                good, good_since = True, t[i]
            if t[i] - good_since >= hold_on:
                valid = True
        valid_out[i] = valid
    return valid_out


@entry_kernel
def _plausible_not(a, b, sideslip, rate, r, plaus, r_sq, vy_sq, steady_sq, max_sideslip, mixed_floor,  # noqa: ANN001, ANN201, PLR0913
                   course_ratio):
    """Whether ValidityMonitor._plausibility finds a reason, over plausibility epochs a..b-1."""
    count = b - a
    if count < 5:
        return False
    if np.sort(sideslip[a:b])[count // 2] > max_sideslip:
        return True
    num = 0.0
    den = 0.0
    for j in range(a + 1, b):
        yaw_rate = r[plaus[j]]
        num += rate[j] * yaw_rate
        den += yaw_rate * yaw_rate
    if den > mixed_floor * count and num / den < -1.0:
        return True
    sum_r = 0.0
    sum_vy = 0.0
    sum_steady = 0.0
    for j in range(a, b):
        sum_r += r_sq[j]
        sum_vy += vy_sq[j]
        sum_steady += steady_sq[j]
    rms_r = np.sqrt(sum_r / count)
    rms_vy = np.sqrt(sum_vy / count)
    return rms_r > 0.05 and rms_vy < course_ratio * np.sqrt(sum_steady / count)


@entry_kernel
def _std(values):  # noqa: ANN001, ANN201
    """validity._std: the population standard deviation, summed in order."""
    total = 0.0
    for v in values:
        total += v
    mean = total / len(values)
    square = 0.0
    for v in values:
        square += (v - mean) * (v - mean)
    return np.sqrt(square / len(values))


@entry_kernel
def _inconsistent(lo, i, t, window, nonlinear, steering, r, consist, nis, whitened, max_nonlinear,  # noqa: ANN001, ANN201, PLR0913
                  min_steering_std, min_yaw_rate_std, sigmas, max_rho):
    """Whether ValidityMonitor._consistency finds a reason, over epochs lo..i."""
    count = i - lo + 1
    if count < 5 or t[i] - t[lo] < 0.5 * window:
        return True
    if nonlinear[lo:i + 1].sum() / count > max_nonlinear:
        return True
    if _std(steering[lo:i + 1]) < min_steering_std and _std(r[lo:i + 1]) < min_yaw_rate_std:
        return True
    a = np.searchsorted(consist, lo)
    b = np.searchsorted(consist, i, side="right")
    m = b - a
    if m < 5:
        return False
    total = 0.0
    for j in range(a, b):
        total += nis[j]
    dof = 2 * m
    if total > dof + sigmas * np.sqrt(2.0 * dof):
        return True
    mean = 0.0
    for j in range(a, b):
        mean += whitened[j]
    mean = mean / m
    power = 0.0
    for j in range(a, b):
        power += (whitened[j] - mean) * (whitened[j] - mean)
    if power <= 0.0:
        return False
    lag = 0.0
    for j in range(a + 1, b):
        lag += (whitened[j - 1] - mean) * (whitened[j] - mean)
    return lag / power > max_rho


@entry_kernel
def _drifting(lo, i, updates, limits):  # noqa: ANN001, ANN201
    """Whether ValidityMonitor._drift finds a reason, over the updates of epochs lo..i (rows not both 0)."""
    drift_window, max_sigmas, min_updates = limits[13], limits[14], limits[15]
    if drift_window <= 0.0:
        return False
    count = 0
    total_f = 0.0
    total_r = 0.0
    for j in range(lo, i + 1):
        if updates[j, 0] != 0.0 or updates[j, 1] != 0.0:
            count += 1
            total_f += updates[j, 0]
            total_r += updates[j, 1]
    if count < min_updates:
        return False
    limit = max_sigmas * np.sqrt(count)
    return abs(total_f) > limit or abs(total_r) > limit
