"""A second truth simulator that shares no code with ``transplanter_ident.sim``: drives to check the estimator on.

The package's simulator integrates the same bicycle model the filter is built on, so agreement
with it can hide a shared mistake. This one is written apart: scipy's adaptive RK45 (not a fixed
RK4 grid), Magic Formula tires (Pacejka: F = D sin(C atan(B a - E (B a - atan(B a)))), D = mu Fz,
B C D = the cornering stiffness, so the small-slip slope is the same C as the truth reports), and
optionally tires whose force lags the slip over a relaxation length. The sensors are the project's
(SensorNoise: antenna velocity in ENU, heading at the GNSS rate, steering at 50 Hz), drawn from a
generator of their own.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

from transplanter_ident.config.parameters import VehicleParams
from transplanter_ident.sim.simulator import SensorNoise, SimResult

GRAVITY = 9.81
#: Pacejka's lateral shape factor and a curvature that keeps the peak round
SHAPE, CURVATURE = 1.3, -1.0


def magic_formula(slip: float, stiffness: float, peak: float) -> float:
    """Lateral force of one tire (N) at ``slip`` (rad): slope ``stiffness`` at 0, at most ``peak``."""
    b = stiffness / (SHAPE * peak)
    x = b * slip
    return peak * math.sin(SHAPE * math.atan(x - CURVATURE * (x - math.atan(x))))


def independent_drive(seed: int, *, speed: float = 2.0, amplitude_deg: float = 15.0, period: float = 6.0,
                      duration: float = 120.0, gnss_rate: float = 5.0, friction: float = 0.8,
                      relaxation_length: float = 0.0, cf: float = 8000.0, cr: float = 10000.0,
                      vehicle: VehicleParams | None = None,
                      surface: tuple[float, float, float] | None = None) -> SimResult:
    """A sine-steer drive at constant speed (the identification drive's shape) through this simulator.

    ``surface``: (time s, stiffness factor, friction): from that time on both tires' cornering stiffness is
    the factor times cf, cr and their friction the one given (a new surface under all four wheels at once).
    """
    vehicle = vehicle or VehicleParams()
    m, iz, lf, lr = vehicle.mass, vehicle.yaw_inertia, vehicle.lf, vehicle.lr
    load_f = m * GRAVITY * lr / (lf + lr) / 2.0  # static load of one front tire
    load_r = m * GRAVITY * lf / (lf + lr) / 2.0
    amplitude, omega = math.radians(amplitude_deg), 2.0 * math.pi / period

    def tires(t: float) -> tuple[float, float]:
        """(stiffness factor, friction) at time t."""
        return (surface[1], surface[2]) if surface is not None and t >= surface[0] else (1.0, friction)

    def steady_forces(t: float, vy: float, r: float) -> tuple[float, float]:
        alpha_f = amplitude * math.sin(omega * t) - (vy + lf * r) / speed
        alpha_r = (lr * r - vy) / speed
        factor, mu = tires(t)
        return (magic_formula(alpha_f, factor * cf, mu * load_f), magic_formula(alpha_r, factor * cr, mu * load_r))

    def rhs(t: float, s: np.ndarray) -> list[float]:
        vy, r = s[0], s[1]
        target_f, target_r = steady_forces(t, vy, r)
        force_f, force_r = (s[3], s[4]) if relaxation_length > 0.0 else (target_f, target_r)
        motion = [(2.0 * force_f + 2.0 * force_r) / m - speed * r, (2.0 * lf * force_f - 2.0 * lr * force_r) / iz, r]
        if relaxation_length > 0.0:
            rate = speed / relaxation_length
            motion += [rate * (target_f - force_f), rate * (target_r - force_r)]
        return motion

    t = np.arange(0.0, duration + 1e-9, 1.0 / gnss_rate)
    start = [0.0] * (5 if relaxation_length > 0.0 else 3)
    solution = solve_ivp(rhs, (0.0, t[-1]), start, t_eval=t, rtol=1e-8, atol=1e-10, max_step=0.02)
    if not solution.success:
        raise RuntimeError(f"independent simulator: {solution.message}")
    vy, r, psi = solution.y[0], solution.y[1], solution.y[2]
    factor = np.array([tires(ti)[0] for ti in t])
    return _sensors(seed, t, vy, r, psi, speed, amplitude, omega, duration, vehicle, cf * factor, cr * factor)


def _sensors(seed: int, t: np.ndarray, vy: np.ndarray, r: np.ndarray, psi: np.ndarray, speed: float,
             amplitude: float, omega: float, duration: float, vehicle: VehicleParams, cf: np.ndarray,
             cr: np.ndarray) -> SimResult:
    """GNSS (antenna velocity in ENU, heading) and steering samples with the project's sensor noise; cf, cr per sample."""
    noise, rng = SensorNoise(), np.random.default_rng([seed, 7919])
    vx_antenna, vy_antenna = speed - r * vehicle.antenna_y, vy + r * vehicle.antenna_x
    east = vx_antenna * np.cos(psi) - vy_antenna * np.sin(psi)
    north = vx_antenna * np.sin(psi) + vy_antenna * np.cos(psi)
    velocity = np.column_stack((east, north)) + noise.velocity * rng.standard_normal((len(t), 2))
    heading = np.angle(np.exp(1j * (psi + noise.heading * rng.standard_normal(len(t)))))
    steering_time = np.arange(0.0, duration + 1e-9, 1.0 / 50.0)
    steering = amplitude * np.sin(omega * steering_time) + noise.steering * rng.standard_normal(len(steering_time))
    ones = np.ones_like(t)
    return SimResult(gnss_time=t, velocity_enu=velocity, heading=heading, steering_time=steering_time,
                     steering=steering, truth_vx=speed * ones, truth_vy=vy, truth_yaw_rate=r, truth_heading=psi,
                     truth_cf=cf * ones, truth_cr=cr * ones, truth_steering=amplitude * np.sin(omega * t))
