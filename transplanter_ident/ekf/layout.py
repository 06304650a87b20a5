"""Index layout of the compiled filter (paper eqs. 9-14): every array slot named once.

The kernels of :mod:`.model` and :mod:`.kernels` work on flat float arrays; this module names
their slots so that no kernel writes a bare number:

* state x (n,): [vy, r, psi, theta_f, theta_r, b, g, h] in ``heading`` mode (z = [vy_antenna, psi]; in ``course``
  mode, a single antenna, psi is the antenna's course over ground and z its measurement alone) or
  [vy, r, theta_f, theta_r, b, g, h] in ``yaw_rate`` mode (the paper's eq. 11 plus b, g and h, z = [vy_antenna, r]);
  theta = ln C (``log``) or C (``linear``), b the steering-sensor offset and g the relative error of its
  gain left out of ``vehicle.steering_scale`` (wheel = (1 + g) sensor - b), h the
  heading's misalignment left out of ``vehicle.heading_offset`` (the vy measurement is vy + antenna_x r
  - vx h, :mod:`.update`). With a tire relaxation length (``vehicle.relaxation_length`` > 0) the slip
  lags of the two axles, d_f and d_r (the force is C (alpha - d)), follow the motion states:
  [vy, r, (psi), d_f, d_r, theta_f, theta_r, b, g, h];
* settings (N_SETTINGS,): the filter options as numbers (``S_*``);
* outputs (N_OUTPUTS,): one row per epoch (``O_*``);
* memo (N_MEMO,): what the step remembers between epochs (``M_*``);
* epoch columns (N_EPOCH_COLUMNS,): the kernel input of one epoch (``E_*``);
* work buffer (WORK_SLOTS, WORK_SIZE, WORK_SIZE): scratch matrices (``W_*``) and vectors
  (rows ``V_*`` of slot ``W_VEC``);
* :class:`StepStatus`: what the step did with an epoch (an IntEnum: a constant to numba).
* validity limits (N_LIMITS,): the thresholds of the validity's window checks (``L_*``,
  evaluation/window_checks.py), and its hysteresis' state (N_HYSTERESIS,) (``H_*``).
"""

from __future__ import annotations

import enum

# state: the motion states first, then the two stiffness states, the steering offset and gain error, and the
# heading's misalignment
X_VY, X_R, X_PSI = 0, 1, 2
HEADING_STATES, YAW_RATE_STATES = 8, 7  # [vy, r, psi, th_f, th_r, b, g, h] and [vy, r, th_f, th_r, b, g, h]
N_MOTION_HEADING, N_MOTION_YAW_RATE = 3, 2
N_LAG = 2  # the slip lags [d_f, d_r] of a relaxing tire (model.continuous_matrix), after the motion states
HEADING_LAG_STATES, YAW_RATE_LAG_STATES = HEADING_STATES + N_LAG, YAW_RATE_STATES + N_LAG
MAX_STATES = HEADING_LAG_STATES
X_THETA_F, X_THETA_R, X_OFFSET, X_STEERING_GAIN, X_HEADING_OFFSET = -5, -4, -3, -2, -1  # counted from the end
N_PARAMETER_STATES = 5  # [theta_f, theta_r, b, g, h], after the motion states and slip lags
#: the parameter states a learned state keeps (persistence.py) and a new pass starts from (relinearization.py);
#: the heading's misalignment is learnt anew in a minute (ekf.estimate_heading_offset)
PARAMETER_STATES = [X_THETA_F, X_THETA_R, X_OFFSET, X_STEERING_GAIN]

# measurement z = [vy at the antenna, psi] (heading) or [vy at the antenna, r] (yaw_rate)
Z_VY, Z_SECOND = 0, 1

