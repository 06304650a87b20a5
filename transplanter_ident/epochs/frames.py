"""Frames, angles and stamps: GNSS velocity and heading into the body frame at the CG.

* heading: ENU yaw, or compass heading (clockwise from north) for ``ned``; unwrapped across +-pi;
* velocity: ENU or NED, rotated into the body frame by the heading;
* lever arm: v_cg = v_antenna - r x p_antenna;
* :func:`wrap_angle`, the one angle wrap of the package (compiled: the filter kernels call it too).
"""

from __future__ import annotations

import math

from transplanter_ident.jit import entry_kernel


@entry_kernel
def wrap_angle(angle):  # noqa: ANN001, ANN201 - a float or an array, compiled for each
    """Wrap to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


#: the yaw variance's index in sensor_msgs/Imu orientation_covariance (3x3, row-major) and in a
#: PoseWithCovariance covariance (6x6 over x, y, z, roll, pitch, yaw)
YAW_VARIANCE_IMU = 8
YAW_VARIANCE_POSE = 35

def stamp_seconds(sec: int, nanosec: int) -> float:
    """A ROS time (sec, nanosec) in seconds, via integer nanoseconds (node and bag reader alike)."""
    return (sec * 1_000_000_000 + nanosec) / 1e9


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rotation about z) of an orientation quaternion; NaN if it is non-finite or of zero norm."""
    if not all(math.isfinite(c) for c in (x, y, z, w)) or x * x + y * y + z * z + w * w < 1e-12:
        return math.nan
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def heading_to_enu_yaw(heading: float, frame: str) -> float:
    """ENU yaw from an ENU yaw (``enu``) or a compass heading, clockwise from north (``ned``)."""
    return heading if frame == "enu" else math.pi / 2.0 - heading


def velocity_to_enu(first: float, second: float, frame: str) -> tuple[float, float]:
    """(east, north) from (east, north) for ``enu`` or (north, east) for ``ned``."""
    return (first, second) if frame == "enu" else (second, first)


def body_velocity(east: float, north: float, yaw: float) -> tuple[float, float]:
    """Rotate an ENU ground velocity into the body frame (x forward, y left)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return c * east + s * north, -s * east + c * north


def lateral_variance(variance_first: float, variance_second: float, yaw: float) -> float:
    """Variance of the body-frame vy of :func:`body_velocity` from the two axes' variances (no cross term).

    0 (unknown, the ROS convention for a zero covariance) unless both are given (> 0).
    """
    if not (variance_first > 0.0 and variance_second > 0.0):
        return 0.0
    s, c = math.sin(yaw), math.cos(yaw)
    return s * s * variance_first + c * c * variance_second


def interval_rate_variance(start: float, end: float, dt: float) -> float:
    """Variance of (end - start) / dt from the two angles' reported variances (0: unknown, as either is)."""
    return (start + end) / (dt * dt) if start > 0.0 and end > 0.0 else 0.0


def remove_lever_arm(vx: float, vy: float, yaw_rate: float, antenna_x: float,
                     antenna_y: float) -> tuple[float, float]:
    """CG velocity from the antenna's: v_cg = v_ant - r e_z x p_ant."""
    return vx + yaw_rate * antenna_y, vy - yaw_rate * antenna_x


def unwrap_heading(previous_unwrapped: float, wrapped: float) -> float:
    """Continue an unwrapped heading with a new wrapped sample (the shortest turn)."""
    return previous_unwrapped + wrap_angle(wrapped - previous_unwrapped)
