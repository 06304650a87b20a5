"""The simulator's sensor models: the GNSS antenna's velocity, correlated GNSS errors, the steering linkage's play.

* the antenna's ENU velocity: the CG's plus r x the lever arm, rotated by the heading (the inverse of the
  assembler's lever-arm compensation, DESIGN.md section 2);
* GNSS errors as first-order Gauss-Markov processes (a receiver's own filter, multipath);
* a steering sensor reading the wheels through a linkage with play (``vehicle.steering_play``); the
  package's compensation (:mod:`transplanter_ident.epochs.steering_play`) shares no code with it.
"""

from __future__ import annotations

import math

import numpy as np

from transplanter_ident.config.parameters import VehicleParams


def correlated(white: np.ndarray, t: np.ndarray, correlation_time: float) -> np.ndarray:
    """Unit-variance first-order Gauss-Markov errors from unit white draws (rows: samples at t)."""
    if correlation_time <= 0.0 or len(t) < 2:
        return white
    a = np.exp(-np.diff(t) / correlation_time)
    out = np.array(white, dtype=float)
    for k in range(1, len(t)):
        out[k] = a[k - 1] * out[k - 1] + math.sqrt(1.0 - a[k - 1] ** 2) * white[k]
    return out


def antenna_velocity_enu(
    vx: np.ndarray, vy: np.ndarray, r: np.ndarray, psi: np.ndarray, vehicle: VehicleParams
) -> np.ndarray:
    """(N, 2) east/north velocity of the antenna: v_cg + r x lever arm, rotated by psi."""
    vxa = vx - r * vehicle.antenna_y
    vya = vy + r * vehicle.antenna_x
    cos_psi, sin_psi = np.cos(psi), np.sin(psi)
    return np.column_stack((vxa * cos_psi - vya * sin_psi, vxa * sin_psi + vya * cos_psi))


def through_play(wheel: np.ndarray, play: float) -> np.ndarray:
    """The angle a steering sensor reads of the wheel angles ``wheel`` through a linkage with ``play`` (rad).

    play > 0: the wheels follow the sensor, which leads them by half the play towards their last motion;
    play < 0: the sensor follows the wheels, moving only once they have crossed the free travel.
    """
    half = 0.5 * abs(play)
    if half == 0.0:
        return wheel
    sensor = np.empty_like(wheel)
    lead = 0.0  # play > 0: the sensor's lead over the wheel
    sensor[0] = wheel[0]
    for k in range(1, len(wheel)):
        if play > 0.0:
            step = wheel[k] - wheel[k - 1]
            lead = half if step > 0.0 else -half if step < 0.0 else lead
            sensor[k] = wheel[k] + lead
        else:
            sensor[k] = min(max(sensor[k - 1], wheel[k] - half), wheel[k] + half)
    return sensor
