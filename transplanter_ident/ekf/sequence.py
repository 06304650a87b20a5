"""The filter over a whole epoch sequence, and the tuning objective (paper eqs. 12, 21).

:func:`make_sequence_kernels` wraps one size's compiled step (:mod:`.kernels`) in the two loops the
offline drivers use: ``run`` (replay: one output row per epoch) and ``objective`` (tuning: eq. 21's
mean absolute innovation, or the innovation negative log-likelihood).

Both take R per epoch from :func:`epoch_measurement_noise`: the configured R, or, with
``ekf.measurement_noise_from_covariance``, the variance the GNSS messages report wherever it is
larger (the configured R is a floor; issue #12 item 5). The node's step does the same.
:func:`innovation_covariance` (with :func:`heading_error_terms`, the full R's correlation) and
:func:`normalized_innovation_squared` are shared by the step and the Fisher information.
"""

from __future__ import annotations

import math

import numpy as np

from transplanter_ident.ekf.layout import (
    DIVERGENCE_PENALTY,
    E_PSI,
    E_SPEED,
    E_STEERING,
    E_STEERING_RATE,
    E_T,
    E_VAR_PSI,
    E_VAR_VY,
    E_VAR_YAW_RATE,
    E_VY,
    E_YAW_RATE,
    MAE,
    N_OUTPUTS,
    O_E0,
    O_E1,
    O_NIS,
    O_S00,
    O_S01,
    O_S11,
    S_MEASURE_ERRORS,
    S_NOISE_CORRELATION,
    S_R_FROM_COVARIANCE,
    WORK_SIZE,
    WORK_SLOTS,
    Z_SECOND,
    Z_VY,
    StepStatus,
)
from transplanter_ident.jit import inline_kernel, sized_kernel


@inline_kernel
def floored_variance(configured, reported):
    """The reported variance where it is larger than the configured one (0 = not reported, or smaller: configured)."""
    return reported if reported > configured else configured


@inline_kernel
def epoch_measurement_noise(r_noise, from_covariance, heading, velocity_variance, heading_variance,
                            yaw_rate_variance, r_epoch):
    """R of one epoch into ``r_epoch`` (2,): diag [vy (m/s)^2, psi rad^2 or r (rad/s)^2].

    ``from_covariance``: ``ekf.measurement_noise_from_covariance`` (settings[S_R_FROM_COVARIANCE]).
    """
    r_epoch[Z_VY] = r_noise[Z_VY]
    r_epoch[Z_SECOND] = r_noise[Z_SECOND]
    if from_covariance:
        r_epoch[Z_VY] = floored_variance(r_noise[Z_VY], velocity_variance)
        second = heading_variance if heading else yaw_rate_variance
        r_epoch[Z_SECOND] = floored_variance(r_noise[Z_SECOND], second)


@inline_kernel
def heading_error_terms(r_psi, speed):
    """What R gains in heading mode: (vx^2 R_psi, -vx R_psi) for (vy, vy) and (vy, psi); R_psi = ``r_psi``.

    The body-frame vy is the GNSS velocity turned by the *measured* heading, so e_vy = e_v - vx e_psi.
    """
    return speed * speed * r_psi, -speed * r_psi


@inline_kernel
def innovation_covariance(heading, hph00, hph01, hph11, r_vy, r_second, speed):
    """S = H P^- H^T + R as (s00, s01, s11), R = diag(r_vy, r_second) plus the heading's error in vy (heading mode).

    The step takes it with the learned factors on R (and again without, for the validity's NIS against
    the configured R); the Fisher information with H P^- H^T = 0.
    """
    s00, s01, s11 = hph00 + r_vy, hph01, hph11 + r_second
    if heading:
        extra00, extra01 = heading_error_terms(r_second, speed)
        s00 += extra00
        s01 += extra01
    return s00, s01, s11