# settings vector
S_METHOD, S_LOG, S_HEADING, S_MIN_SPEED, S_LOW, S_HIGH = 0, 1, 2, 3, 4, 5
S_GATE, S_MAX_GATED, S_MAX_INTERVAL, S_P0_VY, S_P0_R, S_P0_PSI = 6, 7, 8, 9, 10, 11
S_ANTENNA_X, S_MAX_SLIP, S_MAX_LAT_ACC = 12, 13, 14
S_CUSUM_SCALE, S_CUSUM_THRESHOLD, S_CUSUM_CAP, S_CHANGE_Q = 15, 16, 17, 18
S_LINEAR_RANGE, S_CHANGE_DETECTION, S_CHANGE_HOLD, S_R_FROM_COVARIANCE = 19, 20, 21, 22
S_P0_THETA_F, S_P0_THETA_R, S_P0_OFFSET = 23, 24, 25  # the parameter states' P0 (recovery.py re-initialises to it)
S_MIN_FRICTION, S_SATURATION_CORRECTION = 26, 27  # adaptation.propagate_tire_bias
S_NOISE_ADAPTATION, S_NOISE_MEMORY, S_MAX_NOISE_SCALE = 28, 29, 30  # adaptation.learn_noise_scales
S_DELAY_UNCERTAINTY = 31  # s, 1-sigma of the GNSS delay left out of gnss.delay (adaptation.propagate_delay_bias)
S_DELAY_MEMORY = 32  # s, time constant of the delay's adaptation.score_signature (ekf.identifiability_memory)
S_SATURATION_PRIOR, S_SATURATION_MEMORY = 33, 34  # adaptation.saturation_share, and its measure's memory (s)
S_SCALE_UNCERTAINTY = 35  # relative 1-sigma of the steering sensor's gain left out of vehicle.steering_scale
S_SPEED_NOISE = 36  # 1: the speed input's noise (R's velocity variance per sample) enters P through dx/dvx
S_MAX_UTILISATION = 37  # the linear range's force limit, a fraction of mu Fz at min_friction (adaptation.py)
S_SHIFT, S_SHIFT_THRESHOLD = 38, 39  # the directional change test's shift (in std) and alarm level (adaptation.py)
S_INERTIA_UNCERTAINTY = 40  # relative 1-sigma of the yaw inertia left out of vehicle.iz (adaptation.propagate_inertia_bias)
S_RELAXATION_UNCERTAINTY = 41  # m, 1-sigma of the relaxation length left out of vehicle.relaxation_length
#: 1: the step measures the relaxation length and the steering gain left out (the validity tests them); the
#: tuner's objective (sequence.objective_n), which reads no validity, sets it to 0
S_MEASURE_ERRORS = 42
#: 1: each R is widened by its innovations' lag-1 autocorrelation (noise_correlation.py); the tuner's objective sets 0
S_NOISE_CORRELATION = 43
#: rad^2/s: the steering offset's Q density while a change alarm's raised density lasts (update.propagate_covariance)
S_CHANGE_OFFSET_Q = 44
S_P0_HEADING_OFFSET = 45  # rad^2: P0 of the heading's misalignment h (0: not estimated, recovery.py re-initialises to it)
S_PLAY_UNCERTAINTY = 46  # rad, 1-sigma of the steering play left out of vehicle.steering_play (play_signature.py)
S_ROLL_LEVER = 47  # s^2, the antenna's sideways travel per m/s^2 of lateral acceleration (measurement_row.roll_velocity)
S_P0_STEERING_GAIN = 48  # P0 of the steering gain's error g (0: not estimated, recovery.py re-initialises to it)
S_RAMP_SHIFT, S_RAMP_THRESHOLD = 49, 50  # the slow change test's shift (in std; 0: off) and alarm level (change.py)
N_SETTINGS = 51

