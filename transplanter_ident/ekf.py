"""Joint-state EKF over the motion states and the cornering stiffness (paper eqs. 9-14, 21).

State: [vy, r, psi, theta_f, theta_r] with z = [vy, psi] (``heading``, the default) or
[vy, r, theta_f, theta_r] with z = [vy, r] (``yaw_rate``, the paper's eq. 11). theta is ln C
(``log``) or C (``linear``). The prediction uses :func:`model.discretize` (eq. 10 or exact
ZOH, Jacobian eq. 13 with the A23 erratum fixed); the update is eq. 12 in Joseph form with a
Mahalanobis innovation gate. The stiffness is a random walk with process noise Q (eq. 22).

Alongside the filter runs the *model output* of the paper's Figs. 6-7: the bicycle model
driven by the measured steering and speed with the stiffness identified so far, open loop
from the first measured state. It shares the filter's discretisation at every step.

One compiled step, :func:`ekf_step`, serves the node (:class:`JointEKF`, epoch by epoch) and
the offline drivers (:func:`run_sequence`, :func:`sequence_objective`), so online and offline
numbers are identical.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numba
import numpy as np

from .measurements import Epoch, EpochArrays
from .model import (
    EULER,
    EXACT,
    W_DE_F,
    W_DE_R,
    W_E,
    WORK_SIZE,
    WORK_SLOTS,
    discretize_heading,
    discretize_yaw_rate,
    vehicle_array,
    work_buffer,
)
from .parameters import EstimatorConfig, NoiseParams

# settings vector layout
S_METHOD, S_LOG, S_HEADING, S_MIN_SPEED, S_LOW, S_HIGH = 0, 1, 2, 3, 4, 5
S_GATE, S_MAX_GATED, S_MAX_INTERVAL, S_P0_VY, S_P0_R, S_P0_PSI = 6, 7, 8, 9, 10, 11
N_SETTINGS = 12

# output vector layout (one row per epoch)
O_STATUS, O_VY, O_R, O_CF, O_CR, O_CF_STD, O_CR_STD = 0, 1, 2, 3, 4, 5, 6
O_VY_MODEL, O_R_MODEL, O_E0, O_E1, O_S00, O_S01, O_S11, O_NIS = 7, 8, 9, 10, 11, 12, 13, 14
N_OUTPUTS = 15

# memory vector layout
M_T_PREV, M_INITIALISED, M_GATED = 0, 1, 2

# epoch array columns (see measurements.EpochArrays.kernel_input)
E_T, E_SPEED, E_STEERING, E_STEERING_RATE, E_VY, E_PSI, E_YAW_RATE = 0, 1, 2, 3, 4, 5, 6

# objectives
MAE = 0
NLL = 1
DIVERGENCE_PENALTY = 1.0e6


class StepStatus(enum.IntEnum):
    """What the filter did with an epoch."""

    UPDATED = 0
    GATED = 1  # predicted; the measurement failed the innovation gate
    LOW_SPEED = 2  # |vx| below min_speed: motion states follow the measurement, stiffness held
    REVERSING = 3  # vx negative: as LOW_SPEED
    INITIALISED = 4  # first epoch: motion states taken from the measurement
    GAP = 5  # interval longer than max_interval: motion states re-initialised
    REJECTED_INVALID = 6  # NaN or Inf in the epoch: nothing changed
    REJECTED_STAMP = 7  # stamp not after the previous epoch: nothing changed
    DIVERGED = 8  # the step produced a non-finite state: rolled back

    @property
    def stiffness_updated(self) -> bool:
        """Whether the stiffness estimate saw this epoch's measurement."""
        return self is StepStatus.UPDATED


@numba.njit(cache=True)
def _finite(value):
    return not (math.isnan(value) or math.isinf(value))


@numba.njit(cache=True)
def _wrap(angle):
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


# work-buffer slots of this module (model.py uses 0..11)
W_F, W_TMP, W_GAIN, W_BACKUP_P, W_VEC = 12, 13, 14, 15, 16  # W_GAIN rows: K[:, 0], K[:, 1], P[0], P[h1]
V_BACKUP_X, V_BACKUP_MODEL, V_NEW_X, V_NEW_MODEL = 0, 1, 2, 3  # rows of ws[W_VEC]


