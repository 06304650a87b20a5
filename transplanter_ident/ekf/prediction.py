"""The prediction of eq. (12): the state and the open-loop model over one GNSS interval (eqs. 4, 10, 13).

:func:`make_prediction` compiles, for one state size, the three helpers of the filter step
(:mod:`.kernels`) that know what the motion states are: their reset from a measurement, the
stiffness a state holds, and the prediction through :mod:`.model`'s discretisation, with its
Jacobian F = df/dx (eq. 13) and df/dvx, (``predict_inertia_gain``) df/d ln Iz, and (``course_model_speed``)
a single antenna's forward speed from a trial of the motion over the interval. With relaxing tires the slip
lags d_f, d_r follow the motion states (layout.N_LAG).
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.layout import (
    B_INERTIA,
    B_VEHICLE,
    EULER,
    HEADING_STATES,
    N_LAG,
    N_MOTION_HEADING,
    N_MOTION_YAW_RATE,
    N_VEHICLE,
    S_ANTENNA_X,
    S_INERTIA_UNCERTAINTY,
    S_LOG,
    S_METHOD,
    S_P0_PSI,
    S_P0_R,
    S_P0_VY,
    S_SPEED_NOISE,
    V_NEW_MODEL,
    V_NEW_X,
    V_SPEED_GAIN,
    VEH_IZ,
    VEH_LF,
    VEH_LR,
    W_BIAS,
    W_DE_F,
    W_DE_R,
    W_DE_V,
    W_E,
    W_F,
    W_VEC,
    X_PSI,
    X_R,
    X_VY,
    YAW_RATE_STATES,
)
from transplanter_ident.ekf.measurement_row import course_speed
from transplanter_ident.ekf.model import (
    discretize_heading,
    discretize_heading_lagged,
    discretize_yaw_rate,
    discretize_yaw_rate_lagged,
)
from transplanter_ident.jit import inline_kernel

#: the relative step of Iz in the difference quotient of ``predict_inertia_gain``
INERTIA_STEP = 1.0e-4


def make_prediction(heading, lagged):  # noqa: ANN001, ANN201 - numba closures
    """The step's prediction helpers for one measurement mode, with or without lags.

    (reset_motion, stiffness, predict_n, carry_lags, add_lag_noise, predict_inertia_gain).
    """
    lag = N_LAG if lagged else 0
    n = (HEADING_STATES if heading else YAW_RATE_STATES) + lag
    nd = (N_MOTION_HEADING if heading else N_MOTION_YAW_RATE) + lag  # motion states and slip lags
    nf, nr, nb, ng = nd, nd + 1, nd + 2, nd + 3  # theta_f, theta_r, steering offset, its gain's error
    if lagged:
        discretize_n = discretize_heading_lagged if heading else discretize_yaw_rate_lagged
    else:
        discretize_n = discretize_heading if heading else discretize_yaw_rate

    @inline_kernel
    def reset_motion(x, p, model, settings, vy_antenna, psi, yaw_rate):
        """Take the motion states from the measurement, slip lags 0 (a steady turn); keep the parameter states."""
        vy = vy_antenna - settings[S_ANTENNA_X] * yaw_rate
        x[X_VY] = vy
        x[X_R] = yaw_rate
        model[X_VY] = vy
        model[X_R] = yaw_rate
        model[X_PSI] = psi
        if heading:
            x[X_PSI] = psi
        for i in range(nd - lag, nd):
            x[i] = 0.0
            model[i] = 0.0
        for i in range(nd):
            for j in range(n):
                p[i, j] = 0.0
                p[j, i] = 0.0
        p[X_VY, X_VY] = settings[S_P0_VY]
        p[X_R, X_R] = settings[S_P0_R]
        if heading:
            p[X_PSI, X_PSI] = settings[S_P0_PSI]

    @inline_kernel
    def wheel_ramp(x, sensor, sensor_rate):
        """The wheel angle's ramp over the interval from the sensor's: (1 + g) sensor - b, and (1 + g) its rate."""
        gain = 1.0 + x[ng]
        return gain * sensor - x[nb], gain * sensor_rate

    @inline_kernel
    def stiffness(x, settings, k):
        """C of theta_f (k = 0) or theta_r (k = 1), and dC/dtheta."""
        if settings[S_LOG] > 0.5:
            c = math.exp(x[nf + k])
            return c, c
        return x[nf + k], 1.0

    @inline_kernel
    def ramp_start(steering, steering_rate, dt, method):
        """The sensor's angle the interval's ramp starts from: the mean minus rate dt / 2 (``exact``), the mean (``euler``)."""
        return steering if method == EULER else steering - 0.5 * dt * steering_rate

    @inline_kernel
    def predict_n(x, model, vehicle, settings, dt, speed, steering, steering_rate, relaxation, ws):
        """X <- f(x, u), model <- f(model, u); F = df/dx into ws[W_F], df/dvx into ws[W_VEC, V_SPEED_GAIN].

        The wheel angle is the sensor's times 1 + g minus the offset b: a ramp from (1 + g) (mean - rate dt / 2) - b
        (``exact``) or the held (1 + g) mean - b (``euler``), so df/db = -E[:, delta] and df/dg = E[:, delta] sensor
        + E[:, delta_rate] rate. ``relaxation``: the tires' relaxation length the slip lags follow (0: held, the
        forces as in eq. 4).
        """
        cf, dcf = stiffness(x, settings, 0)
        cr, dcr = stiffness(x, settings, 1)
        method = int(settings[S_METHOD])
        speed_noise = settings[S_SPEED_NOISE] > 0.5  # dx/dvx only when the speed's noise enters Q
        discretize_n(cf, cr, dcf, dcr, speed, dt, vehicle, method, speed_noise, relaxation, ws)
        sensor = ramp_start(steering, steering_rate, dt, method)
        level, rate = wheel_ramp(x, sensor, steering_rate)
        for i in range(nd, n):  # the parameter rows (random walks); the motion rows are written below
            for j in range(n):
                ws[W_F, i, j] = 1.0 if i == j else 0.0
        for i in range(nd):
            acc = ws[W_E, i, nd] * level + ws[W_E, i, nd + 1] * rate
            acc_f = ws[W_DE_F, i, nd] * level + ws[W_DE_F, i, nd + 1] * rate
            acc_r = ws[W_DE_R, i, nd] * level + ws[W_DE_R, i, nd + 1] * rate
            acc_v = ws[W_DE_V, i, nd] * level + ws[W_DE_V, i, nd + 1] * rate
            acc_m = acc
            for j in range(nd):
                acc += ws[W_E, i, j] * x[j]
                acc_f += ws[W_DE_F, i, j] * x[j]
                acc_r += ws[W_DE_R, i, j] * x[j]
                acc_v += ws[W_DE_V, i, j] * x[j]
                acc_m += ws[W_E, i, j] * model[j]
                ws[W_F, i, j] = ws[W_E, i, j]
            ws[W_F, i, nf] = acc_f
            ws[W_F, i, nr] = acc_r
            ws[W_F, i, nb] = -ws[W_E, i, nd]
            ws[W_F, i, ng] = ws[W_E, i, nd] * sensor + ws[W_E, i, nd + 1] * steering_rate
            ws[W_F, i, n - 1] = 0.0  # h, the heading's misalignment: in the vy measurement only
            ws[W_VEC, V_NEW_X, i], ws[W_VEC, V_NEW_MODEL, i] = acc, acc_m
            ws[W_VEC, V_SPEED_GAIN, i] = acc_v if speed_noise else 0.0
        for i in range(nd):
            x[i] = ws[W_VEC, V_NEW_X, i]
            model[i] = ws[W_VEC, V_NEW_MODEL, i]

    @inline_kernel
    def carry_lags(x, p, model, previous_speed, speed, vehicle):
        """The slip lags at a new interval's speed: the force F = C (alpha - d) carries on, alpha does not.

        alpha_f = delta - (vy + lf r) / vx and alpha_r = (lr r - vy) / vx change with 1 / vx, so d changes
        by as much: d_f += (vy + lf r) c, d_r += (vy - lr r) c with c = 1 / previous_speed - 1 / speed, in
        x, in the open-loop model and in P (P = T P T^T for that linear map T).
        """
        c = 1.0 / previous_speed - 1.0 / speed
        first = nd - lag
        arms = (vehicle[VEH_LF], -vehicle[VEH_LR])
        for a in range(lag):
            x[first + a] += c * (x[X_VY] + arms[a] * x[X_R])
            model[first + a] += c * (model[X_VY] + arms[a] * model[X_R])
            for j in range(n):  # T P: the lag rows take c (row vy + arm row r)
                p[first + a, j] += c * (p[X_VY, j] + arms[a] * p[X_R, j])
        for a in range(lag):
            for i in range(n):  # (T P) T^T: the lag columns likewise
                p[i, first + a] += c * (p[i, X_VY] + arms[a] * p[i, X_R])

    @inline_kernel
    def add_lag_noise(p, q, dt, speed, vehicle):
        """The motion noise's share of the slip lags: P += G Q dt G^T - Q dt, G = [I; g] over [vy, r].

        A disturbance that changes vy or r changes the slip at once and the force only over the lag,
        so it moves d = alpha - F / C with it: d_f by -(dvy + lf dr) / vx, d_r by (lr dr - dvy) / vx
        (g). The [vy, r] block itself is propagate_covariance's; this adds the lag rows and columns.
        """
        lf, lr = vehicle[VEH_LF], vehicle[VEH_LR]
        first = nd - lag
        g_vy = (-1.0 / speed, -1.0 / speed)  # d_f, d_r per unit vy disturbance
        g_r = (-lf / speed, lr / speed)
        q_vy, q_r = q[X_VY] * dt, q[X_R] * dt
        for a in range(lag):
            p[first + a, X_VY] += g_vy[a] * q_vy
            p[X_VY, first + a] += g_vy[a] * q_vy
            p[first + a, X_R] += g_r[a] * q_r
            p[X_R, first + a] += g_r[a] * q_r
            for b in range(lag):
                p[first + a, first + b] += g_vy[a] * g_vy[b] * q_vy + g_r[a] * g_r[b] * q_r

    @inline_kernel
    def predict_inertia_gain(x, vehicle, settings, dt, speed, steering, steering_rate, relaxation, ws, after):
        """D x_{k+1} / d ln Iz of the motion states, by a difference quotient, in ws[W_BIAS, B_INERTIA].

        Call it with ``after`` False before predict_n (the motion predicted with Iz x (1 + INERTIA_STEP);
        it overwrites the discretisation predict_n then redoes), and with ``after`` True once predict_n has
        put the prediction in x. Only with ``ekf.yaw_inertia_uncertainty`` > 0.
        """
        if not settings[S_INERTIA_UNCERTAINTY] > 0.0:
            return
        if after:
            for i in range(nd):
                ws[W_BIAS, B_INERTIA, i] = (ws[W_BIAS, B_INERTIA, i] - x[i]) / math.log1p(INERTIA_STEP)
            return
        perturbed = ws[W_BIAS, B_VEHICLE]  # a row of the work buffer (the kernels do not allocate)
        for i in range(N_VEHICLE):
            perturbed[i] = vehicle[i]
        perturbed[VEH_IZ] *= 1.0 + INERTIA_STEP
        cf, dcf = stiffness(x, settings, 0)
        cr, dcr = stiffness(x, settings, 1)
        method = int(settings[S_METHOD])
        discretize_n(cf, cr, dcf, dcr, speed, dt, perturbed, method, False, relaxation, ws)
        level, rate = wheel_ramp(x, ramp_start(steering, steering_rate, dt, method), steering_rate)
        for i in range(nd):
            acc = ws[W_E, i, nd] * level + ws[W_E, i, nd + 1] * rate
            for j in range(nd):
                acc += ws[W_E, i, j] * x[j]
            ws[W_BIAS, B_INERTIA, i] = acc

    @inline_kernel
    def interval_motion(x, vehicle, settings, dt, speed, steering, steering_rate, ws):
        """(vy, r) averaged over the interval's two ends, x's and the prediction's (x and F unchanged).

        A single antenna's speed is the mean |v| of the interval's two samples (measurement_row.course_speed);
        the lateral dynamics settle within the interval, so its start alone is not its middle.
        """
        cf, dcf = stiffness(x, settings, 0)
        cr, dcr = stiffness(x, settings, 1)
        method = int(settings[S_METHOD])
        discretize_n(cf, cr, dcf, dcr, speed, dt, vehicle, method, False, 0.0, ws)
        level, rate = wheel_ramp(x, ramp_start(steering, steering_rate, dt, method), steering_rate)
        end_vy = ws[W_E, X_VY, nd] * level + ws[W_E, X_VY, nd + 1] * rate
        end_r = ws[W_E, X_R, nd] * level + ws[W_E, X_R, nd + 1] * rate
        for j in range(nd):
            end_vy += ws[W_E, X_VY, j] * x[j]
            end_r += ws[W_E, X_R, j] * x[j]
        return 0.5 * (x[X_VY] + end_vy), 0.5 * (x[X_R] + end_r)

    @inline_kernel
    def course_model_speed(x, vehicle, settings, dt, speed, steering, steering_rate, ws):
        """A single antenna's ``speed`` (the mean |v| of the interval's ends) as the CG's forward speed.

        :func:`.measurement_row.course_speed` at the motion over the interval, from a trial prediction at the
        speed the start's motion gives (a trial at |v| itself misses by antenna_y r: 1 % at 0.5 m, 0.4 rad/s).
        """
        first = course_speed(vehicle, speed, (x[X_VY], x[X_R]))
        return course_speed(vehicle, speed, interval_motion(x, vehicle, settings, dt, first, steering, steering_rate, ws))

    return reset_motion, stiffness, predict_n, carry_lags, add_lag_noise, predict_inertia_gain, course_model_speed
