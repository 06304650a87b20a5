"""Continuous-time truth simulator of the rice transplanter's lateral dynamics.

The truth model is the 2-DOF bicycle model of the paper (Li, Li & Guo 2020) in the body
frame at the CG:

- eq. (1), corrected (DESIGN.md section 1): ``m (dvy/dt + vx r) = 2 Fyf cos(delta) + 2 Fyr``
  and ``Iz dr/dt = 2 lf Fyf cos(delta) - 2 lr Fyr``; with ``small_angle`` cos(delta) is 1;
- eq. (2), tire forces: linear ``F = C alpha``, or the saturating ``Fmax tanh(C alpha / Fmax)``
  (same small-slip slope C, ``Fmax = friction * Fz`` from the static axle load per tire);
- eq. (3), slip angles: ``alpha_f = delta - (vy + lf r) / vx``, ``alpha_r = (lr r - vy) / vx``;
- eq. (4): with linear tires and ``small_angle`` the truth equals the state-space model exactly;
- eq. (5): ``Iz = m lf lr`` unless the vehicle gives Iz (``VehicleParams.yaw_inertia``);
- beyond the paper, ``relaxation_length`` sigma > 0: each tire builds its force over sigma of travel,
  dF/dt = (vx / sigma) (F(alpha) - F), so the forces lag the slip by about sigma / vx (a real tire's
  relaxation length is of the order of its radius). The filter's model has no such lag.

``[vy, r, psi]`` (``psi' = r``) is integrated with classical RK4 on a fixed fine grid; the
steering angle, vx and the stiffness are evaluated at the RK4 stage times. The grid step
divides the GNSS period, so GNSS samples fall on grid points, and it is refined automatically
when a stiff configuration (very low speed, very stiff tires) would make RK4 inaccurate.
The sensors are sampled like real ones: GNSS velocity of the antenna in ENU and the heading
together at ``gnss_rate``, the steering angle at ``steering_rate`` on its own clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from transplanter_ident.config.parameters import VehicleParams, check_fields
from transplanter_ident.epochs.frames import wrap_angle
from transplanter_ident.sim.sensors import antenna_velocity_enu, correlated, through_play
from transplanter_ident.sim.signals import (
    Signal,
    StiffnessSchedule,
    require_finite,
    require_positive,
    sine_steering,
)

GRAVITY = 9.80665  # m/s^2
TIRE_MODELS = ("linear", "saturating")
# RK4 is stable on the negative real axis up to h*|lambda| = 2.79; keeping the step below
# 1 / ||A||_inf keeps the fast lateral modes both stable and accurate.
_MAX_STEP_STIFFNESS = 1.0


# --------------------------------------------------------------------------- steering inputs


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class SensorNoise:
    """1-sigma Gaussian sensor noise; the GNSS errors white, or first-order Gauss-Markov.

    ``correlation_time`` > 0: each GNSS error follows e_k = a e_(k-1) + sqrt(1 - a^2) w_k,
    a = exp(-dt / correlation_time), with the same 1-sigma (a receiver's own filter smooths its
    velocity and heading; multipath drifts slowly). The draws w are the white case's, so a seed
    gives the same noise at 0.
    """

    velocity: float = 0.02  # m/s per axis, GNSS velocity (ENU)
    heading: float = math.radians(0.2)  # rad
    steering: float = math.radians(0.1)  # rad, steering-angle sensor
    correlation_time: float = 0.0  # s, of the GNSS velocity and heading errors (0: white)

    def __post_init__(self) -> None:
        check_fields(self, "noise", non_negative=("velocity", "heading", "steering", "correlation_time"))


@dataclass(frozen=True)
class SimConfig:
    """A simulation scenario. ``speed_profile`` (vx(t), m/s) overrides the constant ``speed``."""

    vehicle: VehicleParams = field(default_factory=VehicleParams)
    duration: float = 120.0  # s
    speed: float = 2.0  # m/s, constant forward speed vx at the CG
    speed_profile: Signal | None = None
    steering: Signal = field(default_factory=lambda: sine_steering(math.radians(15.0), 6.0))
    stiffness: StiffnessSchedule = field(default_factory=StiffnessSchedule)
    tire: str = "linear"  # "linear" | "saturating"
    friction: float = 0.8  # mu of the saturating tire
    gnss_rate: float = 5.0  # Hz, velocity and heading
    steering_rate: float = 50.0  # Hz
    steering_time_offset: float = 0.0  # s, first steering sample time (phase relative to GNSS)
    noise: SensorNoise = field(default_factory=SensorNoise)
    initial_heading: float = 0.0  # rad, ENU yaw
    integration_step: float = 0.002  # s, upper bound; the used step divides 1 / gnss_rate
    seed: int = 0
    small_angle: bool = True  # cos(delta) -> 1, so linear tires reproduce eq. (4) exactly
    steering_offset: float = 0.0  # rad: the steering sensor reads the wheel angle + this
    steering_scale: float = 1.0  # the steering sensor reads the wheel angle x this (a calibration's gain error)
    #: rad: the steering linkage's free travel (vehicle.steering_play): > 0 the wheels follow the sensor through it,
    #: < 0 the sensor follows the wheels
    steering_play: float = 0.0
    gnss_delay: float = 0.0  # s: GNSS messages are stamped this late (the motion is at stamp - delay)
    #: rad: a cross slope along the path (a field's side slope): gravity adds g sin(bank) to dvy/dt (+: to the left)
    bank_angle: float = 0.0
    #: (start s, end s, factor): the GNSS velocity and heading noise is this many times larger in the window
    #: (an RTK fix lost to float); the result's velocity_std/heading_std say what was applied
    gnss_degraded: tuple[float, float, float] = (0.0, 0.0, 1.0)
    #: m: the tires' relaxation length (0: the force follows the slip at once, as in the paper's model)
    relaxation_length: float = 0.0

    def __post_init__(self) -> None:
        if self.tire not in TIRE_MODELS:
            raise ValueError(f"tire must be one of {', '.join(TIRE_MODELS)}, got {self.tire!r}")
        for name in ("duration", "speed", "friction", "gnss_rate", "steering_rate", "integration_step",
                     "steering_scale"):
            require_positive(name, getattr(self, name))
        require_finite("steering_time_offset", self.steering_time_offset)
        require_finite("initial_heading", self.initial_heading)
        require_finite("steering_offset", self.steering_offset)
        require_finite("gnss_delay", self.gnss_delay)
        require_finite("bank_angle", self.bank_angle)
        require_finite("relaxation_length", self.relaxation_length)
        require_finite("steering_play", self.steering_play)
        if self.relaxation_length < 0.0:
            raise ValueError(f"relaxation_length must be >= 0, got {self.relaxation_length!r}")
        if not (len(self.gnss_degraded) == 3 and all(math.isfinite(v) for v in self.gnss_degraded)
                and self.gnss_degraded[2] > 0.0):
            raise ValueError(f"gnss_degraded must be (start, end, factor > 0), got {self.gnss_degraded!r}")


@dataclass(frozen=True)
class SimResult:
    """Sensor samples (with noise) and the ground truth at the GNSS sample times."""

    gnss_time: np.ndarray  # (N,) s, starting at 0: the time of the motion the GNSS samples describe
    velocity_enu: np.ndarray  # (N, 2) east, north velocity of the antenna, with noise
    heading: np.ndarray  # (N,) ENU yaw of the body, wrapped to (-pi, pi], with noise
    steering_time: np.ndarray  # (M,) s
    steering: np.ndarray  # (M,) measured steering angle, with noise
    truth_vx: np.ndarray  # (N,) CG, body frame
    truth_vy: np.ndarray  # (N,) lateral velocity at the CG
    truth_yaw_rate: np.ndarray  # (N,)
    truth_heading: np.ndarray  # (N,) unwrapped ENU yaw
    truth_cf: np.ndarray  # (N,) N/rad per tire
    truth_cr: np.ndarray  # (N,)
    truth_steering: np.ndarray  # (N,) true delta at gnss_time
    gnss_stamp: np.ndarray | None = None  # (N,) s, the GNSS messages' stamps: gnss_time + gnss_delay
    velocity_std: np.ndarray | None = None  # (N,) m/s per axis: the 1-sigma noise applied to each velocity
    heading_std: np.ndarray | None = None  # (N,) rad: likewise for each heading

    def __post_init__(self) -> None:
        if self.gnss_stamp is None:
            object.__setattr__(self, "gnss_stamp", self.gnss_time)


# --------------------------------------------------------------------------- simulation


@dataclass(frozen=True)
class _Inputs:
    """Exogenous signals on the half-step grid: entries 2k, 2k+1, 2k+2 are the RK4 stages of step k."""

    step: float
    vx: np.ndarray
    delta: np.ndarray
    cf: np.ndarray
    cr: np.ndarray


def simulate(config: SimConfig) -> SimResult:
    """Integrate the truth model and sample the sensors."""
    gnss_time = _sample_times(0.0, config.gnss_rate, config.duration)
    steering_time = _sample_times(config.steering_time_offset, config.steering_rate, config.duration)
    inputs, stride = _build_inputs(config, n_periods=len(gnss_time) - 1)
    vy, r, psi = _integrate(config, inputs)
    vy, r, psi = vy[::stride], r[::stride], psi[::stride]

    vx = _speed(config, gnss_time)
    cf, cr = config.stiffness.at(gnss_time)
    delta_true = _evaluate(config.steering, gnss_time)
    vel_enu = antenna_velocity_enu(vx, vy, r, psi, config.vehicle)

    rng = np.random.default_rng(config.seed)
    noise = config.noise
    start, end, factor = config.gnss_degraded
    scale = np.where((gnss_time >= start) & (gnss_time < end), factor, 1.0)
    vel_errors = correlated(rng.standard_normal(vel_enu.shape), gnss_time, noise.correlation_time)
    vel_meas = vel_enu + (noise.velocity * scale)[:, None] * vel_errors
    heading_errors = correlated(rng.standard_normal(psi.shape), gnss_time, noise.correlation_time)
    heading_meas = wrap_angle(psi + noise.heading * scale * heading_errors)
    wheel = _evaluate(config.steering, steering_time)
    steer_meas = (config.steering_scale * through_play(wheel, config.steering_play)
                  + noise.steering * rng.standard_normal(steering_time.shape)
                  + config.steering_offset)

    return SimResult(
        gnss_time=gnss_time,
        velocity_enu=vel_meas,
        heading=heading_meas,
        steering_time=steering_time,
        steering=steer_meas,
        truth_vx=vx,
        truth_vy=vy,
        truth_yaw_rate=r,
        truth_heading=psi,
        truth_cf=cf,
        truth_cr=cr,
        truth_steering=delta_true,
        gnss_stamp=gnss_time + config.gnss_delay,
        velocity_std=noise.velocity * scale,
        heading_std=noise.heading * scale,
    )


def _sample_times(offset: float, rate: float, duration: float) -> np.ndarray:
    """Sample times offset + k / rate, k = 0, 1, ..., up to duration (1e-9 s tolerance)."""
    count = math.floor((duration - offset) * rate + 1e-9) + 1
    return offset + np.arange(max(count, 0)) / rate


def _speed(config: SimConfig, t: np.ndarray) -> np.ndarray:
    if config.speed_profile is None:
        return np.full(np.shape(t), config.speed, dtype=float)
    return _evaluate(config.speed_profile, t)


def _evaluate(signal: Signal, t: np.ndarray) -> np.ndarray:
    """signal(t) as a float array of the shape of t (a scalar result is broadcast)."""
    return np.broadcast_to(np.asarray(signal(t), dtype=float), np.shape(t)).copy()


def _build_inputs(config: SimConfig, n_periods: int) -> tuple[_Inputs, int]:
    """Signals on the integration grid, and the number of steps per GNSS period."""
    period = 1.0 / config.gnss_rate
    stride = max(1, math.ceil(period / config.integration_step - 1e-9))
    while True:
        inputs = _evaluate_inputs(config, period / stride, n_periods * stride)
        fastest = _max_system_norm(inputs, config.vehicle)
        if config.relaxation_length > 0.0:
            fastest = max(fastest, float(np.max(inputs.vx)) / config.relaxation_length)
        refine = math.ceil(inputs.step * fastest / _MAX_STEP_STIFFNESS)
        if refine <= 1:
            return inputs, stride
        stride *= refine


def _evaluate_inputs(config: SimConfig, step: float, n_steps: int) -> _Inputs:
    t_half = np.arange(2 * n_steps + 1) * (0.5 * step)
    vx = _speed(config, t_half)
    if not np.all(np.isfinite(vx)) or np.any(vx <= 0.0):
        raise ValueError(
            "vx must stay positive and finite: the slip angles of eq. (3) are singular at vx = 0"
        )
    delta = _evaluate(config.steering, t_half)
    if not np.all(np.isfinite(delta)):
        raise ValueError("the steering function must return finite values")
    cf, cr = config.stiffness.at(t_half)
    return _Inputs(step=step, vx=vx, delta=delta, cf=cf, cr=cr)


def _max_system_norm(inputs: _Inputs, vehicle: VehicleParams) -> float:
    """Largest ||A||_inf of eq. (4) on the grid; bounds the fastest mode (also for saturating tires)."""
    m, iz, lf, lr = vehicle.mass, vehicle.yaw_inertia, vehicle.lf, vehicle.lr
    cf, cr, vx = inputs.cf, inputs.cr, inputs.vx
    row_vy = 2.0 * (cf + cr) / (m * vx) + np.abs(vx + 2.0 * (cf * lf - cr * lr) / (m * vx))
    row_r = np.abs(2.0 * (cr * lr - cf * lf)) / (iz * vx) + 2.0 * (lf**2 * cf + lr**2 * cr) / (iz * vx)
    return float(np.max(np.maximum(row_vy, row_r)))


def _integrate(config: SimConfig, inputs: _Inputs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RK4 over the grid; returns vy, r, psi at every grid point (n_steps + 1 values each)."""
    if config.relaxation_length > 0.0:
        return _integrate_lagged(config, inputs)
    h = inputs.step
    n_steps = (len(inputs.vx) - 1) // 2
    deriv = _derivative(config, inputs)
    vy_out = np.empty(n_steps + 1)
    r_out = np.empty(n_steps + 1)
    psi_out = np.empty(n_steps + 1)
    vy, r, psi = 0.0, 0.0, config.initial_heading
    vy_out[0], r_out[0], psi_out[0] = vy, r, psi
    half, sixth = 0.5 * h, h / 6.0
    for k in range(n_steps):
        a1, b1 = deriv(vy, r, 2 * k)
        vy2, r2 = vy + half * a1, r + half * b1
        a2, b2 = deriv(vy2, r2, 2 * k + 1)
        vy3, r3 = vy + half * a2, r + half * b2
        a3, b3 = deriv(vy3, r3, 2 * k + 1)
        vy4, r4 = vy + h * a3, r + h * b3
        a4, b4 = deriv(vy4, r4, 2 * k + 2)
        psi += sixth * (r + 2.0 * r2 + 2.0 * r3 + r4)
        vy += sixth * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        r += sixth * (b1 + 2.0 * b2 + 2.0 * b3 + b4)
        vy_out[k + 1], r_out[k + 1], psi_out[k + 1] = vy, r, psi
    return vy_out, r_out, psi_out


