"""Message types of the bags, and the decoding of one message into ``(stamp, values)``.

The configured velocity, heading and steering topics are read in every accepted message type
(DESIGN.md section 3):

* velocity, ``geometry_msgs/TwistStamped`` or ``TwistWithCovarianceStamped``: ``(linear.x, linear.y)``;
* heading, ``geometry_msgs/QuaternionStamped`` or ``sensor_msgs/Imu``: ``(yaw,)`` of the quaternion,
  ``atan2(2(wz + xy), 1 - 2(y^2 + z^2))``;
* steering, ``sensor_msgs/JointState`` (joint ``steering.joint_name``) or ``std_msgs/Float64``: ``(angle,)``.

The stamp is ``header.stamp`` in seconds; ``std_msgs/Float64`` has no header and a zero header
stamp means "unset", so those use the log time. Each message is deserialised with the Jazzy
typestore and its fields are taken by an extractor chosen once per connection.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from transplanter_ident.config.schema import PARAMS
from transplanter_ident.epochs.frames import quaternion_yaw, stamp_seconds

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
TWIST_COV_STAMPED = "geometry_msgs/msg/TwistWithCovarianceStamped"
QUATERNION_STAMPED = "geometry_msgs/msg/QuaternionStamped"
IMU = "sensor_msgs/msg/Imu"
JOINT_STATE = "sensor_msgs/msg/JointState"
FLOAT64 = "std_msgs/msg/Float64"
VECTOR3_STAMPED = "geometry_msgs/msg/Vector3Stamped"

ROLES = ("velocity", "heading", "steering")
#: message types accepted per input role (DESIGN.md section 3)
ACCEPTED_TYPES: dict[str, tuple[str, ...]] = {
    "velocity": (TWIST_STAMPED, TWIST_COV_STAMPED),
    "heading": (QUATERNION_STAMPED, IMU),
    "steering": (JOINT_STATE, FLOAT64),
}

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
    """A message that deserialises but lacks what is needed (the reason is the message)."""


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
    linear = msg.twist.twist.linear
    return _stamp(msg, log_ns), (linear.x, linear.y)


def _from_quaternion(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    q = msg.quaternion
    return _stamp(msg, log_ns), (quaternion_yaw(q.x, q.y, q.z, q.w),)


def _from_imu(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    q = msg.orientation
    return _stamp(msg, log_ns), (quaternion_yaw(q.x, q.y, q.z, q.w),)


def _from_joint_state(msg: Any, log_ns: int, joint: str) -> tuple[float, tuple[float, ...]]:
    if joint not in msg.name:
        raise _Unusable(f"joint {joint!r} not in the JointState")
    index = msg.name.index(joint)
    if index >= len(msg.position):
        raise _Unusable(f"joint {joint!r} has no position")
    return _stamp(msg, log_ns), (float(msg.position[index]),)


def _from_float64(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    return seconds(log_ns), (float(msg.data),)


def _from_vector3(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    v = msg.vector
    return _stamp(msg, log_ns), (v.x, v.y, v.z)


def _from_twist_truth(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    twist = msg.twist
    return _stamp(msg, log_ns), (twist.linear.x, twist.linear.y, twist.angular.z)


#: extractor of the input samples per accepted message type
EXTRACTORS: dict[str, Extractor] = {
    TWIST_STAMPED: _from_twist,
    TWIST_COV_STAMPED: _from_twist_cov,
    QUATERNION_STAMPED: _from_quaternion,
    IMU: _from_imu,
    JOINT_STATE: _from_joint_state,
    FLOAT64: _from_float64,
    VECTOR3_STAMPED: _from_vector3,
}


def decode_message(msgtype: str, data: bytes, log_ns: int, joint_name: str = "front_steering") -> tuple:
    """Decode one serialized input message to ``(stamp s, values)`` as the reader does (for tests/tools)."""
    msgtype = normalize_msgtype(msgtype)
    return EXTRACTORS[msgtype](TYPESTORE.deserialize_cdr(data, msgtype), log_ns, joint_name)


# --------------------------------------------------------------------------- reading


# --------------------------------------------------------------------------- writing


