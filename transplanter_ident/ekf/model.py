"""The 2-DOF bicycle model (paper eq. 4) and its discretisations (eq. 10 and exact ZOH).

The model is stated once, as the augmented continuous matrix

    M(C) = [[A(Cf, Cr, vx), B(Cf), 0], [0, 0, 1], [0, 0, 0]]      (eq. 4, corrected eq. 1)

over the motion states [vy, r] (plus heading psi with psi' = r in heading mode; in course mode the antenna's
course, :func:`course_row`), the steering
angle delta and its rate. With a tire relaxation length sigma (beyond the paper) each axle's force
builds over sigma of travel, F' = (vx / sigma) (C alpha - F); the model then carries the slip lags
d = alpha - F / C of both axles after the motion states (d' = alpha' - (vx / sigma) d, zero in a
steady turn), and eq. 4's forces become C (alpha - d). Over one GNSS interval the steering is a ramp (the least-squares
line through the faster steering stream); a constant delta is the special case of rate 0.
A discretisation maps M to E(dt), x_{k+1} = E[:n, :n] x_k + E[:n, n] delta_start + E[:n, n+1]
delta_rate:

* ``exact``: E = expm(M dt), exact for the ramp input (Taylor series, scaling and squaring);
* ``euler``: E = I + M dt, the paper's first-order difference quotient (eq. 10), which holds
  the interval-mean steering.

The stiffness derivatives dE/dtheta that form the Jacobian columns of eq. (13) are carried
exactly through the same recursion (forward-mode differentiation of the series), so the
exact model has an exact Jacobian. So is dE/dvx: the speed is a measured input, and its noise
enters Q through it (kernels.py). The A23 erratum of eq. (13) does not arise: the Jacobian
follows from M. ``theta`` is ln C (``log``) or C (``linear``).

Everything here is numba-compiled scalar code on preallocated buffers: it is the tuner's hot
loop. Vehicle constants are passed as ``vehicle_array = [mass, lf, lr, iz]``.
"""

from __future__ import annotations

import numpy as np

from transplanter_ident.config.parameters import VehicleParams
from transplanter_ident.ekf.layout import (
    EULER,
    EXACT,
    N_LAG,
    N_MOTION_HEADING,
    N_MOTION_YAW_RATE,
    VEH_ANTENNA_X,
    VEH_COURSE,
    VEH_IZ,
    VEH_LF,
    VEH_LR,
    VEH_MASS,
    W_DE_F,
    W_DE_R,
    W_DE_V,
    W_DM_F,
    W_DM_R,
    W_DM_V,
    W_DT_F,
    W_DT_R,
    W_DT_V,
    W_E,
    W_M,
    W_NDT_F,
    W_NDT_R,
    W_NDT_V,
    W_NT,
    W_T,
    WORK_SIZE,
    WORK_SLOTS,
)
from transplanter_ident.jit import entry_kernel, inline_kernel, sized_kernel

TAYLOR_ORDER = 10
SCALING_NORM = 0.5


def vehicle_array(vehicle: VehicleParams, course: bool = False) -> np.ndarray:
    """Pack the vehicle constants for the compiled kernels (layout.VEH_*); ``course``: a single antenna's heading state."""
    return np.array([vehicle.mass, vehicle.lf, vehicle.lr, vehicle.yaw_inertia, vehicle.relaxation_length,
                     1.0 if course else 0.0, vehicle.antenna_x, vehicle.antenna_y], dtype=np.float64)


def work_buffer() -> np.ndarray:
    """A work buffer (layout.W_*) for the kernels of this module and of kernels.py; one buffer, no per-step views."""
    return np.zeros((WORK_SLOTS, WORK_SIZE, WORK_SIZE))


