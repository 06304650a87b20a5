"""Parameters of the vehicle (paper Table 1, eq. 5) and of the joint-state EKF (eqs. 12, 22).

Frozen dataclasses shared by every driver (node, replay, tuner). Values are SI and N/rad;
noise entries are in the units of the filter state (log or linear stiffness).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

DISCRETIZATIONS = ("exact", "euler")
NOISE_UNITS = ("per_second", "per_step")
STIFFNESS_STATES = ("log", "linear")
MEASUREMENTS = ("heading", "yaw_rate", "course")

#: s, the GNSS-steering timing left after calibration that the band holds while ``ekf.delay_uncertainty`` is not
#: stated (< 0); a heading's delay measure flags 10 ms and more, seldom 5 (docs/robustness.md)
ASSUMED_DELAY_UNCERTAINTY = 0.001


#: where the steering sensor's angle is taken: the single-track angle, or one front wheel's (Ackermann)
STEERING_SENSOR_WHEELS = ("center", "left", "right")


@dataclass(frozen=True)
class VehicleParams:
    """Rigid-body parameters of the 2-DOF bicycle model (paper eq. 4, Table 1)."""

    mass: float = 720.0
    lf: float = 0.7
    lr: float = 0.4
    iz: float = 0.0  # <= 0 means m * lf * lr (eq. 5)
    antenna_x: float = 0.0
    antenna_y: float = 0.0
    max_steering: float = 0.7
    steering_offset: float = 0.0  # rad: wheel angle = sensor - offset (initial value, or fixed)
    steering_scale: float = 1.0  # wheel angle per steering-sensor angle (the sensor's calibrated gain)
    steering_sensor_wheel: str = "center"  # the angle the sensor gives: center (single-track), left or right wheel
    steering_play: float = 0.0  # rad of wheel angle, the linkage's free travel; > 0 wheels follow sensor, < 0 reverse
    track_width: float = 0.0  # m, front track: turns one wheel's angle into the single-track one (Ackermann)
    relaxation_length: float = 0.0  # m: each axle's force builds over this travel (0: at once, eq. 4)
    heading_offset: float = 0.0  # rad: yaw of the GNSS heading source relative to the vehicle x axis
    antenna_height: float = 0.0  # m, the GNSS antenna above the body's roll axis
    roll_gradient: float = 0.0  # rad of body roll (outward) per m/s^2 of lateral acceleration (0: no roll)
    max_speed: float = 5.0  # m/s: a GNSS speed beyond it is rejected
    max_lateral_speed: float = 1.0  # m/s: an epoch with |vy| at the CG beyond it is rejected
    max_yaw_rate: float = 1.5  # rad/s: an epoch with |r| beyond it is rejected
    max_steering_rate: float = 1.5  # rad/s: a steering sample changing faster (plus 0.01 rad) is a spike

    def __post_init__(self) -> None:
        check_fields(self, "vehicle", positive=("mass", "lf", "lr", "max_steering", "max_speed", "max_lateral_speed",
                                                "max_yaw_rate", "max_steering_rate", "steering_scale"),
                     finite=("iz", "antenna_x", "antenna_y", "steering_offset", "heading_offset", "steering_play",
                             "roll_gradient"),
                     non_negative=("track_width", "relaxation_length", "antenna_height"))
        _check_choice("vehicle.steering_sensor_wheel", self.steering_sensor_wheel, STEERING_SENSOR_WHEELS)
        if self.steering_sensor_wheel != "center" and not self.track_width > 0.0:
            raise ValueError("vehicle.track_width must be positive for a steering sensor on one wheel")

    @property
    def roll_lever(self) -> float:
        """s^2: the antenna's sideways travel per m/s^2 of lateral acceleration (antenna_height x roll_gradient)."""
        return self.antenna_height * self.roll_gradient

    @property
    def yaw_inertia(self) -> float:
        """Iz, or its eq. (5) approximation m * lf * lr when not given."""
        return self.iz if self.iz > 0.0 else self.mass * self.lf * self.lr


