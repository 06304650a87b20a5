"""The one parameter schema of the estimator: every dotted key the node declares (DESIGN.md section 3).

Each :class:`Param` row gives a key its default, type (``float``, ``int``, ``bool``, ``str`` or a
fixed-length ``float_list``), unit, range (``low``/``high``, inclusive) or choices, description and
whether it is read-only at run time. Everything else derives from this table: the keys the params
file accepts and how their values are converted (:mod:`.params_file`), the node's parameter
declarations and ParameterDescriptors (:mod:`transplanter_ident.ros.parameters`), and the
diagnostics thresholds. The frozen dataclasses of :mod:`.parameters` keep literal defaults for
readability; a test holds them equal to the defaults here.

Choices that are ROS message types are written in full (``geometry_msgs/msg/TwistStamped``); a
value may also name them as ``geometry_msgs/TwistStamped`` or just ``TwistStamped``.

This module imports no ROS and no YAML.
"""

from __future__ import annotations

import math

from transplanter_ident.config.param import Param, Value
from transplanter_ident.config.parameters import (
    DISCRETIZATIONS,
    MEASUREMENTS,
    NOISE_UNITS,
    STEERING_SENSOR_WHEELS,
    STIFFNESS_STATES,
)

FRAMES = ("enu", "ned")


def _float(key: str, default: float, unit: str, description: str, low: float | None = None,
           high: float | None = None, *, read_only: bool = True) -> Param:
    return Param(key, "float", default, unit, description, low, high, read_only=read_only)


def _int(key: str, default: int, description: str, low: int, high: int, *, read_only: bool = True) -> Param:
    return Param(key, "int", default, "", description, low, high, read_only=read_only)


def _str(key: str, default: str, description: str, choices: tuple[str, ...] = ()) -> Param:
    return Param(key, "str", default, "", description, choices=choices)


def _bool(key: str, default: bool, description: str) -> Param:
    return Param(key, "bool", default, "", description)


def _floats(key: str, default: tuple[float, ...], unit: str, description: str, low: float | None = None,
            high: float | None = None, *, read_only: bool = True) -> Param:
    """A fixed-length float list; ``low``/``high`` bound every entry."""
    return Param(key, "float_list", default, unit, description, low, high, read_only=read_only)


def _measured_error(name: str, what: str, short: str, diagnostic: str, per: str, sigmas: float, shift: float,
                    why: str = "") -> tuple[Param, Param]:
    """``validity.max_<name>_sigmas`` and ``_shift``: the two tests on one measured model error (model_errors.py)."""
    return (_float(f"validity.max_{name}_sigmas", sigmas, "", f"{what}, as the filter measures it from its "
                   f"innovations (/diagnostics {diagnostic}), this many std from zero makes the estimate invalid",
                   0.5, 100.0, read_only=False),
            _float(f"validity.max_{name}_shift", shift, "", f"the shift of Cf or Cr that the measured {short} implies "
                   f"(its lower 1-sigma bound times the estimate's sensitivity {per}), in the estimate's reported "
                   f"std, above which the estimate is not valid{why}", 0.1, 100.0, read_only=False))


#: the largest value of any noise entry (Q density or R; absurd beyond, e.g. a run-time Q of 1e300
#: that made the filter diverge for good): the tuner's search box (tuning/problem.py) lies well inside
MAX_NOISE = 1.0e6
#: N/rad: the range of the stiffness bounds and of the initial stiffness (which must also lie within the bounds)
STIFFNESS_RANGE = (1.0, 1.0e8)


