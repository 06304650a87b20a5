"""The 2-DOF bicycle model (paper eq. 4) and its discretisations (eq. 10 and exact ZOH).

The model is stated once, as the augmented continuous matrix

    M(C) = [[A(Cf, Cr, vx), B(Cf), 0], [0, 0, 1], [0, 0, 0]]      (eq. 4, corrected eq. 1)

over the motion states [vy, r] (plus heading psi with psi' = r in heading mode), the steering
angle delta and its rate. Over one GNSS interval the steering is a ramp (the least-squares
line through the faster steering stream); a constant delta is the special case of rate 0.
A discretisation maps M to E(dt), x_{k+1} = E[:n, :n] x_k + E[:n, n] delta_start + E[:n, n+1]
delta_rate:

* ``exact``: E = expm(M dt), exact for the ramp input (Taylor series, scaling and squaring);
* ``euler``: E = I + M dt, the paper's first-order difference quotient (eq. 10), which holds
  the interval-mean steering.

The stiffness derivatives dE/dtheta that form the Jacobian columns of eq. (13) are carried
exactly through the same recursion (forward-mode differentiation of the series), so the
exact model has an exact Jacobian. The A23 erratum of eq. (13) does not arise: the Jacobian
follows from M. ``theta`` is ln C (``log``) or C (``linear``).

Everything here is numba-compiled scalar code on preallocated buffers: it is the tuner's hot
loop. Vehicle constants are passed as ``vehicle_array = [mass, lf, lr, iz]``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .parameters import VehicleParams

TAYLOR_ORDER = 10
SCALING_NORM = 0.5

# discretisation codes
EXACT = 0
EULER = 1


def vehicle_array(vehicle: VehicleParams) -> np.ndarray:
    """Pack the vehicle constants for the compiled kernels."""
    return np.array([vehicle.mass, vehicle.lf, vehicle.lr, vehicle.yaw_inertia], dtype=np.float64)


@numba.njit(cache=True)
def continuous_matrix(cf, cr, vx, vehicle, with_heading, m, dm_front, dm_rear):  # noqa: ANN001, ANN201
    """Fill M (eq. 4) and dM/dCf, dM/dCr over [motion states, delta, d delta/dt].

    Size nd + 2 with nd = 3 (vy, r, psi) in heading mode, else 2 (vy, r). The steering angle
    is an extra state whose derivative is the (constant) steering rate, so one matrix
    exponential yields the response to a steering ramp over the interval.
    """
    mass, lf, lr, iz = vehicle[0], vehicle[1], vehicle[2], vehicle[3]
    nd = 3 if with_heading else 2
    size = nd + 2
    for i in range(size):
        for j in range(size):
            m[i, j] = 0.0
            dm_front[i, j] = 0.0
            dm_rear[i, j] = 0.0
    u = nd  # steering column
    a = 2.0 / (mass * vx)
    b = 2.0 / (iz * vx)
    m[0, 0] = -(cf + cr) * a
    m[0, 1] = -vx - (cf * lf - cr * lr) * a
    m[1, 0] = (cr * lr - cf * lf) * b
    m[1, 1] = -(lf * lf * cf + lr * lr * cr) * b
    m[0, u] = 2.0 * cf / mass
    m[1, u] = 2.0 * cf * lf / iz
    m[u, u + 1] = 1.0
    dm_front[0, 0] = -a
    dm_front[0, 1] = -lf * a
    dm_front[1, 0] = -lf * b
    dm_front[1, 1] = -lf * lf * b
    dm_front[0, u] = 2.0 / mass
    dm_front[1, u] = 2.0 * lf / iz
    dm_rear[0, 0] = -a
    dm_rear[0, 1] = lr * a
    dm_rear[1, 0] = lr * b
    dm_rear[1, 1] = -lr * lr * b
    if with_heading:
        m[2, 1] = 1.0


@numba.njit(cache=True)
def _mul_top(left, right, out, nd, in00, in01, in11, accumulate):  # noqa: ANN001, ANN201
    """out[:nd] (+)= (left @ right)[:nd] where right's input rows are [[0, in00, in01], [0, 0, in11]]."""
    u = nd
    for i in range(nd):
        for j in range(nd + 2):
            acc = 0.0
            for k in range(nd):
                acc += left[i, k] * right[k, j]
            if j == u:
                acc += left[i, u] * in00
            elif j == u + 1:
                acc += left[i, u] * in01 + left[i, u + 1] * in11
            if accumulate:
                out[i, j] += acc
            else:
                out[i, j] = acc