@dataclass(frozen=True)
class FilterOptions:
    """Structural choices of the filter (DESIGN.md section 1)."""

    discretization: str = "exact"
    stiffness_state: str = "log"
    measurement: str = "heading"
    min_speed: float = 0.3
    stiffness_bounds: tuple[float, float] = (50.0, 1.0e6)
    gate_threshold: float = 25.0  # Mahalanobis d^2 above which an update is gated
    max_gated: int = 5  # this many consecutive gated epochs re-initialise the motion states
    max_interval: float = 2.0  # s; a longer gap re-initialises the motion states
    estimate_steering_offset: bool = True  # the steering-sensor offset as a filter state
    estimate_steering_gain: bool = False  # the steering gain's error left out of vehicle.steering_scale, a state
    estimate_heading_offset: bool = True  # the heading's misalignment left out of vehicle.heading_offset, a state
    process_noise_units: str = "per_second"  # Q as a spectral density, or per GNSS step (old files)
    process_noise_step: float = 0.2  # s: the GNSS interval per-step Q values were tuned for
    linear_range_check: bool = True  # hold the stiffness where the tire leaves its linear range
    max_slip_angle: float = 0.15  # rad: beyond it the tire is taken as nonlinear (stiffness held), whatever its C
    max_lateral_acceleration: float = 2.0  # m/s^2: likewise
    max_tire_utilisation: float = 0.9  # likewise beyond C alpha > this x min_friction x Fz (0: off)
    min_friction: float = 0.3  # lowest friction expected (wet field): the stiffness std holds the bias there; 0 off
    saturation_correction: bool = False  # report Cf, Cr corrected by that bias (min_friction = the field's, if known)
    saturation_prior: float = 0.5  # 1-sigma prior of the saturation the innovations measure (1: min_friction); 0 off
    saturation_memory: float = 300.0  # s, time constant of that measure and of the relaxation length's
    delay_uncertainty: float = -1.0  # s, 1-sigma of the GNSS delay left out of gnss.delay (the std holds its bias); < 0 not stated
    steering_scale_uncertainty: float = 0.003  # relative 1-sigma of the steering gain left out of vehicle.steering_scale
    yaw_inertia_uncertainty: float = 0.0  # relative 1-sigma of the yaw inertia left out of vehicle.iz
    relaxation_uncertainty: float = 0.0  # m, 1-sigma of the tire relaxation length left out of vehicle.relaxation_length
    steering_play_uncertainty: float = 0.0  # rad, 1-sigma of the steering play left out of vehicle.steering_play
    speed_noise: bool = True  # the GNSS speed, the model's input, is noisy: its variance enters Q through dx/dvx
    noise_adaptation: bool = True  # R raised to what the innovations show (covariance matching), never lowered
    noise_memory: float = 60.0  # s, time constant of that measure
    max_noise_scale: float = 100.0  # largest factor on R it may set
    noise_correlation: bool = True  # R widened by the innovations' lag-1 autocorrelation (GNSS errors correlated in time)
    change_detection: bool = True  # the surface-change CUSUM on the innovations
    change_scale: float = 2.0  # innovation variance ratio the surface-change CUSUM tests for
    change_threshold: float = 8.0  # CUSUM alarm level (log-likelihood ratio)
    change_shift: float = 0.7  # mean of the normalised stiffness updates (in their std) the directional test looks for
    change_shift_threshold: float = 10.0  # its CUSUM alarm level (log-likelihood ratio)
    change_ramp_shift: float = 0.3  # the same test for a slow change (a surface changing over a minute); 0: off
    change_ramp_threshold: float = 8.0  # its CUSUM alarm level (log-likelihood ratio)
    change_process_noise: float = 2.0e-2  # stiffness Q density after an alarm, (ln C)^2/s
    change_hold: float = 4.0  # s the raised density lasts after an alarm
    change_offset_variance: float = 3.0e-4  # rad^2 the steering offset may have moved by at an alarm (~1 deg)^2
    measurement_noise_from_covariance: bool = False  # R per epoch: the messages' variances, floored by R
    identifiability_check: bool = True  # a band along a direction the recent data do not pin is the prior's
    identifiability_memory: float = 60.0  # s of recent epochs whose Fisher information is summed
    identifiability_max_epochs: int = 600  # at most this many of them (the latest)
    identifiability_min_steering: float = 0.05  # rad: re-evaluated only while the wheels are turned this much
    identifiability_period: float = 1.0  # s of data between two evaluations of the information
    max_identifiable_rel_std: float = 0.10  # Cramer-Rao 1-sigma (relative) above which a direction is not pinned
    relinearization_window: float = 60.0  # s of stiffness updates at the start with re-linearised passes; 0: one pass
    relinearization_threshold: float = 0.1  # |d ln C| since the pass began that starts a new one

    def __post_init__(self) -> None:
        _check_choice("ekf.discretization", self.discretization, DISCRETIZATIONS)
        _check_choice("ekf.stiffness_state", self.stiffness_state, STIFFNESS_STATES)
        _check_choice("ekf.measurement", self.measurement, MEASUREMENTS)
        low, high = self.stiffness_bounds
        if not (0.0 < low < high and math.isfinite(high)):
            raise ValueError(f"ekf.stiffness_bounds must satisfy 0 < low < high, got {self.stiffness_bounds}")
        if not (self.min_speed >= 0.0 and math.isfinite(self.min_speed)):
            raise ValueError(f"ekf.min_speed must be >= 0, got {self.min_speed}")
        if not self.gate_threshold > 0.0:
            raise ValueError(f"ekf.gate_threshold must be > 0, got {self.gate_threshold}")
        if not self.max_interval > 0.0:
            raise ValueError(f"ekf.max_interval must be > 0, got {self.max_interval}")
        _check_choice("ekf.process_noise_units", self.process_noise_units, NOISE_UNITS)
        check_fields(self, "ekf", positive=("process_noise_step", "saturation_memory", "max_slip_angle", "max_lateral_acceleration",
                                            "change_process_noise", "change_hold", "noise_memory",
                                            "identifiability_memory", "identifiability_period",
                                            "max_identifiable_rel_std"), non_negative=("identifiability_min_steering",
                                                                                   "steering_scale_uncertainty",
                                                                                   "yaw_inertia_uncertainty",
                                                                                   "relaxation_uncertainty",
                                                                                   "steering_play_uncertainty",
                                                                                   "change_offset_variance",
                                                                                   "saturation_prior",
                                                                                   "max_tire_utilisation",
                                                                                   "relinearization_window"))
        if not (math.isfinite(self.relinearization_threshold) and self.relinearization_threshold > 0.0):
            raise ValueError(f"ekf.relinearization_threshold must be > 0, got {self.relinearization_threshold!r}")
        if self.identifiability_max_epochs < 2:
            raise ValueError(f"ekf.identifiability_max_epochs must be >= 2, got {self.identifiability_max_epochs!r}")
        if not (math.isfinite(self.max_noise_scale) and self.max_noise_scale >= 1.0):
            raise ValueError(f"ekf.max_noise_scale must be >= 1, got {self.max_noise_scale!r}")
        if not (math.isfinite(self.change_scale) and self.change_scale > 1.0):
            raise ValueError(f"ekf.change_scale must be > 1, got {self.change_scale!r}")
        for name in ("change_threshold", "change_shift", "change_shift_threshold", "change_ramp_threshold"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"ekf.{name} must be > 0, got {value!r}")
        if not (math.isfinite(self.change_ramp_shift) and self.change_ramp_shift >= 0.0):
            raise ValueError(f"ekf.change_ramp_shift must be >= 0, got {self.change_ramp_shift!r}")
        if not math.isfinite(self.delay_uncertainty):
            raise ValueError(f"ekf.delay_uncertainty must be finite (< 0: not stated), got {self.delay_uncertainty!r}")

    @property
    def heading_state(self) -> bool:
        """Whether the filter carries a heading state (``heading``, or ``course``: the antenna's course over ground)."""
        return self.measurement in ("heading", "course")

    @property
    def course(self) -> bool:
        """A single antenna: the heading state is the antenna's course, measured from the velocity's direction."""
        return self.measurement == "course"

    @property
    def timing_stated(self) -> bool:
        """Whether ``ekf.delay_uncertainty`` states the timing left after ``gnss.delay`` (>= 0)."""
        return self.delay_uncertainty >= 0.0

    @property
    def timing_uncertainty(self) -> float:
        """s, the timing 1-sigma the band holds: the stated one, else :data:`ASSUMED_DELAY_UNCERTAINTY`."""
        return self.delay_uncertainty if self.timing_stated else ASSUMED_DELAY_UNCERTAINTY

    @property
    def heading_offset_estimated(self) -> bool:
        """The heading's misalignment as a state: a dual-antenna heading only (a course has no misalignment)."""
        return self.estimate_heading_offset and self.measurement == "heading"

    @property
    def noise_rate_scale(self) -> float:
        """Factor from the configured Q entries to a spectral density (per second)."""
        return 1.0 if self.process_noise_units == "per_second" else 1.0 / self.process_noise_step


