"""Input checks shared by the node and the bag reader: rejection kinds, invalid markers, quaternions, joints.

Every sample the estimator does not use becomes a :class:`~.epoch.Rejection` with a reason and a
``kind`` (the class of the reason, DESIGN.md section 6 and issue #14): the diagnostics count each
kind, and the log throttle is keyed by it. The field checks here are pure functions on plain
numbers, so the node (rclpy messages) and the bag reader (rosbags messages) reject the same
messages for the same reasons:

* :func:`covariance_problem`: a velocity whose covariance diagonal is negative or NaN carries a
  driver's invalid marker (swiftnav: zeros with covariance[0] = -1; septentrio: NaN fields);
* :func:`quaternion_problem`: an orientation is a heading only if it is finite and its norm is
  within :data:`QUATERNION_NORM_TOLERANCE` of 1 (a norm-3 quaternion is not an orientation);
* :func:`joint_angle`: the steering joint of a sensor_msgs/JointState, refused when any joint
  name is listed twice (which position would be meant is unknowable).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

# kinds of rejection (Rejection.kind)
NON_FINITE = "non_finite"
INVALID_MARKER = "invalid_marker"
STAMP_ORDER = "stamp_order"
STAMP_JUMP = "stamp_jump"
RESYNC = "time_resync"
SPEED_LIMIT = "speed_limit"
LATERAL_SPEED_LIMIT = "lateral_speed_limit"
YAW_RATE_LIMIT = "yaw_rate_limit"
STEERING_LIMIT = "steering_limit"
STEERING_RATE = "steering_rate"
QUATERNION_NORM = "quaternion_norm"
MISSING_JOINT = "missing_joint"
DUPLICATE_JOINT = "duplicate_joint"
UNPAIRED = "unpaired"
SURPLUS = "gnss_surplus"
NO_STEERING = "no_steering"
UNDECODABLE = "undecodable"
WRONG_TYPE = "wrong_type"
OTHER = "other"

#: one line per kind whose reasons carry per-sample numbers (a summary counts them together)
SUMMARY_LABELS = {
    NON_FINITE: "non-finite value",
    INVALID_MARKER: "invalid marker (negative or NaN covariance diagonal)",
    STAMP_JUMP: "stamp beyond gnss.max_stamp_jump from the others (an outlier)",
    RESYNC: "time base stepped: re-synchronised",
    SPEED_LIMIT: "speed beyond vehicle.max_speed",
    LATERAL_SPEED_LIMIT: "lateral speed beyond vehicle.max_lateral_speed",
    YAW_RATE_LIMIT: "yaw rate beyond vehicle.max_yaw_rate",
    STEERING_RATE: "steering spike beyond vehicle.max_steering_rate",
    QUATERNION_NORM: "orientation quaternion not of norm 1",
    DUPLICATE_JOINT: "joint names listed twice in the JointState",
    UNPAIRED: "no partner within gnss.pairing_tolerance",
    SURPLUS: "a GNSS stream faster than its partner: samples without one are not used",
}

#: kinds that do not make the input suspect (validity.max_suspect_fraction): a faster GNSS stream's surplus
#: (a set-up), and the node's check of a publisher's type (offline has none)
NOT_SUSPECT = frozenset({SURPLUS, WRONG_TYPE})

#: rad: a steering change within max_steering_rate dt plus this is no spike (sensor noise at a high rate)
STEERING_NOISE = 0.01

#: the largest | |q| - 1 | of an orientation quaternion taken as a heading (float32 drivers stay far below)
QUATERNION_NORM_TOLERANCE = 0.01


def covariance_problem(variance_x: float, variance_y: float) -> str | None:
    """Why a velocity with these covariance diagonal entries (linear x, y) must not be used, or None.

    A negative or NaN variance is a driver's "invalid" marker (REP 145 style -1); zero means unknown
    and is accepted. Only the entries of the used components count (drivers mark the unsupported
    angular part with -1 too).
    """
    if any(math.isnan(v) or v < 0.0 for v in (variance_x, variance_y)):
        return (f"invalid marker: covariance diagonal ({variance_x:g}, {variance_y:g}) negative or NaN "
                "(the driver flags the velocity as invalid)")
    return None


def quaternion_problem(x: float, y: float, z: float, w: float,
                       tolerance: float = QUATERNION_NORM_TOLERANCE) -> tuple[str, str] | None:
    """(kind, reason) why an orientation quaternion is no heading, or None when it is one."""
    if not all(math.isfinite(c) for c in (x, y, z, w)):
        return NON_FINITE, f"non-finite orientation quaternion {(x, y, z, w)}"
    norm_sq = x * x + y * y + z * z + w * w
    if norm_sq < 1e-12:
        return QUATERNION_NORM, "orientation quaternion of zero norm"
    norm = math.sqrt(norm_sq)
    if abs(norm - 1.0) > tolerance:
        return QUATERNION_NORM, f"orientation quaternion of norm {norm:.4g}, not within {tolerance:g} of 1"
    return None


def joint_angle(names: Sequence[str], positions: Sequence[float], joint: str) -> tuple[float | None, str, str]:
    """(position of ``joint``, "", "") or (None, kind, reason) for a JointState's names and positions."""
    names = list(names)
    if len(set(names)) != len(names):
        duplicates = sorted(name for name, n in Counter(names).items() if n > 1)
        return None, DUPLICATE_JOINT, f"joint name(s) {', '.join(map(repr, duplicates))} listed twice in the JointState"
    if joint not in names:
        return None, MISSING_JOINT, f"joint {joint!r} not in the JointState"
    index = names.index(joint)
    if index >= len(positions):
        return None, MISSING_JOINT, f"joint {joint!r} has no position"
    return float(positions[index]), "", ""