@numba.njit(cache=True)
def discretize(cf, cr, dcf_dtheta, dcr_dtheta, vx, dt, vehicle, with_heading, method, ws):  # noqa: ANN001, ANN201
    """Discretise eq. (4) over dt: E, dE/dtheta_f, dE/dtheta_r in ws[0:3] (rows < nd valid).

    x_{k+1} = E[:nd, :nd] x_k + E[:nd, nd] delta_start + E[:nd, nd+1] steering_rate.
    ``exact``: E = expm(M dt) (Taylor series, scaling and squaring, derivatives carried
    through both); ``euler``: E = I + M dt (eq. 10; the steering-rate column is then 0).
    ws is a (>= 12, 5, 5) work buffer.
    """
    nd = 3 if with_heading else 2
    size = nd + 2
    e, de_f, de_r = ws[0], ws[1], ws[2]
    m, dm_f, dm_r = ws[3], ws[4], ws[5]
    continuous_matrix(cf, cr, vx, vehicle, with_heading, m, dm_f, dm_r)
    for i in range(nd):
        for j in range(size):
            dm_f[i, j] *= dcf_dtheta
            dm_r[i, j] *= dcr_dtheta
    if method == EULER:
        for i in range(nd):
            for j in range(size):
                e[i, j] = (1.0 if i == j else 0.0) + m[i, j] * dt
                de_f[i, j] = dm_f[i, j] * dt
                de_r[i, j] = dm_r[i, j] * dt
            e[i, nd + 1] = 0.0
        return
    norm = 0.0
    for i in range(nd):
        row = 0.0
        for j in range(nd + 1):
            row += abs(m[i, j])
        norm = max(norm, row)
    squarings = 0
    while norm * dt / (1 << squarings) > SCALING_NORM:
        squarings += 1
    h = dt / (1 << squarings)
    for i in range(nd):
        for j in range(size):
            m[i, j] *= h
            dm_f[i, j] *= h
            dm_r[i, j] *= h
    t, dt_f, dt_r = ws[6], ws[7], ws[8]
    nt, ndt_f, ndt_r = ws[9], ws[10], ws[11]
    for i in range(nd):
        for j in range(size):
            one = 1.0 if i == j else 0.0
            e[i, j] = one + m[i, j]
            de_f[i, j] = dm_f[i, j]
            de_r[i, j] = dm_r[i, j]
            t[i, j] = m[i, j]
            dt_f[i, j] = dm_f[i, j]
            dt_r[i, j] = dm_r[i, j]
    for order in range(2, TAYLOR_ORDER + 1):
        inv = 1.0 / order
        _mul_top(t, m, nt, nd, 0.0, h, 0.0, False)
        _mul_top(dt_f, m, ndt_f, nd, 0.0, h, 0.0, False)
        _mul_top(t, dm_f, ndt_f, nd, 0.0, 0.0, 0.0, True)
        _mul_top(dt_r, m, ndt_r, nd, 0.0, h, 0.0, False)
        _mul_top(t, dm_r, ndt_r, nd, 0.0, 0.0, 0.0, True)
        for i in range(nd):
            for j in range(size):
                t[i, j] = nt[i, j] * inv
                dt_f[i, j] = ndt_f[i, j] * inv
                dt_r[i, j] = ndt_r[i, j] * inv
                e[i, j] += t[i, j]
                de_f[i, j] += dt_f[i, j]
                de_r[i, j] += dt_r[i, j]
    span = h
    for _ in range(squarings):
        _mul_top(e, e, nt, nd, 1.0, span, 1.0, False)
        _mul_top(de_f, e, ndt_f, nd, 1.0, span, 1.0, False)
        _mul_top(e, de_f, ndt_f, nd, 0.0, 0.0, 0.0, True)
        _mul_top(de_r, e, ndt_r, nd, 1.0, span, 1.0, False)
        _mul_top(e, de_r, ndt_r, nd, 0.0, 0.0, 0.0, True)
        for i in range(nd):
            for j in range(size):
                e[i, j] = nt[i, j]
                de_f[i, j] = ndt_f[i, j]
                de_r[i, j] = ndt_r[i, j]
        span *= 2.0


def discrete_matrices(
    vehicle: VehicleParams,
    cornering_stiffness_front: float,
    cornering_stiffness_rear: float,
    speed: float,
    dt: float,
    *,
    method: str = "exact",
    with_heading: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Discrete state matrix Phi and input vector Gamma of eq. (4) (a convenience for tests and plots)."""
    ws = np.zeros((12, 5, 5))
    code = EXACT if method == "exact" else EULER
    discretize(cornering_stiffness_front, cornering_stiffness_rear, 1.0, 1.0, speed, dt,
               vehicle_array(vehicle), with_heading, code, ws)
    nd = 3 if with_heading else 2
    return ws[0, :nd, :nd].copy(), ws[0, :nd, nd].copy()


def steady_state_yaw_rate(vehicle: VehicleParams, cf: float, cr: float, speed: float, steering: float) -> float:
    """Steady-state yaw rate of eq. (4) for a constant steering angle."""
    ws = np.zeros((12, 5, 5))
    continuous_matrix(cf, cr, speed, vehicle_array(vehicle), False, ws[3], ws[4], ws[5])
    a, b = ws[3, :2, :2], ws[3, :2, 2]
    return float(np.linalg.solve(a, -b * steering)[1])


def euler_stability_limit(vehicle: VehicleParams, speed: float, dt: float) -> float:
    """Rough Cf + Cr below which eq. (10) is stable: 2 m vx / dt (DESIGN.md section 1)."""
    return 2.0 * vehicle.mass * speed / dt if math.isfinite(dt) and dt > 0 else math.inf
