"""The validity decision of a whole replay at once: :class:`~.validity.ValidityMonitor`'s, bit for bit.

Feeding 72k epochs one by one through the monitor costs about a second of Python. Offline every
epoch is known, so the per-epoch checks are computed as columns (:mod:`.epoch_checks`' predicates,
which the monitor takes per epoch), the window checks' terms with the monitor's :func:`~.window_checks.window_columns`,
and a compiled kernel runs the monitor's sequence: the window bounds, the window checks
(:mod:`.window_checks`, which the monitor runs too) every RECHECK s, and the hysteresis
(:mod:`.hysteresis`, the monitor's too). Sequences
whose times do not strictly increase (the monitor would reset) return None, and the caller runs the
monitor.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from transplanter_ident.config.parameters import ValiditySettings
from transplanter_ident.ekf.layout import (
    L_DRIFT_WINDOW,
    L_HOLD_OFF,
    L_HOLD_ON,
    L_RECHECK,
    L_WINDOW,
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
from transplanter_ident.evaluation.epoch_checks import (
    change_suspected,
    consistency_nis,
    noisier,
    pinned,
    relative_stds,
    unconverged,
)
from transplanter_ident.evaluation.hysteresis import hysteresis_step, initial_state
from transplanter_ident.evaluation.model_errors import MODEL_ERRORS
from transplanter_ident.evaluation.window_checks import (
    PREDICTED,
    drift_checks,
    plausibility_checks,
    soft_checks,
    window_columns,
    window_limits,
)
from transplanter_ident.jit import entry_kernel


def decide_batch(settings: ValiditySettings, bounds: tuple[float, float], lever: float, recheck: float,
                 epochs: EpochArrays, outputs: np.ndarray, rejected: Sequence[int],
                 distrusted: Iterable[StepStatus], antenna_x: float = 0.0,
                 rear_slip_gain: float = 0.0, course: bool = False, setup: bool = False) -> np.ndarray | None:
    """The monitor's ``valid`` for every epoch, or None when the times do not strictly increase.

    ``rejected``: per epoch, the samples rejected since the previous one (Sample.rejected);
    ``distrusted``: the statuses that make an epoch suspect (validity.DISTRUSTED); ``antenna_x``: the
    antenna ahead of the CG (the sideslip check takes vy at the CG, ValidityMonitor.antenna_x);
    ``rear_slip_gain``: the course-over-ground check's (window_checks.steady_antenna_vy, ValidityMonitor.rear_slip_gain);
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
    suspect = (np.asarray(rejected, dtype=np.int64).reshape(-1) != 0) | np.isin(status, [int(s) for s in distrusted])
    if len(suspect) != n:
        return None
    cf, cr, cf_std, cr_std = (outputs[:, i] for i in (O_CF, O_CR, O_CF_STD, O_CR_STD))
    with np.errstate(divide="ignore", invalid="ignore"):
        hard = pinned(cf, bounds) | pinned(cr, bounds)
        front, rear, worst = relative_stds(cf, cr, cf_std, cr_std)
        soft = ~predicted | unconverged(worst, settings) | setup
        for error in MODEL_ERRORS:  # a GNSS delay, a relaxation length, a steering gain left out (model_errors.py)
            soft |= error.fails(outputs, front, rear, settings)
        soft |= noisier(outputs[:, O_NOISE_SCALE_VY], outputs[:, O_NOISE_SCALE_SECOND], settings)
        soft |= change_suspected(outputs[:, O_CHANGE_EVIDENCE], settings)
        s00 = outputs[:, O_S00]
        whitened = np.divide(outputs[:, O_E0], np.sqrt(np.where(s00 > 0.0, s00, 1.0)), where=s00 > 0.0,
                             out=np.zeros(n))
    nis = consistency_nis(outputs[:, O_NOISE_SCALE_VY], outputs[:, O_NOISE_SCALE_SECOND], outputs[:, O_NIS],
                          outputs[:, O_NIS_CONFIGURED], settings)
    columns = window_columns(t, status, np.ascontiguousarray(epochs.speed, dtype=np.float64),
                             np.ascontiguousarray(epochs.antenna_lateral_velocity, dtype=np.float64),
                             np.ascontiguousarray(epochs.yaw_rate, dtype=np.float64), epochs.steering, cr, nis,
                             whitened, suspect, (lever, rear_slip_gain, antenna_x))
    updates = np.ascontiguousarray(outputs[:, [O_UPDATE_F, O_UPDATE_R]], dtype=np.float64)
    return _decide_kernel(hard, soft, *columns, updates, outputs[:, O_CHANGE] > 0.0,
                          window_limits(settings, recheck, course), initial_state())


@entry_kernel
def _decide_kernel(epoch_hard, epoch_soft, t, nonlinear, steering, yaw_rate, suspect, plaus, sideslip, rate, r_sq,  # noqa: ANN001, ANN201, PLR0913
                   vy_sq, steady_sq, consist, nis, whitened, updates, change, limits, state):
    """ValidityMonitor.step over the sequence (times strictly increasing): the valid flag of every epoch.

    ``state``: the hysteresis' (hysteresis.initial_state), updated.
    """
    window, recheck, drift_window = limits[L_WINDOW], limits[L_RECHECK], limits[L_DRIFT_WINDOW]
    hold_on, hold_off = limits[L_HOLD_ON], limits[L_HOLD_OFF]
    n = len(t)
    valid_out = np.zeros(n, dtype=np.bool_)
    lo = 0
    drift_lo = 0  # the drift test's span: from the last change alarm, and drift_window s
    checked_at = -np.inf
    window_hard = False
    window_soft = False
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
            _median, too_large, mixed, course = plausibility_checks(a, b, sideslip, rate, yaw_rate, plaus, r_sq,
                                                                    vy_sq, steady_sq, limits)
            window_hard = too_large or mixed or course
            c0 = np.searchsorted(consist, lo)
            c1 = np.searchsorted(consist, i, side="right")
            (_suspects, suspect_fails, too_little, _fraction, too_nonlinear, unexcited, _mean_nis, nis_fails, _rho,
             rho_fails) = soft_checks(lo, i, c0, c1, t, nonlinear, steering, yaw_rate, suspect, nis, whitened, limits)
            _count, _total_f, _total_r, drift_f, drift_r = drift_checks(drift_lo, i, updates, limits)
            window_soft = (suspect_fails or too_little or too_nonlinear or unexcited or nis_fails or rho_fails
                           or drift_f or drift_r)
        hard = epoch_hard[i] or window_hard
        valid_out[i] = hysteresis_step(state, t[i], hard, hard or epoch_soft[i] or window_soft, hold_on, hold_off)
    return valid_out