@dataclass(frozen=True)
class NoiseParams:
    """Q, R, the initial state and covariance (paper eqs. 12, 22).

    process_noise: diag Q for vy, r, Cf, Cr as a spectral density (state units squared per
      second; each GNSS interval dt adds Q dt), or per step (``ekf.process_noise_units``).
    measurement_noise: diag R for vy (m/s)^2 and heading rad^2 (or r (rad/s)^2 in yaw_rate mode).
    heading_process_noise: Q density of the heading state (heading mode only), rad^2/s.
    steering_offset_process_noise: Q density of the steering offset, rad^2/s.
    steering_offset_initial_variance: P0 of the steering offset, rad^2 (0 when it is not estimated).
    steering_gain_process_noise: Q density of the steering gain's relative error g (wheel = (1 + g) sensor - b), 1/s.
    steering_gain_initial_variance: its P0 (0 when it is not estimated).
    heading_offset_process_noise: Q density of the heading's misalignment left out of vehicle.heading_offset, rad^2/s.
    heading_offset_initial_variance: its P0, rad^2 (0 when it is not estimated).
    """

    process_noise: tuple[float, float, float, float] = (1.0e-4, 1.0e-4, 1.5e-5, 1.5e-5)
    measurement_noise: tuple[float, float] = (4.0e-4, 1.2e-5)
    heading_process_noise: float = 1.0e-8
    steering_offset_process_noise: float = 1.0e-8
    steering_offset_initial_variance: float = 1.2e-3
    steering_gain_process_noise: float = 1.0e-9
    steering_gain_initial_variance: float = 4.0e-4
    heading_offset_process_noise: float = 1.0e-8
    heading_offset_initial_variance: float = 1.2e-3
    initial_stiffness: tuple[float, float] = (1000.0, 1000.0)
    initial_covariance: tuple[float, float, float, float] = (1.0e-2, 1.0e-2, 4.0, 4.0)
    initial_heading_covariance: float = 1.0e-2

    def __post_init__(self) -> None:
        _check_vector("ekf.process_noise", self.process_noise, 4, allow_zero=True)
        _check_vector("ekf.measurement_noise", self.measurement_noise, 2, allow_zero=False)
        _check_vector("ekf.initial_stiffness", self.initial_stiffness, 2, allow_zero=False)
        _check_vector("ekf.initial_covariance", self.initial_covariance, 4, allow_zero=True)
        _check_vector("ekf.heading_process_noise", (self.heading_process_noise,), 1, allow_zero=True)
        _check_vector("ekf.initial_heading_covariance", (self.initial_heading_covariance,), 1, allow_zero=True)
        _check_vector("ekf.steering_offset_process_noise", (self.steering_offset_process_noise,), 1,
                      allow_zero=True)
        _check_vector("ekf.steering_offset_initial_variance", (self.steering_offset_initial_variance,), 1,
                      allow_zero=True)
        _check_vector("ekf.steering_gain_process_noise", (self.steering_gain_process_noise,), 1, allow_zero=True)
        _check_vector("ekf.steering_gain_initial_variance", (self.steering_gain_initial_variance,), 1,
                      allow_zero=True)
        _check_vector("ekf.heading_offset_process_noise", (self.heading_offset_process_noise,), 1, allow_zero=True)
        _check_vector("ekf.heading_offset_initial_variance", (self.heading_offset_initial_variance,), 1,
                      allow_zero=True)


