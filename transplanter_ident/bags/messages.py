"""Message types of the bags, and the decoding of one message into ``(stamp, values)``.

The configured velocity, heading and steering topics are read in every accepted message type
(DESIGN.md section 3, issue #12). Each becomes a sample for one input of the
:class:`~transplanter_ident.epochs.assembler.EpochAssembler` (``assemble``'s names):

* velocity, ``geometry_msgs/TwistStamped``: ``velocity`` ``(linear.x, linear.y)`` in frames.velocity;
  ``TwistWithCovarianceStamped``: the same plus the covariance diagonal ``(c[0], c[7])`` (a negative or
  NaN entry is a driver's invalid marker); ``nav_msgs/Odometry``: ``velocity_body``, the twist in the
  child (body) frame with its covariance diagonal;
* heading, ``geometry_msgs/QuaternionStamped``, ``sensor_msgs/Imu``, ``PoseWithCovarianceStamped`` or
  ``nav_msgs/Odometry``: ``heading_quaternion`` ``(x, y, z, w[, yaw variance])`` of the orientation (the
  assembler checks its norm and takes its yaw; the variance, where the type has one, serves
  ``ekf.measurement_noise_from_covariance``). One Odometry topic may serve velocity and heading;
* steering, ``sensor_msgs/JointState`` (joint ``steering.joint_name``; duplicate names refused),
  ``std_msgs/Float64`` or ``std_msgs/Float32``: ``steering`` ``(angle,)``.

The stamp is ``header.stamp`` in seconds; ``std_msgs/Float64`` and ``Float32`` have no header and a zero header
stamp means "unset", so those use the log time (the receive time of the recorder; online the node
takes its ROS clock, which ``ros2 bag play --clock`` with use_sim_time makes the log time again).
Each message is deserialised with the Jazzy typestore and its fields are taken by an extractor
chosen once per connection.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from transplanter_ident.config.schema import PARAMS
from transplanter_ident.epochs.checks import OTHER, joint_angle
from transplanter_ident.epochs.frames import YAW_VARIANCE_IMU, YAW_VARIANCE_POSE, stamp_seconds
from transplanter_ident.epochs.settings import INPUT_ROLES

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
TWIST_COV_STAMPED = "geometry_msgs/msg/TwistWithCovarianceStamped"
QUATERNION_STAMPED = "geometry_msgs/msg/QuaternionStamped"
IMU = "sensor_msgs/msg/Imu"
POSE_COV_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
JOINT_STATE = "sensor_msgs/msg/JointState"
FLOAT64 = "std_msgs/msg/Float64"
FLOAT32 = "std_msgs/msg/Float32"
VECTOR3_STAMPED = "geometry_msgs/msg/Vector3Stamped"

ROLES = INPUT_ROLES
TRUTH_STIFFNESS_TOPIC = "/sim/cornering_stiffness"  # Vector3Stamped: x = Cf, y = Cr
TRUTH_VELOCITY_TOPIC = "/sim/body_velocity"  # TwistStamped at the CG: linear.x vx, linear.y vy, angular.z r

#: the node's outputs (DESIGN.md section 3), relative to its namespace
OUTPUT_NAMESPACE = "/estimator"
OUTPUT_STIFFNESS = "cornering_stiffness"
OUTPUT_STIFFNESS_STD = "cornering_stiffness_std"
OUTPUT_MODEL = "model_output"
OUTPUT_MEASUREMENT = "measurement"
OUTPUT_FRAME_ID = str(PARAMS["output.frame_id"].default)  # "base_link"; replay -o takes the parameter

NS_PER_S = 1_000_000_000


def seconds(ns: int) -> float:
    """Nanoseconds to seconds (the one conversion used for header stamps and log times)."""
    return ns / 1e9


def to_ns(t: float) -> int:
    """Seconds to integer nanoseconds (rounded)."""
    return int(round(t * 1e9))


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a pure rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def normalize_msgtype(msgtype: str) -> str:
    """``pkg/Type`` -> ``pkg/msg/Type``; ROS 2 names pass unchanged."""
    parts = msgtype.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype


# --------------------------------------------------------------------------- field extraction


class _Unusable(Exception):
    """A message that deserialises but lacks what is needed (the reason is the message; ``kind`` its class)."""

    def __init__(self, reason: str, kind: str = OTHER) -> None:
        super().__init__(reason)
        self.kind = kind


#: errors of deserialising one message's bytes (rosbags wraps struct/unicode/value errors in SerdeError)
_DECODE_ERRORS = (SerdeError, ValueError, IndexError)

#: (deserialised message, log ns, steering joint name) -> (stamp s, values)
Extractor = Callable[[Any, int, str], tuple[float, tuple[float, ...]]]


def _stamp(msg: Any, log_ns: int) -> float:
    """``header.stamp`` in seconds, or the log time when the stamp is zero (unset)."""
    stamp = msg.header.stamp
    return stamp_seconds(stamp.sec, stamp.nanosec) if (stamp.sec or stamp.nanosec) else seconds(log_ns)


def _from_twist(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    linear = msg.twist.linear
    return _stamp(msg, log_ns), (linear.x, linear.y)


def _from_twist_cov(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    linear, covariance = msg.twist.twist.linear, msg.twist.covariance
    return _stamp(msg, log_ns), (linear.x, linear.y, float(covariance[0]), float(covariance[7]))


def _from_odometry_twist(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    linear, covariance = msg.twist.twist.linear, msg.twist.covariance
    return _stamp(msg, log_ns), (linear.x, linear.y, float(covariance[0]), float(covariance[7]))


def _quaternion(q: Any) -> tuple[float, float, float, float]:
    return float(q.x), float(q.y), float(q.z), float(q.w)


def _from_quaternion(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    return _stamp(msg, log_ns), _quaternion(msg.quaternion)


def _from_imu(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    return _stamp(msg, log_ns), (*_quaternion(msg.orientation), float(msg.orientation_covariance[YAW_VARIANCE_IMU]))


def _from_pose(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    pose = msg.pose
    return _stamp(msg, log_ns), (*_quaternion(pose.pose.orientation), float(pose.covariance[YAW_VARIANCE_POSE]))


def _from_joint_state(msg: Any, log_ns: int, joint: str) -> tuple[float, tuple[float, ...]]:
    angle, kind, reason = joint_angle(msg.name, msg.position, joint)
    if angle is None:
        raise _Unusable(reason, kind)
    return _stamp(msg, log_ns), (angle,)


def _from_float_data(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    """std_msgs/Float64 or Float32: no header, so the log time."""
    return seconds(log_ns), (float(msg.data),)


def _from_vector3(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    v = msg.vector
    return _stamp(msg, log_ns), (v.x, v.y, v.z)


def _from_twist_truth(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    twist = msg.twist
    return _stamp(msg, log_ns), (twist.linear.x, twist.linear.y, twist.angular.z)


#: role -> accepted message type -> (the assembler input its samples go to, extractor) (DESIGN.md section 3)
INPUT_TYPES: dict[str, dict[str, tuple[str, Extractor]]] = {
    "velocity": {TWIST_STAMPED: ("velocity", _from_twist), TWIST_COV_STAMPED: ("velocity", _from_twist_cov),
                 ODOMETRY: ("velocity_body", _from_odometry_twist)},
    "heading": {QUATERNION_STAMPED: ("heading_quaternion", _from_quaternion),
                IMU: ("heading_quaternion", _from_imu),
                POSE_COV_STAMPED: ("heading_quaternion", _from_pose),
                ODOMETRY: ("heading_quaternion", _from_pose)},
    "steering": {JOINT_STATE: ("steering", _from_joint_state), FLOAT64: ("steering", _from_float_data),
                 FLOAT32: ("steering", _from_float_data)},
}
#: message types accepted per input role
ACCEPTED_TYPES: dict[str, tuple[str, ...]] = {role: tuple(types) for role, types in INPUT_TYPES.items()}
#: extractor per message type, for the role a type serves first (Odometry: velocity)
EXTRACTORS: dict[str, Extractor] = {
    **{msgtype: entry[1] for role in reversed(ROLES) for msgtype, entry in INPUT_TYPES[role].items()},
    VECTOR3_STAMPED: _from_vector3,
}


def decode_message(msgtype: str, data: bytes, log_ns: int, joint_name: str = "front_steering",
                   role: str | None = None) -> tuple:
    """Decode one serialized input message to ``(stamp s, values)`` as the reader does (for tests/tools).

    ``role`` picks what a nav_msgs/Odometry is read as (velocity, the default, or heading).
    """
    msgtype = normalize_msgtype(msgtype)
    extract = INPUT_TYPES[role][msgtype][1] if role is not None else EXTRACTORS[msgtype]
    return extract(TYPESTORE.deserialize_cdr(data, msgtype), log_ns, joint_name)