# output row (one per epoch)
O_STATUS, O_VY, O_R, O_CF, O_CR, O_CF_STD, O_CR_STD = 0, 1, 2, 3, 4, 5, 6
O_VY_MODEL, O_R_MODEL, O_E0, O_E1, O_S00, O_S01, O_S11, O_NIS = 7, 8, 9, 10, 11, 12, 13, 14
O_OFFSET, O_OFFSET_STD, O_CORRELATION, O_CHANGE, O_CUSUM = 15, 16, 17, 18, 19
O_SLIP_F, O_SLIP_R, O_LAT_ACC, O_DT = 20, 21, 22, 23
O_TIRE_BIAS_F, O_TIRE_BIAS_R = 24, 25  # relative bias of Cf, Cr a saturating tire at min_friction would cause
O_NOISE_SCALE_VY, O_NOISE_SCALE_SECOND = 26, 27  # the factors on R the innovations show (adaptation.noise_scale)
O_NIS_CONFIGURED = 28  # the NIS against the configured R, without those factors (the validity's consistency test)
O_DELAY_SENS_F, O_DELAY_SENS_R = 29, 30  # relative error of Cf, Cr per second of GNSS delay left out of gnss.delay
O_DELAY_ESTIMATE, O_DELAY_ESTIMATE_STD = 31, 32  # s: that delay as the innovations show it (std 0: none yet)
O_SATURATION, O_SATURATION_STD = 33, 34  # the tire's saturation as a fraction of one at min_friction (std 0: none)
O_SCALE_SENS_F, O_SCALE_SENS_R = 35, 36  # relative error of Cf, Cr per unit (relative) steering gain error (0: off)
# the stiffness updates, each normalised by its std and decorrelated (change.decorrelated; 0: no update, or a
# change alarm and its hold): N(0, 1) while the stiffness holds still, one way while it drifts (validity's drift test)
O_UPDATE_F, O_UPDATE_R = 37, 38
# m: the tire relaxation length left out of vehicle.relaxation_length as the innovations show it (std 0: none yet),
# and the relative error of Cf, Cr per metre of it (relaxation_signature.py)
O_RELAXATION, O_RELAXATION_STD, O_RELAXATION_SENS_F, O_RELAXATION_SENS_R = 39, 40, 41, 42
O_SCALE_ESTIMATE, O_SCALE_ESTIMATE_STD = 43, 44  # the steering gain left out as the innovations show it (std 0: none)
#: the lag-1 autocorrelation of each measurement's normalised innovations that widens its R (noise_correlation.py)
O_NOISE_CORRELATION_VY, O_NOISE_CORRELATION_SECOND = 45, 46
#: the directional change tests' largest CUSUM over its alarm level (ekf.change_shift_threshold or
#: ekf.change_ramp_threshold): 0, up to 1 at an alarm (change.py);
#: the validity's "change suspected" check reads it
O_CHANGE_EVIDENCE = 47
#: rad: a heading misaligned with the vehicle beyond vehicle.heading_offset as the innovations show it (std 0: none
#: yet), and the relative error of Cf, Cr per radian of it (heading_signature.py)
O_HEADING_ESTIMATE, O_HEADING_ESTIMATE_STD, O_HEADING_SENS_F, O_HEADING_SENS_R = 48, 49, 50, 51
#: rad: the state h, the heading's misalignment (ekf.estimate_heading_offset; then the measure above is off), and its
#: std (0, 0: not estimated)
O_HEADING_OFFSET, O_HEADING_OFFSET_STD = 52, 53
#: rad: a steering play left out of vehicle.steering_play as the innovations show it (std 0: none yet), and the
#: relative error of Cf, Cr per radian of it (play_signature.py)
O_PLAY_ESTIMATE, O_PLAY_ESTIMATE_STD, O_PLAY_SENS_F, O_PLAY_SENS_R = 54, 55, 56, 57
#: the state g, the steering gain's relative error left out of vehicle.steering_scale (ekf.estimate_steering_gain),
#: and its std (0, 0: not estimated)
O_STEERING_GAIN, O_STEERING_GAIN_STD = 58, 59
N_OUTPUTS = 60

