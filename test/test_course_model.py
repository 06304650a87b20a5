"""A single antenna's course as the heading state (``ekf.measurement: course``): model.course_row against a slow version.

The antenna's course is chi = psi + (vy + antenna_x r) / vx. Written out from eq. (4) (test_model.eq4) with
T = [[1, 0, 0], [0, 1, 0], [1 / vx, antenna_x / vx, 1]] mapping [vy, r, psi] to [vy, r, chi], the course
model is T M T^-1 and its discretisation T expm(M dt) T^-1 (scipy); the stiffness derivatives are central
differences of that, the speed's too (T depends on vx).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import scipy.linalg
from test_model import VEHICLE, eq4

from transplanter_ident.ekf.layout import EXACT, W_DE_F, W_DE_R, W_DE_V, W_E
from transplanter_ident.ekf.model import discretize, vehicle_array, work_buffer


def slow_course_matrix(cf: float, cr: float, vx: float, dt: float, antenna_x: float) -> np.ndarray:
    """Expm of the course model over [vy, r, chi, delta, delta'] (rows of the motion states), from eq. (4)."""
    a, b = eq4(VEHICLE, cf, cr, vx)
    m = np.zeros((5, 5))
    m[:2, :2], m[:2, 3] = a, b
    m[2, 1] = 1.0  # psi' = r
    m[3, 4] = 1.0  # the steering ramp
    t = np.eye(5)
    t[2, 0], t[2, 1] = 1.0 / vx, antenna_x / vx
    return (t @ scipy.linalg.expm(m * dt) @ np.linalg.inv(t))[:3]


def fast_course(cf: float, cr: float, vx: float, dt: float, antenna_x: float) -> np.ndarray:
    """W_E, W_DE_F, W_DE_R (per ln C), W_DE_V of the kernel, stacked over the motion rows."""
    vehicle = vehicle_array(replace(VEHICLE, antenna_x=antenna_x), course=True)
    ws = work_buffer()
    discretize(cf, cr, cf, cr, vx, dt, vehicle, True, EXACT, True, ws)
    return np.stack([ws[slot, :3, :5].copy() for slot in (W_E, W_DE_F, W_DE_R, W_DE_V)])


def test_the_course_model_is_the_heading_model_seen_through_the_course() -> None:
    """E to 1e-10 and dE/d ln Cf, dE/d ln Cr, dE/dvx to 1e-5 of their largest entry (central differences)."""
    rng = np.random.default_rng(29)
    for _ in range(25):
        cf, cr = rng.uniform(2000.0, 30000.0, size=2)
        vx, dt, antenna_x = rng.uniform(0.5, 3.0), rng.uniform(0.01, 0.5), rng.uniform(-0.5, 1.0)
        got = fast_course(cf, cr, vx, dt, antenna_x)
        want = slow_course_matrix(cf, cr, vx, dt, antenna_x)
        assert np.max(np.abs(got[0] - want)) <= 1e-10 * np.max(np.abs(want)), (cf, cr, vx, dt, antenna_x)
        h = 1e-5
        differences = (
            (slow_course_matrix(cf * math.exp(h), cr, vx, dt, antenna_x)
             - slow_course_matrix(cf * math.exp(-h), cr, vx, dt, antenna_x)) / (2 * h),
            (slow_course_matrix(cf, cr * math.exp(h), vx, dt, antenna_x)
             - slow_course_matrix(cf, cr * math.exp(-h), vx, dt, antenna_x)) / (2 * h),
            (slow_course_matrix(cf, cr, vx + h, dt, antenna_x) - slow_course_matrix(cf, cr, vx - h, dt, antenna_x))
            / (2 * h),
        )
        for fast, slow in zip(got[1:], differences, strict=True):
            assert np.max(np.abs(slow)) > 1e-6  # a real derivative, not two zeros
            assert np.max(np.abs(fast - slow)) <= 1e-5 * np.max(np.abs(slow)), (cf, cr, vx, dt, antenna_x)


def test_the_course_row_carries_the_stiffness_the_heading_row_does_not() -> None:
    """Guard against a vacuous comparison: the course's row moves with Cf, the heading's hardly over a short dt."""
    vehicle = vehicle_array(VEHICLE)
    ws = work_buffer()
    discretize(8000.0, 10000.0, 8000.0, 10000.0, 2.0, 0.05, vehicle, True, EXACT, False, ws)
    heading_row = np.abs(ws[W_DE_F, 2, :5]).max()
    course_row = np.abs(fast_course(8000.0, 10000.0, 2.0, 0.05, 0.3)[1, 2]).max()
    assert course_row > 5.0 * heading_row  # measured 8.4x