@inline_kernel
def continuous_matrix(cf, cr, vx, vehicle, with_heading, lagged, relaxation, ws):
    """Fill M (eq. 4) and dM/dCf, dM/dCr, dM/dvx over [motion states, (d_f, d_r), delta, d delta/dt] in ws.

    Size nd + 2 with nd = 3 (vy, r, psi) in heading mode, else 2 (vy, r), plus N_LAG ``lagged``
    (the slip lags of tires that relax over ``relaxation`` m; 0: their rows and columns stay zero,
    the lags held and the forces as in eq. 4). The steering angle
    is an extra state whose derivative is the (constant) steering rate, so one matrix
    exponential yields the response to a steering ramp over the interval. The discretisation
    reads only rows < nd (``mul_top`` takes the input rows [[0, 1], [0, 0]] as arguments).
    """
    mass, lf, lr, iz = vehicle[VEH_MASS], vehicle[VEH_LF], vehicle[VEH_LR], vehicle[VEH_IZ]
    nd = (N_MOTION_HEADING if with_heading else N_MOTION_YAW_RATE) + (N_LAG if lagged else 0)
    for i in range(nd + 2):  # M is (nd + 2) square; the rest of the slot is not part of it
        for j in range(nd + 2):
            ws[W_M, i, j] = 0.0
            ws[W_DM_F, i, j] = 0.0
            ws[W_DM_R, i, j] = 0.0
            ws[W_DM_V, i, j] = 0.0
    u = nd  # steering column
    a = 2.0 / (mass * vx)
    b = 2.0 / (iz * vx)
    ws[W_M, 0, 0] = -(cf + cr) * a
    ws[W_M, 0, 1] = -vx - (cf * lf - cr * lr) * a
    ws[W_M, 1, 0] = (cr * lr - cf * lf) * b
    ws[W_M, 1, 1] = -(lf * lf * cf + lr * lr * cr) * b
    ws[W_M, 0, u] = 2.0 * cf / mass
    ws[W_M, 1, u] = 2.0 * cf * lf / iz
    ws[W_M, u, u + 1] = 1.0
    ws[W_DM_F, 0, 0] = -a
    ws[W_DM_F, 0, 1] = -lf * a
    ws[W_DM_F, 1, 0] = -lf * b
    ws[W_DM_F, 1, 1] = -lf * lf * b
    ws[W_DM_F, 0, u] = 2.0 / mass
    ws[W_DM_F, 1, u] = 2.0 * lf / iz
    ws[W_DM_R, 0, 0] = -a
    ws[W_DM_R, 0, 1] = lr * a
    ws[W_DM_R, 1, 0] = lr * b
    ws[W_DM_R, 1, 1] = -lr * lr * b
    for i in range(2):  # the tire terms go as 1 / vx; the kinematic -vx r term as vx
        for j in range(2):
            ws[W_DM_V, i, j] = -ws[W_M, i, j] / vx
    ws[W_DM_V, 0, 1] = -1.0 + (cf * lf - cr * lr) * a / vx
    if lagged and relaxation > 0.0:
        lag_rows(cf, cr, vx, lf, lr, mass, iz, relaxation, nd - N_LAG, ws)
    if with_heading and vehicle[VEH_COURSE] > 0.5:
        course_row(vx, vehicle[VEH_ANTENNA_X], nd, ws)
    if with_heading:
        ws[W_M, 2, 1] += 1.0


@inline_kernel
def course_row(vx, antenna_x, nd, ws):
    """Row 2 as the antenna's course: chi = psi + (vy + antenna_x r) / vx, so chi' = r + (vy' + antenna_x r') / vx.

    A single antenna measures the direction of its velocity only; with the heading state taken as that
    course the measurement stays one state (z = chi), and the stiffness enters its row through vy' and r'
    (rows 0 and 1, over every column: motion, lags, delta, delta'). The speed is the interval's constant.
    """
    for j in range(nd + 2):
        for slot in (W_M, W_DM_F, W_DM_R, W_DM_V):
            ws[slot, 2, j] = (ws[slot, 0, j] + antenna_x * ws[slot, 1, j]) / vx
        ws[W_DM_V, 2, j] -= ws[W_M, 2, j] / vx  # d/dvx of (row / vx): (d row / dvx) / vx - row / vx^2


@inline_kernel
def lag_rows(cf, cr, vx, lf, lr, mass, iz, sigma, first, ws):
    """The slip lags' columns in the force rows and their own rows (d_f at ``first``, d_r after it).

    The forces are 2 C (alpha - d); d' = alpha' - (vx / sigma) d with alpha_f = delta - (vy + lf r) / vx
    and alpha_r = (lr r - vy) / vx, so d's rows are those combinations of the vy and r rows (over
    every column: d, delta) plus delta' (front) and -vx / sigma on the diagonal.
    """
    f, r = first, first + 1
    ws[W_M, 0, f], ws[W_M, 0, r] = -2.0 * cf / mass, -2.0 * cr / mass
    ws[W_M, 1, f], ws[W_M, 1, r] = -2.0 * cf * lf / iz, 2.0 * cr * lr / iz
    ws[W_DM_F, 0, f], ws[W_DM_F, 1, f] = -2.0 / mass, -2.0 * lf / iz
    ws[W_DM_R, 0, r], ws[W_DM_R, 1, r] = -2.0 / mass, 2.0 * lr / iz
    for j in range(first + 4):  # every column: motion, lags, delta, delta' (rows 0, 1 are complete)
        for slot in (W_M, W_DM_F, W_DM_R, W_DM_V):
            ws[slot, f, j] = -(ws[slot, 0, j] + lf * ws[slot, 1, j]) / vx
            ws[slot, r, j] = (lr * ws[slot, 1, j] - ws[slot, 0, j]) / vx
        ws[W_DM_V, f, j] -= ws[W_M, f, j] / vx  # d/dvx of (row / vx): (d row / dvx) / vx - row / vx^2
        ws[W_DM_V, r, j] -= ws[W_M, r, j] / vx
    ws[W_M, f, first + 3] += 1.0  # alpha_f' holds delta'
    ws[W_M, f, f] -= vx / sigma
    ws[W_M, r, r] -= vx / sigma
    ws[W_DM_V, f, f] -= 1.0 / sigma
    ws[W_DM_V, r, r] -= 1.0 / sigma