# memo vector
M_T_PREV, M_INITIALISED, M_GATED, M_CUSUM, M_ADAPT_UNTIL, M_DIVERGED = 0, 1, 2, 3, 4, 5
M_BIAS = 6  # memo[M_BIAS + i]: the first-order bias of state i from the tire's saturation (adaptation.py)
# the innovations' measure of R (adaptation.learn_noise_scales): the mean ratio of the measurement noise
# variance to R, for vy and for the second measurement, and the weighted seconds of data in each
M_NOISE_VY = M_BIAS + MAX_STATES  # each bias block holds MAX_STATES slots
M_NOISE_SECOND, M_NOISE_SPAN_VY, M_NOISE_SPAN_SECOND = M_NOISE_VY + 1, M_NOISE_VY + 2, M_NOISE_VY + 3
#: 1 once the model was near (noise_correlation.restart_noise_when_near): R's measure started again then
M_NOISE_SETTLED = M_NOISE_SPAN_SECOND + 1
M_DELAY_BIAS = M_NOISE_SETTLED + 1  # memo[M_DELAY_BIAS + i]: the bias of state i per second of unconfigured GNSS delay
# the online measure of that delay (adaptation.score_signature): score, information, seconds of data seen (both measures)
M_DELAY_SCORE = M_DELAY_BIAS + MAX_STATES
M_DELAY_INFORMATION, M_DELAY_SETTLED = M_DELAY_SCORE + 1, M_DELAY_SCORE + 2
# the same measure of the tire's saturation, in units of a tire at min_friction (adaptation.score_signature)
M_SATURATION_SCORE, M_SATURATION_INFORMATION = M_DELAY_SETTLED + 1, M_DELAY_SETTLED + 2
M_SCALE_BIAS = M_SATURATION_INFORMATION + 1  # memo[M_SCALE_BIAS + i]: the bias of state i per unit (relative) steering gain error
# 1 once both stiffnesses were known (adaptation.known_to): the slip lags are modelled from then on (kernels.py)
M_LAG_ACTIVE = M_SCALE_BIAS + MAX_STATES
M_LAG_SPEED = M_LAG_ACTIVE + 1  # m/s, the speed the slip lags were last predicted at (0: none since a reset)
#: memo[M_SPEED_CROSS + i]: Cov(error of state i, error of the last GNSS speed sample), which the next
#: interval's speed shares (update.add_speed_noise)
M_SPEED_CROSS = M_LAG_SPEED + 1
#: the directional change tests (change.py): their CUSUMs (Cf up, Cf down, Cr up, Cr down: the step's, then the
#: slow change's), then per stiffness the normalised updates' mean square minus 1, their lag-1 mean product, and
#: the last one
M_SHIFT = M_SPEED_CROSS + MAX_STATES
N_SHIFT_TESTS = 2  # the step's (ekf.change_shift) and the slow change's (ekf.change_ramp_shift)
N_SHIFT_SUMS = 4  # per test: Cf up, Cf down, Cr up, Cr down
N_SHIFT = N_SHIFT_SUMS * N_SHIFT_TESTS
M_SHIFT_POWER, M_SHIFT_LAG, M_SHIFT_LAST = M_SHIFT + N_SHIFT, M_SHIFT + N_SHIFT + 2, M_SHIFT + N_SHIFT + 4
#: memo[M_INERTIA_BIAS + i]: the bias of state i per unit of ln Iz left out of vehicle.iz (adaptation.py)
M_INERTIA_BIAS = M_SHIFT_LAST + 2
#: memo[M_RELAXATION_BIAS + i]: the bias of state i per metre of tire relaxation left out (relaxation_signature.py),
#: then the online measure of that length (adaptation.score_signature): score and information
M_RELAXATION_BIAS = M_INERTIA_BIAS + MAX_STATES
M_RELAXATION_SCORE, M_RELAXATION_INFORMATION = M_RELAXATION_BIAS + MAX_STATES, M_RELAXATION_BIAS + MAX_STATES + 1
#: the same measure of a steering gain left out (the signature of M_SCALE_BIAS): score and information
M_SCALE_SCORE, M_SCALE_INFORMATION = M_RELAXATION_INFORMATION + 1, M_RELAXATION_INFORMATION + 2
#: the innovations' correlation in time (noise_correlation.py): per measurement (vy, then psi or r) the mean
#: lag-1 product and the mean square of its normalised innovations, the weighted seconds of data in them, then
#: the last normalised innovations and their time (pairs only follow one another)
M_CORRELATION_LAG = M_SCALE_INFORMATION + 1
M_CORRELATION_POWER = M_CORRELATION_LAG + 2
M_CORRELATION_SPAN = M_CORRELATION_POWER + 2
M_CORRELATION_LAST = M_CORRELATION_SPAN + 1
M_CORRELATION_LAST_T = M_CORRELATION_LAST + 2
#: memo[M_HEADING_BIAS + i]: the bias of state i per radian of heading misalignment (heading_signature.py), then
#: the online measure of that misalignment (adaptation.score_signature): score and information
M_HEADING_BIAS = M_CORRELATION_LAST_T + 1
M_HEADING_SCORE, M_HEADING_INFORMATION = M_HEADING_BIAS + MAX_STATES, M_HEADING_BIAS + MAX_STATES + 1
#: memo[M_PLAY_BIAS + i]: the bias of state i per radian of steering play left out (play_signature.py), then the
#: online measure of that play (adaptation.score_signature): score and information
M_PLAY_BIAS = M_HEADING_INFORMATION + 1
M_PLAY_SCORE, M_PLAY_INFORMATION = M_PLAY_BIAS + MAX_STATES, M_PLAY_BIAS + MAX_STATES + 1
N_MEMO = M_PLAY_INFORMATION + 1

