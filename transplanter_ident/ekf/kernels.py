"""Joint-state EKF over the motion states, the cornering stiffness and the steering offset (paper eqs. 9-14, 21).

State: [vy, r, psi, theta_f, theta_r, b, g, h] with z = [vy_antenna, psi] (``heading``, the default) or
[vy, r, theta_f, theta_r, b, g, h] with z = [vy_antenna, r] (``yaw_rate``, the paper's eq. 11). theta is
ln C (``log``) or C (``linear``); b is the steering-sensor offset and g its gain's error left out of
``vehicle.steering_scale`` (wheel angle = (1 + g) sensor - b; ``ekf.estimate_steering_gain``, else fixed at 0); h the
heading's misalignment with the vehicle left out of ``vehicle.heading_offset``. The prediction
(:mod:`.prediction`) uses :func:`model.discretize` (eq. 10 or exact ZOH, Jacobian eq. 13 with the A23
erratum fixed) driven by the steering ramp minus b. The measurement holds the lever arm and h,
h(x) = [vy + antenna_x r - vx h, psi] (:mod:`.measurement_row`), and the update is eq. 12 in Joseph
form with a Mahalanobis gate.
The body-frame vy is the GNSS velocity turned by the *measured* heading, so its error holds
-vx e_psi: R is full, [[R_v + vx^2 R_psi, -vx R_psi], [-vx R_psi, R_psi]] (R_v, R_psi as configured).

Beyond the paper (DESIGN.md section 7):

* Q is a spectral density: each interval adds Q dt, so one parameter file fits any GNSS rate;
* theta, b and h are random walks; a surface change (change.py) raises the stiffness's for a while;
* h, a heading misaligned with the vehicle (``ekf.estimate_heading_offset``): the vy measurement is the
  velocity turned by the measured heading, and the model runs at the vehicle's forward speed
  (:mod:`.measurement_row`); h is held (Schmidt) while the filter starts from its priors;
* beyond the linear tire range only the motion states are updated (a Schmidt update);
* a measurement gated ``max_gated`` times in a row re-initialises the motion states; it never
  forces a stiffness update;
* the speed input is the GNSS's, with its noise: P holds it through dx/dvx, with the covariance of the
  sample two intervals share (``ekf.speed_noise``, update.py);
* a single antenna (``ekf.measurement: course``): psi is the antenna's course and z its measurement alone
  (:func:`.model.course_row`, :mod:`.measurement_row`); its R follows from the velocity's;
* relaxing tires (``vehicle.relaxation_length``): the slip lags of both axles follow the motion states,
  modelled once both stiffnesses are known (before, from a prior far off, their weaker response
  throws the stiffness to its bounds), and carried to each interval's speed (:mod:`.prediction`).

Alongside the filter runs the *model output* of the paper's Figs. 6-7: the bicycle model driven by the
measured steering and speed with the stiffness identified so far, open loop from the first measured state.

One compiled step, :func:`ekf_step`, serves the node and the offline drivers
(:mod:`.joint_ekf`), so online and offline numbers are identical. Array slots are named in
:mod:`.layout`; numba options are fixed in :mod:`.jit`.
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.adaptation import (
    DELAY_SETTLE,
    beyond_linear_range,
    forget_motion_bias,
    known_to,
    noise_scale,
    propagate_delay_bias,
    propagate_inertia_bias,
    propagate_scale_bias,
    propagate_tire_bias,
    score_model_errors,
)
from transplanter_ident.ekf.change import detect_change, normalised_update
from transplanter_ident.ekf.heading_signature import propagate_heading_bias
from transplanter_ident.ekf.layout import (
    HEADING_STATES,
    M_ADAPT_UNTIL,
    M_CUSUM,
    M_DELAY_SETTLED,
    M_DIVERGED,
    M_GATED,
    M_INITIALISED,
    M_LAG_ACTIVE,
    M_LAG_SPEED,
    M_NOISE_SPAN_VY,
    M_NOISE_VY,
    M_SHIFT,
    M_SPEED_CROSS,
    M_T_PREV,
    N_LAG,
    N_MODEL,
    N_MOTION_HEADING,
    N_MOTION_YAW_RATE,
    N_SHIFT,
    O_DT,
    O_E0,
    O_E1,
    O_NIS,
    O_NIS_CONFIGURED,
    O_S00,
    O_S01,
    O_S11,
    O_SLIP_F,
    O_SLIP_R,
    S_ANTENNA_X,
    S_CHANGE_DETECTION,
    S_GATE,
    S_HIGH,
    S_LOG,
    S_LOW,
    S_MAX_GATED,
    S_MAX_INTERVAL,
    S_MEASURE_ERRORS,
    S_MIN_SPEED,
    S_P0_HEADING_OFFSET,
    S_PLAY_UNCERTAINTY,
    S_RELAXATION_UNCERTAINTY,
    S_ROLL_LEVER,
    S_SCALE_UNCERTAINTY,
    S_SPEED_NOISE,
    V_BACKUP_CHANGE,
    V_BACKUP_MODEL,
    V_BACKUP_X,
    VEH_COURSE,
    VEH_LF,
    VEH_LR,
    VEH_RELAXATION,
    W_BACKUP_P,
    W_VEC,
    X_PSI,
    X_R,
    X_VY,
    YAW_RATE_STATES,
    Z_SECOND,
    Z_VY,
    StepStatus,
)
from transplanter_ident.ekf.measure_outputs import score_measures
from transplanter_ident.ekf.measurement_row import (
    body_speed,
    course_variance,
    predict_vy,
    roll_velocity,
    second_innovation,
    vy_row_quadratic,
    vy_row_times_column,
)
from transplanter_ident.ekf.noise_correlation import effective_noise, learn_noise, restart_noise_when_near
from transplanter_ident.ekf.outputs import make_outputs
from transplanter_ident.ekf.play_signature import propagate_play_bias
from transplanter_ident.ekf.prediction import make_prediction
from transplanter_ident.ekf.recovery import make_recovery
from transplanter_ident.ekf.relaxation_signature import propagate_relaxation_bias, slip_deficits
from transplanter_ident.ekf.sequence import innovation_covariance, normalized_innovation_squared
from transplanter_ident.ekf.update import make_update
from transplanter_ident.jit import called_kernel, inline_kernel, sized_kernel

#: a state variance beyond this is divergence (ln C variance 1e12 means nothing is known)
MAX_VARIANCE = 1.0e12


@inline_kernel
def _finite(value):
    return not (math.isnan(value) or math.isinf(value))


def make_kernels(heading, lagged=False):
    """Compile predict/step/run/objective for one measurement mode (sizes become compile-time constants).

    ``heading``: n = 8 states, z = [vy_antenna, psi]; else n = 7, z = [vy_antenna, r]. ``lagged``: the
    tires relax (vehicle.relaxation_length > 0), and the slip lags d_f, d_r follow the motion states
    (n + N_LAG). The small loops unroll; all scratch lives in one work buffer indexed by slot (no
    per-step allocation).
    """
    lag = N_LAG if lagged else 0
    n = (HEADING_STATES if heading else YAW_RATE_STATES) + lag
    nd = (N_MOTION_HEADING if heading else N_MOTION_YAW_RATE) + lag  # motion states and slip lags
    nf, nr, nb, ng = nd, nd + 1, nd + 2, nd + 3  # theta_f, theta_r, steering offset and gain error (then h)
    h1 = X_PSI if heading else X_R  # second measured state
    propagate_covariance, add_speed_noise, joseph_update, keep_speed_cross = make_update(n, nd, h1)

    prediction = make_prediction(heading, lagged)
    reset_motion, stiffness, predict_n, carry_lags, add_lag_noise, predict_inertia_gain, course_model_speed = prediction

    write_outputs = make_outputs(nd, stiffness)

    @called_kernel
    def restart_motion(x, p, model, memo, settings, status, t, vy_antenna, psi, yaw_rate, out):
        reset_motion(x, p, model, settings, vy_antenna, psi, yaw_rate)
        forget_motion_bias(memo, nd)
        for i in range(n):  # the motion states now come from z, not from the speed
            memo[M_SPEED_CROSS + i] = 0.0
        memo[M_T_PREV] = t
        memo[M_INITIALISED] = 1.0
        memo[M_GATED] = 0.0
        memo[M_DIVERGED] = 0.0
        memo[M_LAG_SPEED] = 0.0  # the lags restart at 0, a steady turn at the next interval's speed
        write_outputs(x, p, memo, settings, status, yaw_rate, x[X_VY], out)
        return status

    bounded, recover = make_recovery(n, nd, MAX_VARIANCE, write_outputs, restart_motion)

    @inline_kernel
    def healthy(x, p, r_model, vy_model, nis):
        """Finite state and outputs, and a covariance below MAX_VARIANCE (else the step is rolled back)."""
        return bounded(x, p, 0) and _finite(r_model) and _finite(vy_model) and _finite(nis)

    @sized_kernel(runtime=False)
    def step_n(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,
               steering_rate, vy_antenna, psi, yaw_rate, ws, out):
        """One epoch, in place; returns the StepStatus (see :func:`.entries.ekf_step` for the shapes).

        1. Reject a non-finite epoch or a stamp not after the previous one (nothing changes).
        2. Initialise, or re-initialise after a gap (or a clock step back beyond max_interval), at low
           speed or reversing (motion from z).
        3. Predict x and the open-loop model over dt (eq. 12) at the vehicle's forward speed, P = F P F^T + Q dt
           (+ the speed's noise, update.py).
        4. Innovation, S and NIS with the lever arm and h in h(x) (measurement_row.py), the heading error in vy
           and R as the innovations show it (its variance, adaptation.noise_scale, and its correlation in time,
           noise_correlation.py).
        5. Gate; after max_gated gated epochs in a row, re-initialise the motion states.
        6. Joseph update (motion only outside the linear tire range; h held until both stiffnesses are known);
           the change tests (change.py); clamp the stiffness.
        7. Roll back if anything became non-finite; re-initialise if that lasts (:mod:`.recovery`); else
           propagate the tire's, the delay's and the steering gain's biases, keep the speed sample's covariance (update.py),
           learn R and rho (vy's not while h is held), and score the delay, the tires' saturation and
           (layout.S_MEASURE_ERRORS) a relaxation
           length and a steering gain left out (the saturation's share corrects Cf, Cr; model_errors.py tests the rest).
        """
        out[:] = 0.0
        # 1.
        if not (_finite(t) and _finite(speed) and _finite(steering) and _finite(steering_rate)
                and _finite(vy_antenna) and _finite(psi) and _finite(yaw_rate)):
            write_outputs(x, p, memo, settings, StepStatus.REJECTED_INVALID, model[X_R], model[X_VY], out)
            return StepStatus.REJECTED_INVALID
        stepped_back = t < memo[M_T_PREV] - settings[S_MAX_INTERVAL]  # a lasting clock step: start over below
        if memo[M_INITIALISED] > 0.5 and t <= memo[M_T_PREV] and not stepped_back:
            write_outputs(x, p, memo, settings, StepStatus.REJECTED_STAMP, model[X_R], model[X_VY], out)
            return StepStatus.REJECTED_STAMP
        # 2.
        status = StepStatus.UPDATED
        if memo[M_INITIALISED] < 0.5:
            status = StepStatus.INITIALISED
        elif abs(t - memo[M_T_PREV]) > settings[S_MAX_INTERVAL]:
            status = StepStatus.GAP
        elif speed < 0.0 and -speed >= settings[S_MIN_SPEED]:
            status = StepStatus.REVERSING
        elif speed < settings[S_MIN_SPEED]:
            status = StepStatus.LOW_SPEED
        if status != StepStatus.UPDATED:
            return restart_motion(x, p, model, memo, settings, status, t, vy_antenna, psi, yaw_rate, out)

        dt = t - memo[M_T_PREV]
        out[O_DT] = dt
        course = heading and vehicle[VEH_COURSE] > 0.5  # a single antenna: psi is its course, the one measurement
        vx = (course_model_speed(x, vehicle, settings, dt, speed, steering, steering_rate, ws) if course  # |v|
              else body_speed(x, n, settings[S_ANTENNA_X], speed))  # the model's speed; the measurement's is speed
        for i in range(n):
            ws[W_VEC, V_BACKUP_X, i] = x[i]
            for j in range(n):
                ws[W_BACKUP_P, i, j] = p[i, j]
        for i in range(N_MODEL):
            ws[W_VEC, V_BACKUP_MODEL, i] = model[i]
        ws[W_VEC, V_BACKUP_CHANGE, 0] = memo[M_CUSUM]  # rolled back with the step (recovery.py)
        for i in range(N_SHIFT):
            ws[W_VEC, V_BACKUP_CHANGE, 1 + i] = memo[M_SHIFT + i]

        # the tire's range from the last motion estimate, once both stiffnesses are known (see adaptation.py)
        log_state = settings[S_LOG] > 0.5
        wheel = (1.0 + x[ng]) * (steering - 0.5 * dt * steering_rate)  # at the interval's start, as x (predict_n)
        beyond = beyond_linear_range(vehicle, settings, vx, wheel, x[nb], x[X_VY], x[X_R],
                                     stiffness(x, settings, 0)[0], stiffness(x, settings, 1)[0], out)
        known = known_to(x[nf], p[nf, nf], log_state) and known_to(x[nr], p[nr, nr], log_state)
        nonlinear = beyond and known
        if lagged and known:  # the slip lags from now on (see the module docstring)
            memo[M_LAG_ACTIVE] = 1.0
        # an estimated h is held (Schmidt), and vy's R not learnt, until both stiffnesses are known (or DELAY_SETTLE s
        # of data): a model far off its priors makes vy errors that are neither h nor noise (and h is no noise)
        starting = not known and memo[M_DELAY_SETTLED] < DELAY_SETTLE
        heading_held = settings[S_P0_HEADING_OFFSET] > 0.0 and starting
        gain_held = starting  # likewise the steering gain's error g

        # 3.
        psi_model_before = model[X_PSI]
        relaxation = vehicle[VEH_RELAXATION] if lagged and memo[M_LAG_ACTIVE] > 0.5 else 0.0
        if relaxation > 0.0:
            if memo[M_LAG_SPEED] > 0.0:
                carry_lags(x, p, model, memo[M_LAG_SPEED], vx, vehicle)
            memo[M_LAG_SPEED] = vx
        predict_inertia_gain(x, vehicle, settings, dt, vx, steering, steering_rate, relaxation, ws, False)
        predict_n(x, model, vehicle, settings, dt, vx, steering, steering_rate, relaxation, ws)
        predict_inertia_gain(x, vehicle, settings, dt, vx, steering, steering_rate, relaxation, ws, True)
        measuring = settings[S_MEASURE_ERRORS] > 0.5  # the relaxation and gain measures (off in the tuner's objective)
        relaxing = measuring or settings[S_RELAXATION_UNCERTAINTY] > 0.0
        eps_f = eps_r = 0.0
        if relaxing:
            eps_f, eps_r = slip_deficits(ws[W_VEC, V_BACKUP_MODEL], model, vehicle, dt, vx, steering_rate, nd - lag,
                                         relaxation > 0.0, relaxation)
        r_model = (model[X_PSI] - psi_model_before) / dt if heading and not course else model[X_R]
        vy_model = model[X_VY]
        adapting = t <= memo[M_ADAPT_UNTIL]
        scale_f = 1.0 if settings[S_LOG] > 0.5 else x[nf]
        scale_r = 1.0 if settings[S_LOG] > 0.5 else x[nr]
        propagate_covariance(p, q, dt, adapting, settings, (scale_f, scale_r), ws)
        if relaxation > 0.0:
            add_lag_noise(p, q, dt, vx, vehicle)
        speed_variance = 0.0  # of one GNSS speed sample: R's velocity entry as the innovations show it
        if settings[S_SPEED_NOISE] > 0.5:  # the interval's speed: the mean of two GNSS samples
            speed_variance = r_noise[Z_VY] * noise_scale(memo, settings, M_NOISE_VY, M_NOISE_SPAN_VY)
            add_speed_noise(p, speed_variance, memo, ws)

        # 4.
        e0 = vy_antenna - predict_vy(ws, n, x, settings[S_ANTENNA_X], speed, course)  # ~ vy + ax r - vx h, and H[0]
        if settings[S_ROLL_LEVER] != 0.0 and not course:  # the body's roll moving the antenna sideways
            e0 -= roll_velocity(settings[S_ROLL_LEVER], speed, steering_rate, vehicle[VEH_LF] + vehicle[VEH_LR])
        e1 = second_innovation(x, heading, course, psi, yaw_rate, vehicle, vx)
        hph00 = vy_row_quadratic(ws, n, p)
        hph11 = p[h1, h1]
        second = course_variance(r_noise[Z_VY], speed) if course else r_noise[Z_SECOND]  # R of z[1] as configured
        r0, r1 = effective_noise(memo, settings, r_noise[Z_VY], second)  # as the innovations show it
        hph01 = vy_row_times_column(ws, n, p, h1)
        heading_terms = heading and not course  # the measured heading's error in vy (no vy measured from a course)
        s00, s01, s11 = innovation_covariance(heading_terms, hph00, hph01, hph11, r0, r1, speed)
        nis, det = normalized_innovation_squared(e0, e1, s00, s01, s11)  # det NaN: S lost definiteness, roll back
        out[O_E0], out[O_E1] = e0, e1
        out[O_S00], out[O_S01], out[O_S11] = s00, s01, s11
        out[O_NIS] = nis
        # the NIS against the configured R: the validity's consistency test (noisier sensors, a delay left out)
        c00, c01, c11 = innovation_covariance(heading_terms, hph00, hph01, hph11, r_noise[Z_VY], second, speed)
        out[O_NIS_CONFIGURED] = normalized_innovation_squared(e0, e1, c00, c01, c11)[0]

        # 5.
        if nis > settings[S_GATE] and _finite(nis):
            if memo[M_GATED] + 1.0 >= settings[S_MAX_GATED]:
                return restart_motion(x, p, model, memo, settings, StepStatus.REINITIALISED, t, vy_antenna,
                                      psi, yaw_rate, out)
            status = StepStatus.GATED
            memo[M_GATED] += 1.0
            updated = False
        else:
            # 6.
            memo[M_GATED] = 0.0
            updated = True
            if nonlinear:
                status = StepStatus.NONLINEAR
            theta_f, theta_r, prior_f, prior_r = x[nf], x[nr], p[nf, nf], p[nr, nr]
            joseph_update(x, p, e0, e1, s00, s01, s11, det, nonlinear, heading_held, gain_held, ws)
            if not nonlinear and settings[S_CHANGE_DETECTION] > 0.5:  # gated outliers never raise an alarm
                u_f = normalised_update(theta_f, x[nf], prior_f, p[nf, nf])
                u_r = normalised_update(theta_r, x[nr], prior_r, p[nr, nr])
                detect_change(memo, settings, t, dt, nis, u_f, u_r, out)
        low, high = settings[S_LOW], settings[S_HIGH]
        x[nf], x[nr] = min(max(x[nf], low), high), min(max(x[nr], low), high)

        # 7.
        if not healthy(x, p, r_model, vy_model, nis):  # roll back; re-initialise if it lasts (recovery.py)
            return recover(x, p, model, memo, settings, t, vy_antenna, psi, yaw_rate, ws, out)
        memo[M_T_PREV] = t
        memo[M_DIVERGED] = 0.0
        cf_now, cr_now = stiffness(x, settings, 0)[0], stiffness(x, settings, 1)[0]
        tire0, tire1 = propagate_tire_bias(memo, vehicle, settings, n, nd, h1, updated, out[O_SLIP_F],
                                           out[O_SLIP_R], cf_now, cr_now, log_state, ws)
        g0, g1 = propagate_delay_bias(memo, n, nd, h1, updated, steering_rate, ws)
        gain0 = gain1 = lag0 = head0 = head1 = play0 = play1 = 0.0
        if measuring and not settings[S_P0_HEADING_OFFSET] > 0.0:  # else h is a state
            head0, head1 = propagate_heading_bias(memo, n, nd, h1, updated, speed, ws)
        if measuring or settings[S_SCALE_UNCERTAINTY] > 0.0:
            gain0, gain1 = propagate_scale_bias(memo, n, nd, h1, updated, steering, ws)
        if measuring or settings[S_PLAY_UNCERTAINTY] > 0.0:
            play0, play1 = propagate_play_bias(memo, n, nd, h1, updated, steering_rate, ws)
        propagate_inertia_bias(memo, settings, n, nd, h1, updated, ws)
        if relaxing:
            lag0, _ = propagate_relaxation_bias(memo, n, nd, nb, h1, updated, vx, eps_f, eps_r, ws)
        keep_speed_cross(memo, speed_variance, updated, ws)
        if updated:
            restart_noise_when_near(memo, known)
        if updated and (known or not course):  # a course's errors from a stiffness far off are not noise either
            learn_noise(memo, settings, heading_terms, t, dt, speed, e0, e1, hph00, hph01, hph11, r_noise[Z_VY],
                        second, not (heading_held or course), not heading_held)
        if updated:
            score_model_errors(memo, settings, dt, g0, g1, tire0, tire1, e0, e1, s00, s01, s11, det)
        if updated and measuring:  # the relaxation, gain, heading and play measures (measure_outputs.py)
            score_measures(memo, settings, dt, lag0, gain0, gain1, head0, head1, play0, play1, e0, e1, s00, s01, s11,
                           det)
        write_outputs(x, p, memo, settings, status, r_model, vy_model, out)
        return status

    return predict_n, step_n