def _make_discretize(motion, lagged):
    """Compile the discretisation for ``motion`` states (and the slip lags): sizes become compile-time constants."""
    nd = motion + (N_LAG if lagged else 0)  # the rows the filter's state carries
    size = nd + 2

    @inline_kernel
    def mul_top(ws, left, right, out, in00, in01, in11, accumulate):
        """ws[out][:nd] (+)= (ws[left] @ ws[right])[:nd]; right's input rows [[in00, in01], [0, in11]]."""
        for i in range(nd):
            for j in range(size):
                acc = 0.0
                for k in range(nd):
                    acc += ws[left, i, k] * ws[right, k, j]
                if j == nd:
                    acc += ws[left, i, nd] * in00
                elif j == nd + 1:
                    acc += ws[left, i, nd] * in01 + ws[left, i, nd + 1] * in11
                if accumulate:
                    ws[out, i, j] += acc
                else:
                    ws[out, i, j] = acc

    @inline_kernel
    def product_rule(ws, left, left_f, left_r, left_v, right, right_f, right_r, right_v, in00, in01, in11, with_v):
        """N = L R and dN = dL R + L dR for both stiffnesses (and the speed if ``with_v``) into W_NT, W_NDT_*.

        [[in00, in01], [0, in11]] are R's input rows; dR's are zero (they hold no stiffness).
        """
        mul_top(ws, left, right, W_NT, in00, in01, in11, False)
        mul_top(ws, left_f, right, W_NDT_F, in00, in01, in11, False)
        mul_top(ws, left, right_f, W_NDT_F, 0.0, 0.0, 0.0, True)
        mul_top(ws, left_r, right, W_NDT_R, in00, in01, in11, False)
        mul_top(ws, left, right_r, W_NDT_R, 0.0, 0.0, 0.0, True)
        if with_v:
            mul_top(ws, left_v, right, W_NDT_V, in00, in01, in11, False)
            mul_top(ws, left, right_v, W_NDT_V, 0.0, 0.0, 0.0, True)

    @sized_kernel
    def discretize_fixed(cf, cr, dcf_dtheta, dcr_dtheta, vx, dt, vehicle, method, with_v, relaxation, ws):
        continuous_matrix(cf, cr, vx, vehicle, motion == N_MOTION_HEADING, lagged, relaxation, ws)
        for i in range(nd):
            for j in range(size):
                ws[W_DM_F, i, j] *= dcf_dtheta
                ws[W_DM_R, i, j] *= dcr_dtheta
        if method == EULER:
            for i in range(nd):
                for j in range(size):
                    ws[W_E, i, j] = (1.0 if i == j else 0.0) + ws[W_M, i, j] * dt
                    ws[W_DE_F, i, j] = ws[W_DM_F, i, j] * dt
                    ws[W_DE_R, i, j] = ws[W_DM_R, i, j] * dt
                    ws[W_DE_V, i, j] = ws[W_DM_V, i, j] * dt
                ws[W_E, i, nd + 1] = 0.0
            return
        norm = 0.0
        for i in range(nd):
            row = 0.0
            for j in range(nd + 1):
                row += abs(ws[W_M, i, j])
            norm = max(norm, row)
        squarings = 0
        while norm * dt / (1 << squarings) > SCALING_NORM:
            squarings += 1
        h = dt / (1 << squarings)
        for i in range(nd):
            for j in range(size):
                ws[W_M, i, j] *= h
                ws[W_DM_F, i, j] *= h
                ws[W_DM_R, i, j] *= h
                ws[W_DM_V, i, j] *= h
                one = 1.0 if i == j else 0.0
                ws[W_E, i, j] = one + ws[W_M, i, j]
                ws[W_DE_F, i, j] = ws[W_DM_F, i, j]
                ws[W_DE_R, i, j] = ws[W_DM_R, i, j]
                ws[W_DE_V, i, j] = ws[W_DM_V, i, j]
                ws[W_T, i, j] = ws[W_M, i, j]
                ws[W_DT_F, i, j] = ws[W_DM_F, i, j]
                ws[W_DT_R, i, j] = ws[W_DM_R, i, j]
                ws[W_DT_V, i, j] = ws[W_DM_V, i, j]
        for order in range(2, TAYLOR_ORDER + 1):  # T_k = T_{k-1} X / k, dT_k = (dT_{k-1} X + T_{k-1} dX) / k
            inv = 1.0 / order
            product_rule(ws, W_T, W_DT_F, W_DT_R, W_DT_V, W_M, W_DM_F, W_DM_R, W_DM_V, 0.0, h, 0.0, with_v)
            for i in range(nd):
                for j in range(size):
                    ws[W_T, i, j] = ws[W_NT, i, j] * inv
                    ws[W_DT_F, i, j] = ws[W_NDT_F, i, j] * inv
                    ws[W_DT_R, i, j] = ws[W_NDT_R, i, j] * inv
                    ws[W_DT_V, i, j] = ws[W_NDT_V, i, j] * inv
                    ws[W_E, i, j] += ws[W_T, i, j]
                    ws[W_DE_F, i, j] += ws[W_DT_F, i, j]
                    ws[W_DE_R, i, j] += ws[W_DT_R, i, j]
                    ws[W_DE_V, i, j] += ws[W_DT_V, i, j]
        span = h
        for _ in range(squarings):  # E <- E E, dE <- dE E + E dE
            product_rule(ws, W_E, W_DE_F, W_DE_R, W_DE_V, W_E, W_DE_F, W_DE_R, W_DE_V, 1.0, span, 1.0, with_v)
            for i in range(nd):
                for j in range(size):
                    ws[W_E, i, j] = ws[W_NT, i, j]
                    ws[W_DE_F, i, j] = ws[W_NDT_F, i, j]
                    ws[W_DE_R, i, j] = ws[W_NDT_R, i, j]
                    ws[W_DE_V, i, j] = ws[W_NDT_V, i, j]
            span *= 2.0

    return discretize_fixed