# the open-loop model's state: the filter's motion states and slip lags, [vy, r, psi, d_f, d_r] or [vy, r, d_f, d_r]
N_MODEL = N_MOTION_HEADING + N_LAG

# epoch columns of the kernels' input, and the Epoch field each one holds (joint_ekf.kernel_input)
E_T, E_SPEED, E_STEERING, E_STEERING_RATE, E_VY, E_PSI, E_YAW_RATE = 0, 1, 2, 3, 4, 5, 6
E_VAR_VY, E_VAR_PSI, E_VAR_YAW_RATE = 7, 8, 9  # the variances the messages report (NaN: none)
EPOCH_COLUMNS = ("t", "speed", "steering", "steering_rate", "antenna_lateral_velocity", "heading", "yaw_rate",
                 "velocity_variance", "heading_variance", "yaw_rate_variance")
N_EPOCH_COLUMNS = len(EPOCH_COLUMNS)

# vehicle constants (model.vehicle_array)
VEH_MASS, VEH_LF, VEH_LR, VEH_IZ = 0, 1, 2, 3
VEH_RELAXATION = 4  # m, the tires' relaxation length (0: the force follows the slip at once, eq. 4)
#: 1: the heading state is the antenna's course, psi + (vy + antenna_x r) / vx (model.course_row), with
#: VEH_ANTENNA_X, VEH_ANTENNA_Y the antenna ahead of and left of the CG (measurement_row.course_curvature)
VEH_COURSE, VEH_ANTENNA_X, VEH_ANTENNA_Y = 5, 6, 7
N_VEHICLE = 8

# discretisation codes (settings[S_METHOD])
EXACT, EULER = 0, 1

# tuning objectives
MAE, NLL = 0, 1
DIVERGENCE_PENALTY = 1.0e6

# the Fisher information's parameters (information.py), in its order
I_LN_CF, I_LN_CR, I_OFFSET, I_GAIN = 0, 1, 2, 3  # I_GAIN: the steering gain's relative error g
N_INFORMATION = 4