@inline_kernel
def normalized_innovation_squared(e0, e1, s00, s01, s11):
    """(e^T S^-1 e, det S); both NaN when S is not positive definite (the step then rolls back)."""
    det = s00 * s11 - s01 * s01
    if not det > 0.0:
        det = math.nan
    return (e0 * e0 * s11 - 2.0 * e0 * e1 * s01 + e1 * e1 * s00) / det, det


def make_sequence_kernels(step_n, heading):  # noqa: ANN001, ANN201 - numba closures
    """``run_n`` and ``objective_n`` for one state size, around that size's ``step_n``."""

    @sized_kernel
    def run_n(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):
        """step_n over every row of ``epochs``; one output row per epoch."""
        ws = np.zeros((WORK_SLOTS, WORK_SIZE, WORK_SIZE))
        out = np.zeros(N_OUTPUTS)
        r_epoch = np.zeros(2)
        for k in range(epochs.shape[0]):
            epoch_measurement_noise(r_noise, settings[S_R_FROM_COVARIANCE] > 0.5, heading, epochs[k, E_VAR_VY], epochs[k, E_VAR_PSI],
                                    epochs[k, E_VAR_YAW_RATE], r_epoch)
            step_n(x, p, model, memo, vehicle, settings, q, r_epoch, epochs[k, E_T], epochs[k, E_SPEED],
                   epochs[k, E_STEERING], epochs[k, E_STEERING_RATE], epochs[k, E_VY], epochs[k, E_PSI],
                   epochs[k, E_YAW_RATE], ws, out)
            for j in range(N_OUTPUTS):
                outputs[k, j] = out[j]

    @sized_kernel
    def objective_n(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):
        """Tuning objective over a sequence: eq. 21 mean |innovation| (MAE) or Gaussian NLL.

        Only epochs with a predicted measurement (UPDATED, GATED, NONLINEAR) count. A diverging (or
        restarted) filter, or one that never predicts, scores DIVERGENCE_PENALTY. The step does not
        measure the model errors the validity tests (layout.S_MEASURE_ERRORS): no objective reads them. Nor
        does it widen R by the innovations' correlation (layout.S_NOISE_CORRELATION): the objective scores R
        as the white noise it is configured as, and the filter widens the tuned R at run time.
        """
        settings = settings.copy()
        settings[S_MEASURE_ERRORS] = 0.0
        settings[S_NOISE_CORRELATION] = 0.0
        ws = np.zeros((WORK_SLOTS, WORK_SIZE, WORK_SIZE))
        out = np.zeros(N_OUTPUTS)
        r_epoch = np.zeros(2)
        total = 0.0
        count = 0
        for k in range(epochs.shape[0]):
            epoch_measurement_noise(r_noise, settings[S_R_FROM_COVARIANCE] > 0.5, heading, epochs[k, E_VAR_VY], epochs[k, E_VAR_PSI],
                                    epochs[k, E_VAR_YAW_RATE], r_epoch)
            status = step_n(x, p, model, memo, vehicle, settings, q, r_epoch, epochs[k, E_T], epochs[k, E_SPEED],
                            epochs[k, E_STEERING], epochs[k, E_STEERING_RATE], epochs[k, E_VY], epochs[k, E_PSI],
                            epochs[k, E_YAW_RATE], ws, out)
            if status == StepStatus.DIVERGED or status == StepStatus.RESTARTED:
                return DIVERGENCE_PENALTY
            if status != StepStatus.UPDATED and status != StepStatus.GATED and status != StepStatus.NONLINEAR:
                continue
            if kind == MAE:
                total += abs(out[O_E0]) + abs(out[O_E1])
            else:
                det = out[O_S00] * out[O_S11] - out[O_S01] * out[O_S01]
                if det <= 0.0:
                    return DIVERGENCE_PENALTY
                total += 0.5 * (out[O_NIS] + math.log(det)) + math.log(2.0 * math.pi)
            count += 1
        if count == 0:
            return DIVERGENCE_PENALTY
        value = total / count
        if not math.isfinite(value):
            return DIVERGENCE_PENALTY
        return min(value, DIVERGENCE_PENALTY)

    return run_n, objective_n