def _integrate_lagged(config: SimConfig, inputs: _Inputs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RK4 of [vy, r, psi, Ff, Fr] with tire forces lagging their slip over ``relaxation_length``."""
    h = inputs.step
    n_steps = (len(inputs.vx) - 1) // 2
    steady = _tire_forces(config, inputs)
    motion = _motion(config, inputs)
    rate = (inputs.vx / config.relaxation_length).tolist()

    def deriv(s: np.ndarray, i: int) -> np.ndarray:
        target_f, target_r = steady(s[0], s[1], i)
        dvy, dr = motion(s[3], s[4], s[1], i)
        return np.array([dvy, dr, s[1], rate[i] * (target_f - s[3]), rate[i] * (target_r - s[4])])

    state = np.array([0.0, 0.0, config.initial_heading, *steady(0.0, 0.0, 0)])
    out = np.empty((n_steps + 1, 3))
    out[0] = state[:3]
    for k in range(n_steps):
        k1 = deriv(state, 2 * k)
        k2 = deriv(state + 0.5 * h * k1, 2 * k + 1)
        k3 = deriv(state + 0.5 * h * k2, 2 * k + 1)
        k4 = deriv(state + h * k3, 2 * k + 2)
        state = state + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        out[k + 1] = state[:3]
    return out[:, 0], out[:, 1], out[:, 2]


def _motion(config: SimConfig, inputs: _Inputs) -> Callable[[float, float, float, int], tuple[float, float]]:
    """(dvy/dt, dr/dt) of eq. (1) from the tire forces per tire (Ff, Fr), r and half-grid index i."""
    vehicle = config.vehicle
    m, iz, lr = vehicle.mass, vehicle.yaw_inertia, vehicle.lr
    cos_delta = np.ones_like(inputs.delta) if config.small_angle else np.cos(inputs.delta)
    vx = inputs.vx.tolist()
    front = (2.0 * cos_delta / m).tolist()
    front_yaw = (2.0 * vehicle.lf * cos_delta / iz).tolist()
    rear, rear_yaw = 2.0 / m, -2.0 * lr / iz
    slope = GRAVITY * math.sin(config.bank_angle)

    def motion(force_f: float, force_r: float, r: float, i: int) -> tuple[float, float]:
        return (front[i] * force_f + rear * force_r - vx[i] * r + slope,
                front_yaw[i] * force_f + rear_yaw * force_r)

    return motion


def _tire_forces(config: SimConfig, inputs: _Inputs) -> Callable[[float, float, int], tuple[float, float]]:
    """(Ff, Fr) per tire of eqs. (2)-(3) at (vy, r) and half-grid index i, with the tire model of the config."""
    lf, lr = config.vehicle.lf, config.vehicle.lr
    inv_vx = (1.0 / inputs.vx).tolist()
    delta = inputs.delta.tolist()
    cf, cr = inputs.cf.tolist(), inputs.cr.tolist()
    fmax_f, fmax_r = axle_force_limits(config.vehicle, config.friction)

    def linear(vy: float, r: float, i: int) -> tuple[float, float]:
        return cf[i] * (delta[i] - (vy + lf * r) * inv_vx[i]), cr[i] * ((lr * r - vy) * inv_vx[i])

    def saturating(vy: float, r: float, i: int) -> tuple[float, float]:
        force_f, force_r = linear(vy, r, i)
        return fmax_f * math.tanh(force_f / fmax_f), fmax_r * math.tanh(force_r / fmax_r)

    return saturating if config.tire == "saturating" else linear


def _derivative(config: SimConfig, inputs: _Inputs) -> Callable[[float, float, int], tuple[float, float]]:
    """(dvy/dt, dr/dt) of eq. (1) at half-grid index i, with the forces following the slip at once."""
    forces, motion = _tire_forces(config, inputs), _motion(config, inputs)

    def derivative(vy: float, r: float, i: int) -> tuple[float, float]:
        force_f, force_r = forces(vy, r, i)
        return motion(force_f, force_r, r, i)

    return derivative


def axle_force_limits(vehicle: VehicleParams, friction: float) -> tuple[float, float]:
    """Fmax per tire, front and rear: friction * static axle load / 2."""
    wheelbase = vehicle.lf + vehicle.lr
    weight = vehicle.mass * GRAVITY
    return (
        friction * weight * vehicle.lr / wheelbase / 2.0,
        friction * weight * vehicle.lf / wheelbase / 2.0,
    )


