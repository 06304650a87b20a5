"""The measurements' h(x) and the vy row of H (paper eq. 12, with the lever arm and the heading's misalignment).

The assembler turns the GNSS velocity by the *measured* heading psi + h, so it gives, with the
antenna's body-frame lateral velocity vy + antenna_x r and the speed vx it measured along that heading,

    z_vy = (vy + antenna_x r) / cos h - vx tan h  ~  vy + antenna_x r - vx h,
    H[0] = [1 / cos h, antenna_x / cos h, 0, ..., 0, (vy + antenna_x r) tan h / cos h - vx / cos^2 h]

with h the last state (layout.X_HEADING_OFFSET; 0 when not estimated: H[0] = [1, antenna_x, 0..., -vx]).
A body that rolls moves a high antenna sideways too: with ``vehicle.antenna_height`` and
``vehicle.roll_gradient`` the innovation takes out :func:`roll_velocity`, an input's term (H unchanged).
The heading measurement needs no h: the heading state integrates r from the first *measured* heading,
so it holds the measured frame's heading; the prediction runs at the vehicle's forward speed
(:func:`body_speed`). The step writes the row once per epoch
(:func:`predict_vy`, into ws[W_VEC, V_VY_ROW]); the update, the speed's covariance and the model
errors' bias propagation all read it there, so H is written in one place. The readers take its three
non-zero entries only (a hot loop: the step reads the row some twenty times).

A single antenna (``ekf.measurement: course``) measures only the direction of its velocity, its course
psi + atan2(vy + antenna_x r, vx - antenna_y r). The heading state is then that course linearised,
psi + (vy + antenna_x r) / vx (:func:`.model.course_row`), z_vy measures nothing (H[0] = 0), the course's
innovation holds the rest (:func:`course_curvature`), its R is the velocity's over |v|^2
(:func:`course_variance`), and the model runs at the forward speed under |v| (:func:`course_speed`).
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.layout import (
    V_VY_ROW,
    VEH_ANTENNA_X,
    VEH_ANTENNA_Y,
    W_VEC,
    X_PSI,
    X_R,
    X_VY,
)
from transplanter_ident.epochs.frames import wrap_angle
from transplanter_ident.jit import inline_kernel


@inline_kernel
def predict_vy(ws, n, x, antenna_x, speed, course):
    """H(x)'s vy entry for this epoch; H[0]'s non-zero entries (vy, r, h: state n - 1) into ws[W_VEC, V_VY_ROW].

    ``course`` (a single antenna): the velocity turned by its own direction has no lateral part, so z_vy is 0
    and measures nothing: H[0] = 0 and h(x) = 0 (the course itself is the heading state, :func:`course_variance`).
    """
    if course:
        ws[W_VEC, V_VY_ROW, X_VY] = ws[W_VEC, V_VY_ROW, X_R] = ws[W_VEC, V_VY_ROW, n - 1] = 0.0
        return 0.0
    heading_offset = x[n - 1]
    secant, tangent = 1.0 / math.cos(heading_offset), math.tan(heading_offset)
    antenna_vy = x[X_VY] + antenna_x * x[X_R]
    ws[W_VEC, V_VY_ROW, X_VY] = secant
    ws[W_VEC, V_VY_ROW, X_R] = antenna_x * secant
    ws[W_VEC, V_VY_ROW, n - 1] = (antenna_vy * tangent - speed * secant) * secant
    return antenna_vy * secant - speed * tangent


@inline_kernel
def roll_velocity(roll_lever, speed, steering_rate, wheelbase):
    """The antenna's sideways velocity from the body's roll, -H K d(a_y)/dt (``roll_lever`` = H K, s^2).

    The body rolls outward by K a_y; an antenna H above the roll axis moves at -H K d(a_y)/dt. The
    lateral acceleration's rate is taken kinematic, vx^2 d(delta)/dt / (lf + lr), from the interval's
    steering rate: an input, so H stays as it is (on the identification drive with 0.5 deg per m/s^2 at
    1.5 m, seeds 0-9: valid 0 -> 89 % of the epochs, 1.2 % of those outside +-2 sigma; at 1 deg 32 %, 7.6 %;
    docs/robustness.md, Body roll).
    """
    return -roll_lever * speed * speed * steering_rate / wheelbase


@inline_kernel
def body_speed(x, n, antenna_x, speed):
    """The CG's forward speed in the vehicle's axes, from ``speed`` measured along the measured heading.

    vx_m = cos h vx + sin h (vy + antenna_x r), so vx = (vx_m - sin h (vy + antenna_x r)) / cos h (the
    antenna's lateral offset adds a second-order term); the prediction runs at it, the measurement at vx_m.
    """
    heading_offset = x[n - 1]
    if heading_offset == 0.0:
        return speed
    return (speed - math.sin(heading_offset) * (x[X_VY] + antenna_x * x[X_R])) / math.cos(heading_offset)


@inline_kernel
def vy_row_times_motion(ws, v):
    """H[0] v over the motion states (vy, r): for a vector that is zero beyond them (the speed's gain)."""
    return ws[W_VEC, V_VY_ROW, X_VY] * v[X_VY] + ws[W_VEC, V_VY_ROW, X_R] * v[X_R]


@inline_kernel
def vy_row_times(ws, n, v):
    """H[0] v: its three non-zero entries, on vy, r and h (the last of n states)."""
    return vy_row_times_motion(ws, v) + ws[W_VEC, V_VY_ROW, n - 1] * v[n - 1]


@inline_kernel
def vy_row_times_column(ws, n, m, j):
    """(H[0] M)[j] for an n x n matrix M (P)."""
    return (ws[W_VEC, V_VY_ROW, X_VY] * m[X_VY, j] + ws[W_VEC, V_VY_ROW, X_R] * m[X_R, j]
            + ws[W_VEC, V_VY_ROW, n - 1] * m[n - 1, j])


@inline_kernel
def vy_row_quadratic(ws, n, m):
    """H[0] M H[0]^T for an n x n matrix M (the vy measurement's share of S = H P H^T + R)."""
    return (ws[W_VEC, V_VY_ROW, X_VY] * vy_row_times_column(ws, n, m, X_VY)
            + ws[W_VEC, V_VY_ROW, X_R] * vy_row_times_column(ws, n, m, X_R)
            + ws[W_VEC, V_VY_ROW, n - 1] * vy_row_times_column(ws, n, m, n - 1))


@inline_kernel
def course_variance(velocity_variance, speed):
    """R of a course over ground: a velocity error e across the motion turns it by e / |v| (per-axis variance)."""
    return velocity_variance / max(speed * speed, 1.0e-6)


@inline_kernel
def course_speed(vehicle, speed, motion):
    """A single antenna: the CG's forward speed from the antenna's ``speed``, the mean |v| of the interval's ends.

    The antenna moves at (vx - antenna_y r, vy + antenna_x r), so vx = sqrt(|v|^2 - (vy + antenna_x r)^2) +
    antenna_y r, with ``motion`` = (vy, r) over the interval (prediction's ``interval_motion``). At farm speeds
    the stiffness is read off a response within a percent of the kinematic one, and |v| exceeds the forward
    speed by u^2 / 2 (half a percent at u = 0.1 rad, in phase with the steering) and by -antenna_y r.
    """
    vy, r = motion
    lateral = vy + vehicle[VEH_ANTENNA_X] * r
    return math.sqrt(max(speed * speed - lateral * lateral, 0.25 * speed * speed)) + vehicle[VEH_ANTENNA_Y] * r


@inline_kernel
def course_curvature(x, vehicle, vx):
    """What the measured course lacks of the state's: u - atan2(vy + antenna_x r, vx - antenna_y r).

    The state is psi + u with u = (vy + antenna_x r) / vx (model.course_row, linear); the antenna's velocity
    points at psi + atan2(vy + antenna_x r, vx - antenna_y r). H keeps the linear row (the rest is second order).
    """
    lateral = x[X_VY] + vehicle[VEH_ANTENNA_X] * x[X_R]
    return lateral / vx - math.atan2(lateral, vx - vehicle[VEH_ANTENNA_Y] * x[X_R])


@inline_kernel
def second_innovation(x, heading, course, psi, yaw_rate, vehicle, vx):
    """z[1] - h(x)[1]: the heading's (wrapped; a course's with :func:`course_curvature`), or the yaw rate's."""
    if not heading:
        return yaw_rate - x[X_R]
    e1 = wrap_angle(psi - x[X_PSI])
    return e1 + course_curvature(x, vehicle, vx) if course else e1