@dataclass(frozen=True)
class ValiditySettings:
    """Thresholds of the validity decision (the ``validity.*`` parameters)."""

    window: float = 10.0  # s of data over which excitation and consistency are judged
    max_rel_std: float = 0.08  # relative 1-sigma of Cf and Cr
    min_steering_std: float = 0.02  # rad: steering standard deviation over the window
    min_yaw_rate_std: float = 0.02  # rad/s
    nis_quantile_sigmas: float = 3.0  # the windowed NIS sum may exceed its mean by this many sigmas
    max_noise_factor: float = 2.25  # the NIS test takes R x the factor the innovations show up to this; beyond: invalid
    max_autocorrelation: float = 0.6  # lag-1 autocorrelation of the whitened vy innovation
    max_sideslip: float = 0.35  # rad: |vy / vx| beyond it the velocity and heading disagree
    course_ratio: float = 0.2  # RMS vy at the antenna below this fraction of (lr + ax) RMS r: course over ground
    hold_on: float = 3.0  # s every check must hold before valid
    hold_off: float = 1.0  # s a soft check must fail before invalid
    max_nonlinear_fraction: float = 0.2  # of the window's epochs beyond the linear tire range
    max_suspect_fraction: float = 0.1  # of the window's epochs after a rejected sample, or gated/rolled back
    max_delay_sigmas: float = 3.0  # an unconfigured GNSS delay this many std from 0 (the filter's measure) fails
    max_delay_shift: float = 1.5  # the Cf or Cr shift the measured delay implies (lower 1-sigma), in reported std
    max_relaxation_sigmas: float = 3.0  # a tire relaxation length left out, this many std from 0 (the filter's measure)
    max_relaxation_shift: float = 1.0  # the Cf or Cr shift the measured relaxation implies (lower 1-sigma), in std
    max_steering_gain_sigmas: float = 3.0  # a steering gain (or yaw inertia) error this many std from 0 fails
    max_steering_gain_shift: float = 1.5  # the Cf or Cr shift the measured gain error implies (lower 1-sigma), in std
    drift_window: float = 90.0  # s of stiffness updates (since the last change alarm) the drift test sums; 0: off
    max_drift_sigmas: float = 2.5  # their normalised sum beyond +-this x sqrt(n): the stiffness drifts, the band lags
    max_change_evidence: float = 0.5  # the directional change test's CUSUM past this fraction of its alarm level
    max_heading_sigmas: float = 100.0  # a heading misalignment this many std from 0 fails (100: off, the shift decides)
    max_heading_shift: float = 1.5  # the Cf or Cr shift the measured misalignment implies (lower 1-sigma), in std
    max_steering_play_sigmas: float = 3.0  # a steering play left out, this many std from 0 (the filter's measure)
    max_steering_play_shift: float = 1.5  # the Cf or Cr shift the measured play implies (lower 1-sigma), in std

    def __post_init__(self) -> None:
        check_fields(self, "validity", positive=("window", "max_rel_std", "nis_quantile_sigmas",
                                                 "max_autocorrelation", "max_sideslip", "course_ratio",
                                                 "max_nonlinear_fraction", "max_suspect_fraction",
                                                 "max_delay_sigmas", "max_delay_shift", "max_relaxation_sigmas",
                                                 "max_relaxation_shift", "max_steering_gain_sigmas",
                                                 "max_steering_gain_shift", "max_drift_sigmas",
                                                 "max_change_evidence", "max_heading_sigmas", "max_heading_shift",
                                                 "max_steering_play_sigmas", "max_steering_play_shift"),
                     non_negative=("min_steering_std", "min_yaw_rate_std", "hold_on", "hold_off", "drift_window"))
        if isinstance(self.max_noise_factor, bool) or not (math.isfinite(self.max_noise_factor)
                                                           and self.max_noise_factor >= 1.0):
            raise ValueError(f"validity.max_noise_factor must be a finite number >= 1, got {self.max_noise_factor!r}")