def _make_kernels(n):
    """Compile predict/update/step for n states (5: heading mode, 4: yaw_rate mode).

    The sizes are compile-time constants, so the small loops unroll; all scratch lives in one
    work buffer indexed by slot (no per-step array views or allocations).
    """
    nd = n - 2
    heading = n == 5
    h1 = 2 if heading else 1  # second measured state: psi or r
    nf, nr = n - 2, n - 1
    discretize_n = discretize_heading if heading else discretize_yaw_rate

    @numba.njit(cache=True, inline='always')
    def reset_motion(x, p, model, settings, vy, psi, yaw_rate):
        """Take the motion states from the measurement; keep the stiffness and its variance."""
        x[0] = vy
        x[1] = yaw_rate
        model[0] = vy
        model[1] = yaw_rate
        model[2] = psi
        if heading:
            x[2] = psi
        for i in range(nd):
            for j in range(n):
                p[i, j] = 0.0
                p[j, i] = 0.0
        p[0, 0] = settings[S_P0_VY]
        p[1, 1] = settings[S_P0_R]
        if heading:
            p[2, 2] = settings[S_P0_PSI]

    @numba.njit(cache=True, inline='always')
    def write_outputs(x, p, settings, status, r_model, vy_model, out):
        out[O_STATUS] = status
        out[O_VY] = x[0]
        out[O_R] = x[1]
        for k in range(2):
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

    @numba.njit(cache=True, inline='always')
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

    @numba.njit(cache=True, inline='always')
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

    @numba.njit(cache=True, inline='always')
    def joseph_update(x, p, r_noise, e0, e1, s00, s01, s11, det, ws):
        """Update: x += K e; P = (I - K H) P (I - K H)^T + K R K^T, H selecting states 0 and h1.

        The Joseph form is evaluated expanded, P - K HP - (K HP)^T + K S K^T with S = H P H^T + R:
        the same function of K (so still second-order insensitive to gain errors), in O(n^2).
        """
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det
        for i in range(n):
            hp0, hp1 = p[0, i], p[h1, i]
            k0 = hp0 * i00 + hp1 * i01
            k1 = hp0 * i01 + hp1 * i11
            ws[W_GAIN, 0, i] = k0
            ws[W_GAIN, 1, i] = k1
            ws[W_GAIN, 2, i] = hp0
            ws[W_GAIN, 3, i] = hp1
            x[i] += k0 * e0 + k1 * e1
        for i in range(n):
            k0, k1 = ws[W_GAIN, 0, i], ws[W_GAIN, 1, i]
            hp0, hp1 = ws[W_GAIN, 2, i], ws[W_GAIN, 3, i]
            ks0 = k0 * s00 + k1 * s01 - hp0
            ks1 = k0 * s01 + k1 * s11 - hp1
            for j in range(i, n):
                acc = (p[i, j] - k0 * ws[W_GAIN, 2, j] - k1 * ws[W_GAIN, 3, j]
                       + ks0 * ws[W_GAIN, 0, j] + ks1 * ws[W_GAIN, 1, j])
                p[i, j] = acc
                p[j, i] = acc

    @numba.njit(cache=True, inline='always')
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
    @numba.njit(cache=True, _nrt=False)
    def step_n(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,
               steering_rate, vy, psi, yaw_rate, ws, out):
        for k in range(N_OUTPUTS):
            out[k] = 0.0
        if not (_finite(t) and _finite(speed) and _finite(steering) and _finite(steering_rate)
                and _finite(vy) and _finite(psi) and _finite(yaw_rate)):
            write_outputs(x, p, settings, 6, model[1], model[0], out)
            return 6
        if memo[M_INITIALISED] > 0.5 and t <= memo[M_T_PREV]:
            write_outputs(x, p, settings, 7, model[1], model[0], out)
            return 7
        status = 0
        if memo[M_INITIALISED] < 0.5:
            status = 4
        elif t - memo[M_T_PREV] > settings[S_MAX_INTERVAL]:
            status = 5
        elif speed < 0.0 and -speed >= settings[S_MIN_SPEED]:
            status = 3
        elif speed < settings[S_MIN_SPEED]:
            status = 2
        if status != 0:
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
        for i in range(3):
            ws[W_VEC, V_BACKUP_MODEL, i] = model[i]

        # prediction, eq. 12 first two lines
        psi_model_before = model[2]
        predict_n(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)
        r_model = (model[2] - psi_model_before) / dt if heading else model[1]
        vy_model = model[0]
        propagate_covariance(p, q, ws)

        # innovation (eq. 21 uses its absolute value) and the gate
        e0 = vy - x[0]
        e1 = _wrap(psi - x[2]) if heading else yaw_rate - x[1]
        s00 = p[0, 0] + r_noise[0]
        s01 = p[0, h1]
        s11 = p[h1, h1] + r_noise[1]
        det = s00 * s11 - s01 * s01
        nis = (e0 * e0 * s11 - 2.0 * e0 * e1 * s01 + e1 * e1 * s00) / det
        out[O_E0] = e0
        out[O_E1] = e1
        out[O_S00] = s00
        out[O_S01] = s01
        out[O_S11] = s11
        out[O_NIS] = nis
        if nis > settings[S_GATE] and memo[M_GATED] < settings[S_MAX_GATED]:
            status = 1
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
            for i in range(3):
                model[i] = ws[W_VEC, V_BACKUP_MODEL, i]
            for k in range(N_OUTPUTS):
                out[k] = 0.0
            write_outputs(x, p, settings, 8, model[1], model[0], out)
            return 8
        memo[M_T_PREV] = t
        write_outputs(x, p, settings, status, r_model, vy_model, out)
        return status

    @numba.njit(cache=True)
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

    @numba.njit(cache=True)
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
            if status == 8:
                return DIVERGENCE_PENALTY
            if status > 1:
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


