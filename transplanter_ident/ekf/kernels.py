"""Joint-state EKF over the motion states and the cornering stiffness (paper eqs. 9-14, 21).

State: [vy, r, psi, theta_f, theta_r] with z = [vy, psi] (``heading``, the default) or
[vy, r, theta_f, theta_r] with z = [vy, r] (``yaw_rate``, the paper's eq. 11). theta is ln C
(``log``) or C (``linear``). The prediction uses :func:`model.discretize` (eq. 10 or exact
ZOH, Jacobian eq. 13 with the A23 erratum fixed); the update is eq. 12 in Joseph form with a
Mahalanobis innovation gate. The stiffness is a random walk with process noise Q (eq. 22).

Alongside the filter runs the *model output* of the paper's Figs. 6-7: the bicycle model
driven by the measured steering and speed with the stiffness identified so far, open loop
from the first measured state. It shares the filter's discretisation at every step.

One compiled step, :func:`ekf_step`, serves the node and the offline drivers
(:mod:`.joint_ekf`), so online and offline numbers are identical. Array slots are named in
:mod:`.layout`; numba options are fixed in :mod:`.jit`.
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
    E_VY,
    E_YAW_RATE,
    EULER,
    G_HP0,
    G_HP1,
    G_K0,
    G_K1,
    M_GATED,
    M_INITIALISED,
    M_T_PREV,
    MAE,
    N_MODEL,
    N_OUTPUTS,
    O_CF,
    O_CF_STD,
    O_E0,
    O_E1,
    O_NIS,
    O_R,
    O_R_MODEL,
    O_S00,
    O_S01,
    O_S11,
    O_STATUS,
    O_VY,
    O_VY_MODEL,
    S_GATE,
    S_HIGH,
    S_LOG,
    S_LOW,
    S_MAX_GATED,
    S_MAX_INTERVAL,
    S_METHOD,
    S_MIN_SPEED,
    S_P0_PSI,
    S_P0_R,
    S_P0_VY,
    V_BACKUP_MODEL,
    V_BACKUP_X,
    V_NEW_MODEL,
    V_NEW_X,
    W_BACKUP_P,
    W_DE_F,
    W_DE_R,
    W_E,
    W_F,
    W_GAIN,
    W_TMP,
    W_VEC,
    WORK_SIZE,
    WORK_SLOTS,
    X_PSI,
    X_R,
    X_VY,
    Z_SECOND,
    Z_VY,
    StepStatus,
)
from transplanter_ident.ekf.model import discretize_heading, discretize_yaw_rate
from transplanter_ident.jit import inline_kernel, sized_kernel


@inline_kernel
def _finite(value):
    return not (math.isnan(value) or math.isinf(value))


@inline_kernel
def _wrap(angle):
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def make_kernels(n):
    """Compile predict/update/step for n states (5: heading mode, 4: yaw_rate mode).

    The sizes are compile-time constants, so the small loops unroll; all scratch lives in one
    work buffer indexed by slot (no per-step array views or allocations).
    """
    nd = n - 2
    heading = n == 5
    h1 = 2 if heading else 1  # second measured state: psi or r
    nf, nr = n - 2, n - 1
    discretize_n = discretize_heading if heading else discretize_yaw_rate

    @inline_kernel
    def reset_motion(x, p, model, settings, vy, psi, yaw_rate):
        """Take the motion states from the measurement; keep the stiffness and its variance."""
        x[X_VY] = vy
        x[X_R] = yaw_rate
        model[X_VY] = vy
        model[X_R] = yaw_rate
        model[X_PSI] = psi
        if heading:
            x[X_PSI] = psi
        for i in range(nd):
            for j in range(n):
                p[i, j] = 0.0
                p[j, i] = 0.0
        p[X_VY, X_VY] = settings[S_P0_VY]
        p[X_R, X_R] = settings[S_P0_R]
        if heading:
            p[X_PSI, X_PSI] = settings[S_P0_PSI]

    @inline_kernel
    def write_outputs(x, p, settings, status, r_model, vy_model, out):
        out[O_STATUS] = status.value
        out[O_VY] = x[X_VY]
        out[O_R] = x[X_R]
        for k in range(2):  # front, rear
            theta = x[nf + k]
            var = max(p[nf + k, nf + k], 0.0)
            if settings[S_LOG] > 0.5:
                c = math.exp(theta)
                out[O_CF + k] = c
                out[O_CF_STD + k] = c * math.sqrt(var)
            else:
                out[O_CF + k] = theta
                out[O_CF_STD + k] = math.sqrt(var)
        out[O_VY_MODEL] = vy_model
        out[O_R_MODEL] = r_model

    @inline_kernel
    def predict_n(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):
        """X <- f(x, u), model <- f(model, u); F = df/dx into ws[W_F]."""
        if settings[S_LOG] > 0.5:
            cf, cr = math.exp(x[nf]), math.exp(x[nr])
            dcf, dcr = cf, cr
        else:
            cf, cr = x[nf], x[nr]
            dcf, dcr = 1.0, 1.0
        method = int(settings[S_METHOD])
        discretize_n(cf, cr, dcf, dcr, speed, dt, vehicle, method, ws)
        level = steering if method == EULER else steering - 0.5 * dt * steering_rate
        for i in range(nd, n):  # the stiffness rows; the motion rows are all written below
            for j in range(n):
                ws[W_F, i, j] = 1.0 if i == j else 0.0
        for i in range(nd):
            acc = ws[W_E, i, nd] * level + ws[W_E, i, nd + 1] * steering_rate
            acc_f = ws[W_DE_F, i, nd] * level + ws[W_DE_F, i, nd + 1] * steering_rate
            acc_r = ws[W_DE_R, i, nd] * level + ws[W_DE_R, i, nd + 1] * steering_rate
            acc_m = acc
            for j in range(nd):
                acc += ws[W_E, i, j] * x[j]
                acc_f += ws[W_DE_F, i, j] * x[j]
                acc_r += ws[W_DE_R, i, j] * x[j]
                acc_m += ws[W_E, i, j] * model[j]
                ws[W_F, i, j] = ws[W_E, i, j]
            ws[W_F, i, nf] = acc_f
            ws[W_F, i, nr] = acc_r
            ws[W_VEC, V_NEW_X, i] = acc
            ws[W_VEC, V_NEW_MODEL, i] = acc_m
        for i in range(nd):
            x[i] = ws[W_VEC, V_NEW_X, i]
            model[i] = ws[W_VEC, V_NEW_MODEL, i]

    @inline_kernel
    def propagate_covariance(p, q, ws):
        """P = F P F^T + Q, with F = [[F_motion, F_stiffness], [0, I]] (the stiffness is a random walk)."""
        for i in range(nd):
            for j in range(n):
                acc = 0.0
                for k in range(n):
                    acc += ws[W_F, i, k] * p[k, j]
                ws[W_TMP, i, j] = acc
        for i in range(nd):
            for j in range(i, nd):
                acc = 0.0
                for k in range(n):
                    acc += ws[W_TMP, i, k] * ws[W_F, j, k]
                p[i, j] = acc
                p[j, i] = acc
            for j in range(nd, n):
                p[i, j] = ws[W_TMP, i, j]
                p[j, i] = ws[W_TMP, i, j]
        for i in range(n):
            p[i, i] += q[i]

    @inline_kernel
    def joseph_update(x, p, r_noise, e0, e1, s00, s01, s11, det, ws):
        """Update: x += K e; P = (I - K H) P (I - K H)^T + K R K^T, H selecting states 0 and h1.

        The Joseph form is evaluated expanded, P - K HP - (K HP)^T + K S K^T with S = H P H^T + R:
        the same function of K (so still second-order insensitive to gain errors), in O(n^2).
        """
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det
        for i in range(n):
            hp0, hp1 = p[X_VY, i], p[h1, i]
            k0 = hp0 * i00 + hp1 * i01
            k1 = hp0 * i01 + hp1 * i11
            ws[W_GAIN, G_K0, i] = k0
            ws[W_GAIN, G_K1, i] = k1
            ws[W_GAIN, G_HP0, i] = hp0
            ws[W_GAIN, G_HP1, i] = hp1
            x[i] += k0 * e0 + k1 * e1
        for i in range(n):
            k0, k1 = ws[W_GAIN, G_K0, i], ws[W_GAIN, G_K1, i]
            hp0, hp1 = ws[W_GAIN, G_HP0, i], ws[W_GAIN, G_HP1, i]
            ks0 = k0 * s00 + k1 * s01 - hp0
            ks1 = k0 * s01 + k1 * s11 - hp1
            for j in range(i, n):
                acc = (p[i, j] - k0 * ws[W_GAIN, G_HP0, j] - k1 * ws[W_GAIN, G_HP1, j]
                       + ks0 * ws[W_GAIN, G_K0, j] + ks1 * ws[W_GAIN, G_K1, j])
                p[i, j] = acc
                p[j, i] = acc

    @inline_kernel
    def healthy(x, p, r_model, vy_model, nis):
        for i in range(n):
            if not _finite(x[i]):
                return False
            for j in range(n):
                if not _finite(p[i, j]):
                    return False
        return _finite(r_model) and _finite(vy_model) and _finite(nis)

    # Compiled without numba's runtime (NRT): the step allocates nothing, and with the NRT every
    # call increfs and decrefs its ten array arguments with atomic instructions, which took over half of
    # the euler step (numba issues #2345, #2350 give _nrt=False as the remedy).
    @sized_kernel(runtime=False)
    def step_n(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,
               steering_rate, vy, psi, yaw_rate, ws, out):
        for k in range(N_OUTPUTS):
            out[k] = 0.0
        if not (_finite(t) and _finite(speed) and _finite(steering) and _finite(steering_rate)
                and _finite(vy) and _finite(psi) and _finite(yaw_rate)):
            write_outputs(x, p, settings, StepStatus.REJECTED_INVALID, model[X_R], model[X_VY], out)
            return StepStatus.REJECTED_INVALID
        if memo[M_INITIALISED] > 0.5 and t <= memo[M_T_PREV]:
            write_outputs(x, p, settings, StepStatus.REJECTED_STAMP, model[X_R], model[X_VY], out)
            return StepStatus.REJECTED_STAMP
        status = StepStatus.UPDATED
        if memo[M_INITIALISED] < 0.5:
            status = StepStatus.INITIALISED
        elif t - memo[M_T_PREV] > settings[S_MAX_INTERVAL]:
            status = StepStatus.GAP
        elif speed < 0.0 and -speed >= settings[S_MIN_SPEED]:
            status = StepStatus.REVERSING
        elif speed < settings[S_MIN_SPEED]:
            status = StepStatus.LOW_SPEED
        if status != StepStatus.UPDATED:
            reset_motion(x, p, model, settings, vy, psi, yaw_rate)
            memo[M_T_PREV] = t
            memo[M_INITIALISED] = 1.0
            memo[M_GATED] = 0.0
            write_outputs(x, p, settings, status, yaw_rate, vy, out)
            return status

        dt = t - memo[M_T_PREV]
        for i in range(n):
            ws[W_VEC, V_BACKUP_X, i] = x[i]
            for j in range(n):
                ws[W_BACKUP_P, i, j] = p[i, j]
        for i in range(N_MODEL):
            ws[W_VEC, V_BACKUP_MODEL, i] = model[i]

        # prediction, eq. 12 first two lines
        psi_model_before = model[X_PSI]
        predict_n(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)
        r_model = (model[X_PSI] - psi_model_before) / dt if heading else model[X_R]
        vy_model = model[X_VY]
        propagate_covariance(p, q, ws)

        # innovation (eq. 21 uses its absolute value) and the gate
        e0 = vy - x[X_VY]
        e1 = _wrap(psi - x[X_PSI]) if heading else yaw_rate - x[X_R]
        s00 = p[X_VY, X_VY] + r_noise[Z_VY]
        s01 = p[X_VY, h1]
        s11 = p[h1, h1] + r_noise[Z_SECOND]
        det = s00 * s11 - s01 * s01
        nis = (e0 * e0 * s11 - 2.0 * e0 * e1 * s01 + e1 * e1 * s00) / det
        out[O_E0] = e0
        out[O_E1] = e1
        out[O_S00] = s00
        out[O_S01] = s01
        out[O_S11] = s11
        out[O_NIS] = nis
        if nis > settings[S_GATE] and memo[M_GATED] < settings[S_MAX_GATED]:
            status = StepStatus.GATED
            memo[M_GATED] += 1.0
        else:
            memo[M_GATED] = 0.0
            joseph_update(x, p, r_noise, e0, e1, s00, s01, s11, det, ws)
        low, high = settings[S_LOW], settings[S_HIGH]
        x[nf] = min(max(x[nf], low), high)
        x[nr] = min(max(x[nr], low), high)

        if not healthy(x, p, r_model, vy_model, nis):  # roll back
            for i in range(n):
                x[i] = ws[W_VEC, V_BACKUP_X, i]
                for j in range(n):
                    p[i, j] = ws[W_BACKUP_P, i, j]
            for i in range(N_MODEL):
                model[i] = ws[W_VEC, V_BACKUP_MODEL, i]
            for k in range(N_OUTPUTS):
                out[k] = 0.0
            write_outputs(x, p, settings, StepStatus.DIVERGED, model[X_R], model[X_VY], out)
            return StepStatus.DIVERGED
        memo[M_T_PREV] = t
        write_outputs(x, p, settings, status, r_model, vy_model, out)
        return status

    @sized_kernel
    def run_n(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):
        """step_n over every row of ``epochs``; one output row per epoch."""
        ws = np.zeros((WORK_SLOTS, WORK_SIZE, WORK_SIZE))
        out = np.zeros(N_OUTPUTS)
        for k in range(epochs.shape[0]):
            step_n(x, p, model, memo, vehicle, settings, q, r_noise, epochs[k, E_T], epochs[k, E_SPEED],
                   epochs[k, E_STEERING], epochs[k, E_STEERING_RATE], epochs[k, E_VY], epochs[k, E_PSI],
                   epochs[k, E_YAW_RATE], ws, out)
            for j in range(N_OUTPUTS):
                outputs[k, j] = out[j]

    @sized_kernel
    def objective_n(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):
        """Tuning objective over a sequence: eq. 21 mean |innovation| (MAE) or Gaussian NLL.

        Only epochs with a predicted measurement (UPDATED or GATED) count. A diverging filter, or
        one that never predicts, scores DIVERGENCE_PENALTY.
        """
        ws = np.zeros((WORK_SLOTS, WORK_SIZE, WORK_SIZE))
        out = np.zeros(N_OUTPUTS)
        total = 0.0
        count = 0
        for k in range(epochs.shape[0]):
            status = step_n(x, p, model, memo, vehicle, settings, q, r_noise, epochs[k, E_T], epochs[k, E_SPEED],
                            epochs[k, E_STEERING], epochs[k, E_STEERING_RATE], epochs[k, E_VY], epochs[k, E_PSI],
                            epochs[k, E_YAW_RATE], ws, out)
            if status == StepStatus.DIVERGED:
                return DIVERGENCE_PENALTY
            if status != StepStatus.UPDATED and status != StepStatus.GATED:
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
        if not _finite(value):
            return DIVERGENCE_PENALTY
        return min(value, DIVERGENCE_PENALTY)

    return predict_n, step_n, run_n, objective_n