@dataclass(frozen=True)
class EstimatorConfig:
    """Everything the filter core needs."""

    vehicle: VehicleParams = field(default_factory=VehicleParams)
    options: FilterOptions = field(default_factory=FilterOptions)
    noise: NoiseParams = field(default_factory=NoiseParams)

    def __post_init__(self) -> None:
        low, high = self.options.stiffness_bounds
        for value in self.noise.initial_stiffness:
            if not low <= value <= high:
                raise ValueError(f"ekf.initial_stiffness entries must lie within ekf.stiffness_bounds "
                                 f"[{low:g}, {high:g}], got {value!r}")


def check_fields(obj: object, namespace: str, *, positive: tuple[str, ...] = (), non_negative: tuple[str, ...] = (),
                 finite: tuple[str, ...] = ()) -> None:
    """Raise ValueError naming ``namespace.field`` for the first field that is not as required."""
    for names, test, what in ((positive, lambda v: v > 0.0, "a positive finite number"),
                              (non_negative, lambda v: v >= 0.0, "a finite number >= 0"),
                              (finite, lambda v: True, "finite")):
        for name in names:
            value = getattr(obj, name)
            if isinstance(value, bool) or not (math.isfinite(value) and test(value)):
                raise ValueError(f"{namespace}.{name} must be {what}, got {value!r}")


def _check_choice(key: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{key} must be one of {', '.join(choices)}, got {value!r}")


def _check_vector(key: str, values: tuple[float, ...], length: int, *, allow_zero: bool) -> None:
    if len(values) != length:
        raise ValueError(f"{key} must have {length} entries, got {len(values)}")
    for value in values:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{key} entries must be finite numbers, got {value!r}")
        if value < 0.0 or (value == 0.0 and not allow_zero):
            bound = ">= 0" if allow_zero else "> 0"
            raise ValueError(f"{key} entries must be {bound}, got {value!r}")