# work-buffer slots, ws[slot, i, j]: the discretisation (model.py) ...
W_E, W_DE_F, W_DE_R, W_M, W_DM_F, W_DM_R = 0, 1, 2, 3, 4, 5
W_T, W_DT_F, W_DT_R, W_NT, W_NDT_F, W_NDT_R = 6, 7, 8, 9, 10, 11
# ... and the filter step (kernels.py); W_GAIN rows: K[:, 0], K[:, 1], (HP)[0], (HP)[1]
W_F, W_TMP, W_GAIN, W_BACKUP_P, W_VEC = 12, 13, 14, 15, 16
# ... and the derivatives with respect to the speed vx (model.py; the speed's noise in Q, kernels.py)
W_DE_V, W_DM_V, W_DT_V, W_NDT_V = 17, 18, 19, 20
# ... and the model errors' biases (adaptation.py): rows B_* of ws[W_BIAS]
W_BIAS = 21
WORK_SLOTS = 22
WORK_SIZE = MAX_STATES
# rows of ws[W_VEC]
V_BACKUP_X, V_BACKUP_MODEL, V_NEW_X, V_NEW_MODEL, V_BIAS = 0, 1, 2, 3, 4
V_SPEED_GAIN = 5  # d x_{k+1} / d vx over the interval (the speed input's noise in Q)
V_SPEED_CROSS = 6  # F times memo[M_SPEED_CROSS:] (update.add_speed_noise)
V_BACKUP_CHANGE = 7  # the change tests' sums before the step, memo[M_CUSUM] then memo[M_SHIFT:] (recovery.py)
if 1 + N_SHIFT > WORK_SIZE:  # the kernels do not check bounds
    raise ImportError(f"layout: the change tests' {1 + N_SHIFT} sums do not fit a work vector of {WORK_SIZE}")
V_VY_ROW = 8  # this epoch's row of H for the vy measurement, ~[1, antenna_x, 0..., -vx] (measurement_row.predict_vy)
# rows of ws[W_GAIN]
G_K0, G_K1, G_HP0, G_HP1 = 0, 1, 2, 3
# rows of ws[W_BIAS]: what a model error adds to the predicted motion over the interval (adaptation.carry_bias),
# and the prediction with Iz x (1 + INERTIA_STEP), then d x_{k+1} / d ln Iz (prediction.predict_inertia_gain)
B_DIRECT, B_INERTIA = 0, 1
B_VEHICLE = 2  # the vehicle constants with Iz x (1 + INERTIA_STEP) (prediction.predict_inertia_gain)


# the validity's window checks: their thresholds (evaluation/window_checks.window_limits)
L_WINDOW, L_RECHECK, L_MAX_SIDESLIP, L_MIXED_FLOOR, L_COURSE_RATIO = 0, 1, 2, 3, 4
L_MAX_NONLINEAR, L_MIN_STEERING_STD, L_MIN_YAW_RATE_STD, L_NIS_SIGMAS, L_MAX_AUTOCORRELATION = 5, 6, 7, 8, 9
L_HOLD_ON, L_HOLD_OFF, L_MAX_SUSPECT, L_DRIFT_WINDOW, L_MAX_DRIFT_SIGMAS, L_MIN_DRIFT_UPDATES = 10, 11, 12, 13, 14, 15
N_LIMITS = 16
# ... and the hysteresis' state (evaluation/hysteresis.py): NaN, a time not set
H_VALID, H_GOOD_SINCE, H_BAD_SINCE = 0, 1, 2
N_HYSTERESIS = 3


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
    NONLINEAR = 9  # slip or lateral acceleration beyond the linear tire: motion updated, stiffness and offset held
    REINITIALISED = 10  # max_gated consecutive epochs failed the gate: motion states taken from the measurement
    RESTARTED = 11  # divergence persisted (recovery.py): motion states from the measurement, a diverged P to P0

    @property
    def stiffness_updated(self) -> bool:
        """Whether the stiffness estimate saw this epoch's measurement."""
        return self is StepStatus.UPDATED