discretize_yaw_rate = _make_discretize(N_MOTION_YAW_RATE, False)
discretize_heading = _make_discretize(N_MOTION_HEADING, False)
discretize_yaw_rate_lagged = _make_discretize(N_MOTION_YAW_RATE, True)
discretize_heading_lagged = _make_discretize(N_MOTION_HEADING, True)


@entry_kernel
def discretize(cf, cr, dcf_dtheta, dcr_dtheta, vx, dt, vehicle, with_heading, method, with_v, ws):
    """Discretise eq. (4) over dt: E, dE/dtheta_f, dE/dtheta_r, dE/dvx in ws[W_E], ws[W_DE_F], ws[W_DE_R], ws[W_DE_V].

    x_{k+1} = E[:nd, :nd] x_k + E[:nd, nd] delta_start + E[:nd, nd+1] steering_rate (rows < nd
    valid). ``exact``: E = expm(M dt) (Taylor series, scaling and squaring, derivatives carried
    through both); ``euler``: E = I + M dt (eq. 10; the steering-rate column is then 0). dE/dvx only
    ``with_v`` (the speed's noise in Q); else ws[W_DE_V] holds nothing meaningful. ws: :func:`work_buffer`.
    """
    if with_heading:
        discretize_heading(cf, cr, dcf_dtheta, dcr_dtheta, vx, dt, vehicle, method, with_v, 0.0, ws)
    else:
        discretize_yaw_rate(cf, cr, dcf_dtheta, dcr_dtheta, vx, dt, vehicle, method, with_v, 0.0, ws)


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
    ws = work_buffer()
    code = EXACT if method == "exact" else EULER
    discretize(cornering_stiffness_front, cornering_stiffness_rear, 1.0, 1.0, speed, dt,
               vehicle_array(vehicle), with_heading, code, False, ws)
    nd = N_MOTION_HEADING if with_heading else N_MOTION_YAW_RATE
    return ws[W_E, :nd, :nd].copy(), ws[W_E, :nd, nd].copy()


def steady_state_yaw_rate(vehicle: VehicleParams, cf: float, cr: float, speed: float, steering: float) -> float:
    """Steady-state yaw rate of eq. (4) for a constant steering angle."""
    ws = work_buffer()
    continuous_matrix(cf, cr, speed, vehicle_array(vehicle), False, False, 0.0, ws)
    a, b = ws[W_M, :2, :2], ws[W_M, :2, 2]
    return float(np.linalg.solve(a, -b * steering)[1])