SCHEMA: tuple[Param, ...] = (
    # vehicle (paper Table 1, eq. 5)
    _float("vehicle.mass", 720.0, "kg", "vehicle mass (paper Table 1)", 1.0, 1.0e5),
    _float("vehicle.lf", 0.7, "m", "CG to front axle", 0.01, 20.0),
    _float("vehicle.lr", 0.4, "m", "CG to rear axle", 0.01, 20.0),
    _float("vehicle.iz", 0.0, "kg m^2", "yaw inertia; <= 0 means m*lf*lr (paper eq. 5)", -1.0e7, 1.0e7),
    _float("vehicle.antenna_x", 0.0, "m", "GNSS antenna ahead of the CG", -20.0, 20.0),
    _float("vehicle.antenna_y", 0.0, "m", "GNSS antenna left of the CG", -20.0, 20.0),
    _float("vehicle.max_steering", 0.7, "rad", "steering limit; a sample beyond it is rejected", 0.001, 1.6),
    _float("vehicle.steering_offset", 0.0, "rad", "steering-sensor offset, wheel angle = sensor - offset: the "
           "initial value when estimated (ekf.estimate_steering_offset), else the fixed one", -0.3, 0.3),
    _float("vehicle.steering_scale", 1.0, "", "wheel angle per steering-sensor angle: the assembler multiplies "
           "every steering sample by it (before the offset: wheel = scale x sensor - offset). A sensor reading 1 % "
           "more than the wheel moves Cf by about -5 % and Cr by +8 % (README)", 0.5, 2.0),
    _str("vehicle.steering_sensor_wheel", "center", "the angle the steering sensor gives: center (the "
         "single-track angle of the bicycle model) or that of the left or right front wheel, turned into the "
         "single-track one with vehicle.track_width (Ackermann: cot delta = mean of the wheels' cot)",
         STEERING_SENSOR_WHEELS),
    _float("vehicle.track_width", 0.0, "m", "front track, for a steering sensor on one wheel", 0.0, 10.0),
    _float("vehicle.steering_play", 0.0, "rad", "free travel (play, backlash) of the linkage between the steering "
           "sensor and the wheels, in wheel angle: > 0 the wheels follow the sensor through it (a sensor on the "
           "steering column, motor or cylinder), < 0 the sensor follows the wheels (play in the sensor's own "
           "linkage); the assembler takes it out of every steering sample. 0.1 deg left out moves Cf by about "
           "10 % while the estimate stays valid (docs/robustness.md)", -0.2, 0.2),
    _float("vehicle.relaxation_length", 0.0, "m", "the tires' relaxation length: each axle's lateral force builds "
           "over this much travel (0: at once, the paper's eq. 4). With it the filter carries the slip lags of both "
           "axles; 0.3 m left out biases Cf by about +12 % at 2 m/s while the estimate stays valid (README). Of the "
           "order of the tire's radius; from the tire's data or a rolling test", 0.0, 5.0),
    _float("vehicle.heading_offset", 0.0, "rad", "yaw of the GNSS heading source relative to the vehicle x axis, "
           "counter-clockwise (subtracted from the heading): e.g. +1.5708 for a dual-antenna baseline pointing to "
           "the left; for one nav_msgs/Odometry topic serving velocity and heading it turns the twist too",
           -math.pi, math.pi),
    _float("vehicle.antenna_height", 0.0, "m", "height of the GNSS antenna (the velocity's point) above the body's "
           "roll axis: with vehicle.roll_gradient, the body's roll in turns moves it sideways, which the filter then "
           "predicts (docs/robustness.md, Body roll)", 0.0, 10.0),
    _float("vehicle.roll_gradient", 0.0, "rad s^2/m", "the body's roll, outward, per m/s^2 of lateral acceleration "
           "(a tilt or steady-turn test; 0: no roll). Left out with a high antenna (0.25 deg per m/s^2 at 1.5 m), the "
           "estimate is seldom valid and the reasons name a GNSS delay, a steering gain or a tire relaxation that are "
           "not there", -0.2, 0.2),
    # the vehicle's physical limits: samples beyond them are rejected and counted (issue #14)
    _float("vehicle.max_speed", 5.0, "m/s", "GNSS ground speed beyond which a velocity sample is rejected "
           "(a rice transplanter travels below about 4 m/s on the road)", 0.1, 100.0),
    _float("vehicle.max_lateral_speed", 1.0, "m/s", "lateral speed at the CG beyond which a GNSS epoch is "
           "rejected", 0.01, 50.0),
    _float("vehicle.max_yaw_rate", 1.5, "rad/s", "yaw rate (from heading increments) beyond which a GNSS epoch is "
           "rejected", 0.01, 20.0),
    _float("vehicle.max_steering_rate", 1.5, "rad/s", "a steering sample that changes more than this times the "
           "time since the last one, plus 0.01 rad of sensor noise, is a spike and rejected; a second one in a row "
           "is taken as a real jump (steering actuators turn below about 1 rad/s)", 0.01, 1000.0),
    # GNSS timing
    _float("gnss.delay", 0.0, "s", "the GNSS velocity and heading stamped t describe the motion at t - delay "
           "(drivers that stamp on arrival: about their latency)", -1.0, 10.0),
    _float("gnss.pairing_tolerance", 0.05, "s", "the most the stamps of a velocity and a heading of one GNSS "
           "epoch may differ (the default covers a heading stamped on arrival 35-45 ms after the velocity, as "
           "ublox does, up to 10 Hz); velocity and heading that never pair are a /diagnostics ERROR", 0.001, 1.0),
    _float("gnss.max_stamp_jump", 1.0, "s", "a sample (any input) stamped further than this from the previous "
           "sample of its input and from the other inputs is an outlier and rejected; after 5 consistent such "
           "samples the input re-synchronises to the new time base by itself", 0.01, 3600.0),
    # inputs
    _str("topics.velocity", "/gnss/vel", "GNSS velocity topic"),
    _str("topics.heading", "/gnss/heading", "GNSS heading topic"),
    _str("topics.steering", "/steering_angle", "steering angle topic (rad, positive to the left)"),
    _str("topics.velocity_type", "TwistStamped", "message type of topics.velocity: a ground velocity in "
         "frames.velocity, or nav_msgs/Odometry (its twist in the child frame: body axes at the child frame's "
         "origin, vehicle.antenna_x/y); a negative or NaN covariance diagonal marks a sample invalid",
         ("geometry_msgs/msg/TwistStamped", "geometry_msgs/msg/TwistWithCovarianceStamped", "nav_msgs/msg/Odometry")),
    _str("topics.heading_type", "QuaternionStamped", "message type of topics.heading (the yaw of its orientation; "
         "nav_msgs/Odometry on the velocity topic serves both)",
         ("geometry_msgs/msg/QuaternionStamped", "sensor_msgs/msg/Imu", "geometry_msgs/msg/PoseWithCovarianceStamped",
          "nav_msgs/msg/Odometry")),
    _str("topics.steering_type", "JointState", "message type of topics.steering (JointState: joint "
         "steering.joint_name; Float64 and Float32 have no header: their time is the receive time, on the node's ROS clock online "
         "and the log time offline, which agree to the /clock period with use_sim_time and ros2 bag play --clock)",
         ("sensor_msgs/msg/JointState", "std_msgs/msg/Float64", "std_msgs/msg/Float32")),
    _str("frames.velocity", "enu", "frame of the GNSS velocity: enu (linear.x/y = east/north) or ned "
         "(north/east)", FRAMES),
    _str("frames.heading", "enu", "frame of the GNSS heading: enu (ENU yaw) or ned (compass heading, clockwise "
         "from north)", FRAMES),
    _str("steering.joint_name", "front_steering", "joint of a sensor_msgs/JointState that carries the steering "
         "angle"),
    _float("steering.max_wait", 0.25, "s", "a GNSS epoch waits for a steering sample at or after its time (the "
           "steering driver may lag the GNSS, or an executor take one topic's backlog first) until a later GNSS "
           "epoch more than this after it is matched; then it is formed with the steering it has and counted as "
           "uncovered in /diagnostics (0: as soon as the next GNSS epoch is matched)", 0.0, 10.0),
    # outputs
    _str("output.frame_id", "base_link", "header.frame_id of every output message (the body frame at the CG)"),
    # filter structure (DESIGN.md section 1)
    _str("ekf.discretization", "exact", "exact (zero-order hold) or euler (paper eq. 10)", DISCRETIZATIONS),
    _str("ekf.stiffness_state", "log", "stiffness in the state as log or linear (paper)", STIFFNESS_STATES),
    _str("ekf.measurement", "heading", "heading (z = [vy, psi]), yaw_rate (paper, z = [vy, r]) or course (a single "
         "antenna: z = the velocity's direction, the heading topic unused; R's vy entry is the velocity's per-axis "
         "variance, the heading entry unused)", MEASUREMENTS),
    # noise (settable at run time; the initial values are used from the next ~/reset)
    _floats("ekf.process_noise", (1.0e-4, 1.0e-4, 1.5e-5, 1.5e-5), "state units^2/s",
            "diag Q for vy, r, Cf, Cr as a spectral density (each GNSS interval dt adds Q dt), in the units "
            "of the state; per step with ekf.process_noise_units: per_step", 0.0, MAX_NOISE, read_only=False),
    _str("ekf.process_noise_units", "per_second", "per_second (Q a spectral density: one file fits any GNSS "
         "rate) or per_step (per GNSS interval of ekf.process_noise_step, as before version 0.2)", NOISE_UNITS),
    _float("ekf.process_noise_step", 0.2, "s", "the GNSS interval per_step values were tuned for", 0.001, 10.0),
    _floats("ekf.measurement_noise", (4.0e-4, 1.2e-5), "(m/s)^2, rad^2",
            "diag R: vy, then heading (or r in (rad/s)^2 in yaw_rate mode)", 0.0, MAX_NOISE, read_only=False),
    _bool("ekf.measurement_noise_from_covariance", False, "R per epoch from the variances the GNSS messages "
          "report (TwistWithCovarianceStamped/Odometry twist, Imu/PoseWithCovarianceStamped/Odometry yaw), with "
          "ekf.measurement_noise as the floor; a message without one uses ekf.measurement_noise"),
    _float("ekf.heading_process_noise", 1.0e-8, "rad^2/s", "Q density of the heading state (heading mode)",
           0.0, MAX_NOISE, read_only=False),
    _bool("ekf.estimate_steering_offset", True, "estimate the steering-sensor offset as a filter state"),
    _float("ekf.steering_offset_process_noise", 1.0e-8, "rad^2/s", "Q density of the steering offset",
           0.0, MAX_NOISE, read_only=False),
    _float("ekf.steering_offset_initial_variance", 1.2e-3, "rad^2", "P0 of the steering offset (2 deg 1-sigma; "
           "used from the next ~/reset)", 0.0, 1.0, read_only=False),
    _bool("ekf.estimate_steering_gain", False, "estimate the steering sensor's gain error g left out of "
          "vehicle.steering_scale as a filter state (wheel angle = (1 + g) sensor - offset); at a constant speed only "
          "with gnss.delay and vehicle.steering_play calibrated and a steady surface (a delay or a play left out "
          "reads as a gain, and the validity no longer sees it; a surface change is missed more often); a varying "
          "speed sets them apart"),
    _float("ekf.steering_gain_process_noise", 1.0e-9, "1/s", "Q density of the steering gain's error",
           0.0, MAX_NOISE, read_only=False),
    _float("ekf.steering_gain_initial_variance", 4.0e-4, "1", "P0 of the steering gain's error (2 % 1-sigma; "
           "used from the next ~/reset)", 0.0, 1.0, read_only=False),
    _bool("ekf.estimate_heading_offset", True, "estimate the heading's misalignment with the vehicle's x axis left "
          "out of vehicle.heading_offset as a filter state (the vy measurement is vy + antenna_x r - vx h)"),
    _float("ekf.heading_offset_process_noise", 1.0e-8, "rad^2/s", "Q density of the heading's misalignment",
           0.0, MAX_NOISE, read_only=False),
    _float("ekf.heading_offset_initial_variance", 1.2e-3, "rad^2", "P0 of the heading's misalignment (2 deg "
           "1-sigma; used from the next ~/reset)", 0.0, 1.0, read_only=False),
    _floats("ekf.initial_stiffness", (1000.0, 1000.0), "N/rad", "initial Cf, Cr, within ekf.stiffness_bounds (used "
            "from the next ~/reset)", *STIFFNESS_RANGE, read_only=False),
    _floats("ekf.initial_covariance", (1.0e-2, 1.0e-2, 4.0, 4.0), "state units^2",
            "diag P0 for vy, r, Cf, Cr in the units of the state (used from the next ~/reset)", 0.0, 1.0e10,
            read_only=False),
    _float("ekf.initial_heading_covariance", 1.0e-2, "rad^2", "P0 of the heading state (used from the next "
           "~/reset)", 0.0, 100.0, read_only=False),
    # filter limits
    _float("ekf.min_speed", 0.3, "m/s", "below it, no stiffness update", 0.0, 20.0),
    _floats("ekf.stiffness_bounds", (50.0, 1.0e6), "N/rad", "lower and upper clamp of Cf, Cr", *STIFFNESS_RANGE),
    _float("ekf.gate_threshold", 25.0, "", "Mahalanobis d^2 above which an update is gated", 1.0e-3, 1.0e6),
    _int("ekf.max_gated", 5, "this many consecutive gated epochs re-initialise the motion states (never force "
         "a stiffness update)", 1, 1000),
    _float("ekf.max_interval", 2.0, "s", "a longer GNSS gap re-initialises the motion states", 0.001, 3600.0),
    # the tire's linear range and stiffness changes (DESIGN.md section 7)
    _bool("ekf.linear_range_check", True, "hold the stiffness and offset (update the motion only) where the "
          "tire's linear force, the measured slip angle or the lateral acceleration leaves the linear tire range"),
    _float("ekf.max_slip_angle", 0.15, "rad", "front or rear slip angle beyond which the tire counts as "
           "nonlinear whatever its stiffness (the small-angle slip of eq. 3; ekf.max_tire_utilisation bounds the "
           "force)", 1.0e-4, 1.0),
    _float("ekf.max_lateral_acceleration", 2.0, "m/s^2", "lateral acceleration beyond which the tire counts as "
           "nonlinear", 0.01, 50.0),
    _float("ekf.max_tire_utilisation", 0.9, "", "a tire counts as nonlinear where its linear force, the "
           "estimated stiffness times its slip angle, exceeds this fraction of what it gives on the most slippery "
           "field (ekf.min_friction times its static load): the linear range in slip is mu Fz / C, so a soft tire "
           "slips further in it and a stiff one less (0.9: 0.043 rad on a front tire of 8000 N/rad and 0.061 "
           "rad on a rear one of 10000 N/rad of the default vehicle); 0, or ekf.min_friction 0: off", 0.0, 100.0),
    _float("ekf.min_friction", 0.3, "", "friction coefficient of the most slippery surface expected (a wet "
           "field ~0.3): the reported Cf, Cr std include the bias a linear tire model takes on a tire saturating "
           "there (mu Fz tanh(C alpha / (mu Fz)), Fz the static load); 0: off", 0.0, 2.0),
    _bool("ekf.saturation_correction", False, "report Cf, Cr corrected by that bias (first order): right when "
          "ekf.min_friction is the friction of the field driven, too high by the bias on a grippier one"),
    _float("ekf.saturation_prior", 0.5, "", "the innovations measure how far the tires saturate, as a fraction a "
           "of a tire at ekf.min_friction (a = 1 there, 0 on a linear tire; /diagnostics tire_saturation): Cf, Cr "
           "are corrected by a's posterior times that bias, with a prior N(0, this^2) (0.5: a field as slippery as "
           "ekf.min_friction is a 2-sigma event); the std keeps the bias up to a = 1, or up to max(a, 0) + 1 std of the "
           "measure where that is less; 0: off", 0.0, 10.0),
    _float("ekf.saturation_memory", 300.0, "s", "time constant of the tires' two measures: that one (a surface "
           "change restarts it) and of a relaxation length left out of vehicle.relaxation_length (/diagnostics "
           "relaxation_estimate_m)", 1.0, 1.0e5),
    _float("ekf.delay_uncertainty", -1.0, "s", "1-sigma of the GNSS timing error left after gnss.delay (a driver "
           "stamping on arrival: its latency's spread): the Cf, Cr std hold the bias it causes (~2 % per ms at 2 "
           "m/s; /diagnostics delay_sensitivity_per_ms); < 0: not stated: 1 ms is held (what a calibration "
           "leaves), and a course, which cannot show a timing error, is never valid", -1.0, 1.0),
    _float("ekf.steering_play_uncertainty", 0.0, "rad", "1-sigma of the steering linkage's play left after "
           "vehicle.steering_play (tuner --estimate-steering-play prints its estimate's): the reported Cf, Cr std hold "
           "the bias it causes (~90 % per degree at 2 m/s on a +-15 deg sine; /diagnostics "
           "play_sensitivity_per_deg); 0: off", 0.0, 0.05),
    _float("ekf.steering_scale_uncertainty", 0.003, "", "relative 1-sigma of the steering sensor's gain left after "
           "vehicle.steering_scale (tuner --estimate-steering-scale writes its estimate's): the reported Cf, Cr std "
           "hold the bias it causes (~5-8 % per % at 2 m/s; /diagnostics scale_sensitivity_per_percent); 0: off; "
           "0.003: what a calibration leaves", 0.0, 0.2),
    _float("ekf.yaw_inertia_uncertainty", 0.0, "", "relative 1-sigma of the yaw inertia left after vehicle.iz (tuner "
           "--estimate-yaw-inertia writes it): the Cf, Cr std hold the bias it causes (~0.8 % per %); 0: off", 0.0, 1.0),
    _float("ekf.relaxation_uncertainty", 0.0, "m", "1-sigma of the tire relaxation length left after "
           "vehicle.relaxation_length (tuner --estimate-relaxation-length writes it): the Cf, Cr std hold the bias it "
           "causes (~0.5 % per cm at 2 m/s; /diagnostics relaxation_sensitivity_per_cm); 0: off", 0.0, 2.0),
    _bool("ekf.speed_noise", True, "the speed the model is driven with is the GNSS ground speed, as noisy as the "
          "velocity: the mean of an interval's two samples (each of R's velocity variance times the factor the "
          "innovations show), the first shared with the interval before; it enters P through the model's "
          "sensitivity to the speed. In a tight turn a 1 % speed error moves the yaw rate by 1 %, which a filter "
          "without it reads as a stiffness change"),
    _bool("ekf.noise_adaptation", True, "raise R to what the innovations show (covariance matching over "
          "ekf.noise_memory; never below the configured or reported R), so noisier sensors neither raise change "
          "alarms nor narrow the band"),
    _float("ekf.noise_memory", 60.0, "s", "time constant of the innovations' measure of R", 1.0, 3600.0),
    _float("ekf.max_noise_scale", 100.0, "", "largest factor on R (variance) the innovations may set", 1.0, 1.0e4),
    _bool("ekf.noise_correlation", True, "widen each R by (1 + rho) / (1 - rho), rho the lag-1 autocorrelation of its "
          "normalised innovations over ekf.noise_memory (0-0.9): GNSS errors correlated in time (a receiver that "
          "smooths its output) carry less information than white ones (/diagnostics innovation_correlation)"),
    _bool("ekf.change_detection", True, "CUSUM test of the innovations for a stiffness change (surface)"),
    _float("ekf.change_scale", 2.0, "", "innovation variance ratio the change test looks for (4 before: with GNSS "
           "noise 2x the default and R set to it, a 40 % drop went unseen)", 1.01, 100.0),
    _float("ekf.change_threshold", 8.0, "", "CUSUM alarm level (log-likelihood ratio; 12 before)", 1.0, 1000.0),
    _float("ekf.change_shift", 0.7, "", "the directional change test: mean, in their std, of the stiffness updates "
           "it looks for (a surface change pushes them one way; the variance test alone missed drops)", 0.05, 10.0),
    _float("ekf.change_shift_threshold", 10.0, "", "its CUSUM alarm level (log-likelihood ratio)", 1.0, 1000.0),
    _float("ekf.change_ramp_shift", 0.3, "", "the same test for a slow change: a surface that changes over a "
           "minute, too slowly for ekf.change_shift, lets the estimate lag by several std while each update pushes "
           "it by a fraction of one (its alarm raises the stiffness Q as a step's does); 0: off", 0.0, 10.0),
    _float("ekf.change_ramp_threshold", 8.0, "", "its CUSUM alarm level (log-likelihood ratio)", 1.0, 1000.0),
    _float("ekf.change_process_noise", 2.0e-2, "(ln C)^2/s", "stiffness Q density (relative) for change_hold "
           "after a change alarm", 1.0e-8, 10.0),
    _float("ekf.change_hold", 4.0, "s", "how long the raised stiffness Q lasts after a change alarm", 0.01, 600.0),
    _float("ekf.change_offset_variance", 3.0e-4, "rad^2", "what the steering offset may have moved by when a change "
           "alarm fires (a steering sensor knocked or re-mounted looks like a new surface): added to its variance "
           "over change_hold, so the offset is learnt anew with the stiffness; 0: off (the alarm re-opens the "
           "stiffness only)", 0.0, 1.0),
    # what the recent data pin (ekf/identifiability.py, /diagnostics "identifiability")
    _bool("ekf.identifiability_check", True, "publish, along a direction of (ln Cf, ln Cr) whose Cramer-Rao bound "
          "from the recent data exceeds ekf.max_identifiable_rel_std, at least the initial (prior) band"),
    _float("ekf.identifiability_memory", 60.0, "s", "span of recent epochs whose Fisher information gives the "
           "bound", 1.0, 3600.0),
    _int("ekf.identifiability_max_epochs", 600, "at most this many of them (the latest) are summed", 2, 100000),
    _float("ekf.identifiability_min_steering", 0.05, "rad", "the bound is re-evaluated only at epochs whose wheel "
           "angle is at least this (on a straight it is held: straight driving adds next to no information)",
           0.0, 1.6),
    _float("ekf.identifiability_period", 1.0, "s", "data time between two evaluations of the bound (held in "
           "between)", 0.01, 60.0),
    _float("ekf.max_identifiable_rel_std", 0.10, "", "relative Cramer-Rao 1-sigma above which the recent data "
           "do not pin a direction of (ln Cf, ln Cr)", 1.0e-4, 10.0),
    # re-linearised passes at the start (ekf/relinearization.py)
    _float("ekf.relinearization_window", 60.0, "s", "for this many seconds of stiffness updates after the start, "
           "every 5 s of them, when Cf or Cr has moved more than ekf.relinearization_threshold from where the "
           "filter's pass started, it filters the epochs so far again from the stiffness and offset it holds "
           "(its first steps were linearised at the initial stiffness); 0: one pass (the paper's); see the README",
           0.0, 3600.0),
    _float("ekf.relinearization_threshold", 0.1, "", "relative move of Cf or Cr (|d ln C|) since the pass began "
           "that starts a new pass", 1.0e-3, 10.0),
    # the learned state across restarts (ekf/persistence.py)
    _str("persistence.file", "$ROS_HOME/transplanter_ident/{node}.yaml", "where the learned stiffness, offset and "
         "covariance are kept across restarts ($ROS_HOME: ~/.ros when unset; {node}: the node name); empty: off"),
    _float("persistence.period", 60.0, "s", "how often the learned state is saved (also at shutdown), when valid",
           1.0, 86400.0),
    # the validity decision (evaluation/validity.py; config.parameters.ValiditySettings)
    _float("validity.window", 10.0, "s", "data span over which excitation and innovation consistency are judged",
           1.0, 600.0, read_only=False),
    _float("validity.max_rel_std", 0.08, "", "relative 1-sigma of Cf and Cr above which the estimate is not valid "
           "(the band holds the timing and steering gain left after calibration)", 1.0e-4, 10.0, read_only=False),
    _float("validity.min_steering_std", 0.02, "rad", "steering standard deviation over the window needed for "
           "excitation (or the yaw-rate one)", 0.0, 1.6, read_only=False),
    _float("validity.min_yaw_rate_std", 0.02, "rad/s", "yaw-rate standard deviation over the window needed "
           "for excitation (or the steering one)", 0.0, 10.0, read_only=False),
    _float("validity.nis_quantile_sigmas", 3.0, "", "the window's NIS sum may exceed its chi^2 mean by this "
           "many of its sigmas", 0.1, 100.0, read_only=False),
    _float("validity.max_noise_factor", 2.25, "", "the NIS test takes R times the factor (variance) the "
           "innovations show (ekf.noise_adaptation; /diagnostics noise_factors) up to this: GNSS noise 1.5x the "
           "configured one (1-sigma) is measured, not a fault; beyond it the estimate is not valid until "
           "ekf.measurement_noise is set (or tuned)", 1.0, 1.0e4, read_only=False),
    *_measured_error("delay", "the GNSS delay left out of gnss.delay", "GNSS delay", "delay_estimate_ms",
                     "per second of delay", 3.0, 1.5, ": a delay the data show but cannot yet pin moves the stiffness "
                     "beyond its band"),
    *_measured_error("relaxation", "a tire relaxation length left out of vehicle.relaxation_length",
                     "relaxation length", "relaxation_estimate_m", "per metre", 3.0, 1.0),
    *_measured_error("steering_gain", "a steering gain left out of vehicle.steering_scale (or a yaw inertia off "
                     "vehicle.iz, which looks alike)", "steering gain error", "steering_gain_estimate_percent",
                     "per unit of gain", 3.0, 1.5),
    *_measured_error("heading", "a GNSS heading misaligned with the vehicle's x axis beyond vehicle.heading_offset "
                     "(100, the default: off; the stiffness hardly moves with it, ~0.2 % per degree at 2 m/s, so the "
                     "shift test decides)", "heading misalignment", "heading_misalignment_deg", "per radian", 100.0,
                     1.5),
    *_measured_error("steering_play", "a steering play left out of vehicle.steering_play (or a GNSS delay or a "
                     "tire relaxation, which look alike)", "steering play", "steering_play_estimate_deg", "per radian",
                     3.0, 1.5),
    _float("validity.max_autocorrelation", 0.6, "", "lag-1 autocorrelation of the whitened vy innovation above "
           "which the filter is inconsistent (an unconfigured delay, GNSS errors correlated longer than "
           "ekf.noise_correlation's widening of R holds; 0.3 without it)",
           0.01, 1.0, read_only=False),
    _float("validity.max_sideslip", 0.35, "rad", "median |vy/vx| above which GNSS velocity and heading disagree "
           "(a frame mix-up)", 0.01, 1.6, read_only=False),
    _float("validity.course_ratio", 0.2, "", "RMS antenna vy below this fraction of the RMS vy a steady turn "
           "gives there ((lr + antenna_x) r less the rear axle's slip at the estimated Cr) while turning: the "
           "heading is a course over ground", 0.001, 1.0, read_only=False),
    _float("validity.hold_on", 3.0, "s", "every check must hold this long before the estimate is valid", 0.0,
           600.0, read_only=False),
    _float("validity.hold_off", 1.0, "s", "a soft check must fail this long before the estimate is invalid",
           0.0, 600.0, read_only=False),
    _float("validity.max_nonlinear_fraction", 0.2, "", "fraction of the window's epochs beyond the linear tire "
           "range above which the estimate is not valid", 0.001, 1.0, read_only=False),
    _float("validity.max_suspect_fraction", 0.1, "", "fraction of the window's epochs that follow a rejected "
           "input sample (or a dropped epoch) or that the filter gated, rejected or rolled back, above which the "
           "input is suspect and the estimate not valid (issue #14)", 0.001, 1.0, read_only=False),
    _float("validity.drift_window", 90.0, "s", "span of stiffness updates (since the last surface-change alarm) "
           "that the drift test sums; 0: off", 0.0, 3600.0, read_only=False),
    _float("validity.max_drift_sigmas", 2.5, "", "the sum of those updates, each normalised by its std (N(0, 1) "
           "while the stiffness holds still), beyond this many sqrt(n) makes the estimate invalid: the stiffness "
           "drifts faster than ekf.process_noise lets it follow, and its band lags", 0.1, 100.0, read_only=False),
    _float("validity.max_change_evidence", 0.5, "", "a directional change test's CUSUM (ekf.change_shift, or the "
           "slow change's ekf.change_ramp_shift) past this fraction of its alarm level (ekf.change_shift_threshold, "
           "ekf.change_ramp_threshold) makes the estimate invalid until the alarm or until it falls "
           "back (/diagnostics change_evidence): a new surface is suspected, and the estimate lags it by more than "
           "its band while the test gathers the rest (a 30 % rise: 11 -> 5 % of the valid epochs outside +-2 sigma); "
           "1: off", 0.01, 1.0, read_only=False),
    # diagnostics (evaluation.health.HealthThresholds, plus the publishing period and the latency log)
    _float("diagnostics.stale_timeout", 1.0, "s", "time without a message before an input is reported stale "
           "(ERROR)", 0.01, 3600.0, read_only=False),
    _float("diagnostics.window", 10.0, "s", "span over which rejections, gating and excitation are judged",
           0.1, 3600.0, read_only=False),
    _float("diagnostics.converged_rel_std", 0.05, "", "relative 1-sigma of Cf and Cr below which they count as "
           "converged", 1.0e-6, 10.0, read_only=False),
    _float("diagnostics.min_steering_rms", 0.02, "rad", "steering RMS over the window needed for sufficient "
           "excitation", 0.0, 1.6, read_only=False),
    _float("diagnostics.min_yaw_rate_rms", 0.02, "rad/s", "yaw-rate RMS over the window needed for sufficient "
           "excitation", 0.0, 10.0, read_only=False),
    _int("diagnostics.min_window_epochs", 5, "fewer moving epochs in the window: excitation unknown (WARN)",
         1, 100000, read_only=False),
    _float("diagnostics.rate_window", 5.0, "s", "span of arrivals over which input rates are computed", 0.1,
           3600.0, read_only=False),
    _float("diagnostics.period", 1.0, "s", "time between /diagnostics messages", 0.01, 60.0),
    _str("diagnostics.latency_log", "", "file to append 't latency_s' per published epoch to (empty: off)"),
)

#: dotted key -> row
PARAMS: dict[str, Param] = {row.key: row for row in SCHEMA}
if len(PARAMS) != len(SCHEMA):
    raise ValueError("duplicate key in the parameter schema")


def default_values() -> dict[str, Value]:
    """Every key with its default (float lists as tuples)."""
    return {row.key: row.default for row in SCHEMA}