_predict_yaw_rate, _step_yaw_rate, _run_yaw_rate, _objective_yaw_rate = _make_kernels(4)
_predict_heading, _step_heading, _run_heading, _objective_heading = _make_kernels(5)

# Module-level entry points, one per state size: numba caches a function on disk only when it
# captures no compiled function in a closure, and a top-level entry caches its callees with it.


@numba.njit(cache=True)
def _predict_4(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN202
    _predict_yaw_rate(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)


@numba.njit(cache=True)
def _predict_5(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN202
    _predict_heading(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)


@numba.njit(cache=True)
def _step_4(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN202
            steering_rate, vy, psi, yaw_rate, ws, out):
    return _step_yaw_rate(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate,
                          vy, psi, yaw_rate, ws, out)


@numba.njit(cache=True)
def _step_5(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN202
            steering_rate, vy, psi, yaw_rate, ws, out):
    return _step_heading(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate,
                         vy, psi, yaw_rate, ws, out)


@numba.njit(cache=True)
def _run_4(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN202
    _run_yaw_rate(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


@numba.njit(cache=True)
def _run_5(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN202
    _run_heading(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


@numba.njit(cache=True)
def objective_4(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """objective_kernel for the 4-state (yaw_rate) filter; callable from compiled code."""
    return _objective_yaw_rate(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


@numba.njit(cache=True)
def objective_5(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """objective_kernel for the 5-state (heading) filter; callable from compiled code."""
    return _objective_heading(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


class Kernels(NamedTuple):
    """The compiled filter for one state size (numba compiles each lazily, on first call)."""

    predict: Any
    step: Any
    run: Any
    objective: Any


#: by state size: 5 = [vy, r, psi, Cf, Cr] (heading), 4 = [vy, r, Cf, Cr] (yaw_rate)
KERNELS = {4: Kernels(_predict_4, _step_4, _run_4, objective_4), 5: Kernels(_predict_5, _step_5, _run_5, objective_5)}


def predict(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN201
    """Prediction of eq. (12) in place: x <- f(x, u), model <- f(model, u); F = df/dx in ws[W_F].

    ``steering`` is the interval mean and ``steering_rate`` its slope: ``exact`` drives the ramp
    that starts at mean - rate dt / 2, ``euler`` holds the mean. ws: model.work_buffer().
    """
    KERNELS[x.shape[0]].predict(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)


def ekf_step(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN201
             steering_rate, vy, psi, yaw_rate, ws, out):
    """Process one epoch in place; return the StepStatus code. ``out`` receives one output row.

    x (n,), p (n, n): filter state and covariance; model (3,): open-loop model [vy, r, psi];
    memo (3,): [t_prev, initialised, consecutive gated]; q (n,), r_noise (2,): diag Q and R;
    ws: model.work_buffer(). ``speed`` and ``steering`` are means over the interval that ends
    at ``t``, ``steering_rate`` the slope of the steering over it; ``yaw_rate`` is the
    interval-mean yaw rate from heading increments.
    """
    return KERNELS[x.shape[0]].step(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,
                                    steering_rate, vy, psi, yaw_rate, ws, out)


def run_kernel(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN201
    """ekf_step over every row of ``epochs`` (columns E_*); one output row per epoch."""
    KERNELS[x.shape[0]].run(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


def objective_kernel(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """Tuning objective over a sequence: eq. 21 mean |innovation| (MAE) or Gaussian NLL.

    Only epochs with a predicted measurement (UPDATED or GATED) count. A diverging filter, or
    one that never predicts, scores DIVERGENCE_PENALTY.
    """
    return KERNELS[x.shape[0]].objective(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


@dataclass(frozen=True)
class Estimate:
    """What one epoch produced (Cf, Cr in N/rad per tire)."""

    t: float
    status: StepStatus
    lateral_velocity: float
    yaw_rate: float
    cornering_stiffness_front: float
    cornering_stiffness_rear: float
    cornering_stiffness_front_std: float
    cornering_stiffness_rear_std: float
    lateral_velocity_model: float
    yaw_rate_model: float
    innovation: tuple[float, float]
    innovation_covariance: tuple[float, float, float]  # S00, S01, S11
    normalized_innovation_squared: float

    @classmethod
    def from_row(cls, t: float, row: np.ndarray) -> Estimate:
        """Build from one kernel output row."""
        return cls(
            t=t,
            status=StepStatus(int(row[O_STATUS])),
            lateral_velocity=float(row[O_VY]),
            yaw_rate=float(row[O_R]),
            cornering_stiffness_front=float(row[O_CF]),
            cornering_stiffness_rear=float(row[O_CR]),
            cornering_stiffness_front_std=float(row[O_CF_STD]),
            cornering_stiffness_rear_std=float(row[O_CR_STD]),
            lateral_velocity_model=float(row[O_VY_MODEL]),
            yaw_rate_model=float(row[O_R_MODEL]),
            innovation=(float(row[O_E0]), float(row[O_E1])),
            innovation_covariance=(float(row[O_S00]), float(row[O_S01]), float(row[O_S11])),
            normalized_innovation_squared=float(row[O_NIS]),
        )


@dataclass(frozen=True)
class FilterArrays:
    """The numeric form of an EstimatorConfig for the compiled kernels."""

    vehicle: np.ndarray
    settings: np.ndarray
    process_noise: np.ndarray
    measurement_noise: np.ndarray
    initial_state: np.ndarray
    initial_covariance: np.ndarray

    @classmethod
    def from_config(cls, config: EstimatorConfig) -> FilterArrays:
        """Translate the parameters to the state's units and the kernels' layout."""
        options, noise = config.options, config.noise
        log_state = options.stiffness_state == "log"
        heading = options.measurement == "heading"
        to_state = math.log if log_state else float
        settings = np.zeros(N_SETTINGS)
        settings[S_METHOD] = EXACT if options.discretization == "exact" else EULER
        settings[S_LOG] = 1.0 if log_state else 0.0
        settings[S_HEADING] = 1.0 if heading else 0.0
        settings[S_MIN_SPEED] = options.min_speed
        settings[S_LOW] = to_state(options.stiffness_bounds[0])
        settings[S_HIGH] = to_state(options.stiffness_bounds[1])
        settings[S_GATE] = options.gate_threshold
        settings[S_MAX_GATED] = options.max_gated
        settings[S_MAX_INTERVAL] = options.max_interval
        settings[S_P0_VY] = noise.initial_covariance[0]
        settings[S_P0_R] = noise.initial_covariance[1]
        settings[S_P0_PSI] = noise.initial_heading_covariance
        q, p0 = _state_diagonals(noise, heading)
        x0 = np.zeros(len(q))
        x0[-2] = to_state(noise.initial_stiffness[0])
        x0[-1] = to_state(noise.initial_stiffness[1])
        return cls(
            vehicle=vehicle_array(config.vehicle),
            settings=settings,
            process_noise=q,
            measurement_noise=np.array(noise.measurement_noise, dtype=np.float64),
            initial_state=x0,
            initial_covariance=np.diag(p0),
        )


def _state_diagonals(noise: NoiseParams, heading: bool) -> tuple[np.ndarray, np.ndarray]:
    q, p0 = list(noise.process_noise), list(noise.initial_covariance)
    if heading:
        q.insert(2, noise.heading_process_noise)
        p0.insert(2, noise.initial_heading_covariance)
    return np.array(q, dtype=np.float64), np.array(p0, dtype=np.float64)


class JointEKF:
    """The joint-state EKF, stepped one epoch at a time (the node's view)."""

    def __init__(self, config: EstimatorConfig) -> None:
        self._config = config
        self._arrays = FilterArrays.from_config(config)
        self._ws = work_buffer()
        self._out = np.zeros(N_OUTPUTS)
        self.reset()

    @property
    def config(self) -> EstimatorConfig:
        """The parameters in force."""
        return self._config

    def reset(self) -> None:
        """Restart from the initial state (paper: x(0), P(0))."""
        self.state = self._arrays.initial_state.copy()
        self.covariance = self._arrays.initial_covariance.copy()
        self._model = np.zeros(3)
        self._memo = np.zeros(3)

    def set_noise(self, noise: NoiseParams) -> None:
        """Swap Q and R at run time; the state and covariance carry on."""
        config = EstimatorConfig(vehicle=self._config.vehicle, options=self._config.options, noise=noise)
        arrays = FilterArrays.from_config(config)
        self._config, self._arrays = config, arrays

    def step(self, epoch: Epoch) -> Estimate:
        """Filter one epoch (eq. 12) and return the estimate."""
        a = self._arrays
        ekf_step(self.state, self.covariance, self._model, self._memo, a.vehicle, a.settings,
                 a.process_noise, a.measurement_noise, epoch.t, epoch.speed, epoch.steering,
                 epoch.steering_rate, epoch.lateral_velocity, epoch.heading, epoch.yaw_rate, self._ws, self._out)
        return Estimate.from_row(epoch.t, self._out)


def run_sequence(config: EstimatorConfig, epochs: EpochArrays) -> np.ndarray:
    """Filter a whole epoch sequence; returns the (N, N_OUTPUTS) output rows."""
    a = FilterArrays.from_config(config)
    outputs = np.zeros((len(epochs), N_OUTPUTS))
    run_kernel(epochs.kernel_input(), a.initial_state.copy(), a.initial_covariance.copy(), np.zeros(3),
               np.zeros(3), a.vehicle, a.settings, a.process_noise, a.measurement_noise, outputs)
    return outputs


def sequence_objective(config: EstimatorConfig, epochs: EpochArrays, kind: str = "mae") -> float:
    """Tuning objective (``mae``: eq. 21, ``nll``: innovation negative log-likelihood)."""
    a = FilterArrays.from_config(config)
    code = MAE if kind == "mae" else NLL
    return float(objective_kernel(epochs.kernel_input(), a.initial_state.copy(), a.initial_covariance.copy(),
                                  np.zeros(3), np.zeros(3), a.vehicle, a.settings, a.process_noise,
                                  a.measurement_noise, code))
