"""Message adapters of the `estimator` node: input message types, field extraction, output and diagnostics messages.

The tables map each input message type the schema allows (``topics.*_type``, config/schema.py) to
its rclpy class and to the function that reads the wanted field; the rest converts between ROS
messages and the plain values of the numerics (stamps in float seconds, outputs of an epoch,
:class:`~transplanter_ident.evaluation.health.HealthReport` lines). No node, no callbacks here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import QuaternionStamped, TwistStamped, TwistWithCovarianceStamped, Vector3Stamped
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Bool, Float64

from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.epochs.epoch import Epoch
from transplanter_ident.epochs.frames import stamp_seconds
from transplanter_ident.evaluation.health import HealthReport

#: topics.velocity_type -> (class, message -> geometry_msgs/Vector3 of the velocity)
VELOCITY_TYPES: dict[str, tuple[type, Callable[[Any], Any]]] = {
    "geometry_msgs/msg/TwistStamped": (TwistStamped, lambda msg: msg.twist.linear),
    "geometry_msgs/msg/TwistWithCovarianceStamped": (TwistWithCovarianceStamped, lambda msg: msg.twist.twist.linear),
}
#: topics.heading_type -> (class, message -> geometry_msgs/Quaternion of the orientation)
HEADING_TYPES: dict[str, tuple[type, Callable[[Any], Any]]] = {
    "geometry_msgs/msg/QuaternionStamped": (QuaternionStamped, lambda msg: msg.quaternion),
    "sensor_msgs/msg/Imu": (Imu, lambda msg: msg.orientation),
}
#: topics.steering_type -> class (a JointState carries a stamp and joints, a Float64 only the angle)
STEERING_TYPES: dict[str, type] = {"sensor_msgs/msg/JointState": JointState, "std_msgs/msg/Float64": Float64}


def ros_type_name(msg_type: type) -> str:
    """geometry_msgs.msg.TwistStamped -> 'geometry_msgs/msg/TwistStamped' (as the ROS graph names types)."""
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


def seconds_to_stamp(t: float) -> Time:
    """Float seconds -> builtin_interfaces/Time (nearest nanosecond)."""
    sec = math.floor(t)
    nanosec = round((t - sec) * 1e9)
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return Time(sec=int(sec), nanosec=int(nanosec))


def header_seconds(header: Any) -> float | None:
    """header.stamp in seconds, or None for an unset (zero) stamp (the caller takes the arrival time)."""
    if header.stamp.sec == 0 and header.stamp.nanosec == 0:
        return None
    return stamp_seconds(header.stamp.sec, header.stamp.nanosec)


def joint_position(msg: JointState, joint: str) -> float | None:
    """The position of ``joint`` in a JointState, or None when the joint or its position is missing."""
    try:
        return msg.position[msg.name.index(joint)]
    except (ValueError, IndexError):
        return None


def output_values(epoch: Epoch, est: Estimate) -> tuple[float, ...]:
    """What one epoch publishes (OutputMessages.fill reads them in this order).

    Cf, Cr, their 1-sigma, the model's vy and r, the measured vx, vy, r, the steering offset and its
    1-sigma, and the correlation of the two stiffness states.
    """
    return (est.cornering_stiffness_front, est.cornering_stiffness_rear, est.cornering_stiffness_front_std,
            est.cornering_stiffness_rear_std, est.lateral_velocity_model, est.yaw_rate_model,
            epoch.longitudinal_velocity, epoch.lateral_velocity, epoch.yaw_rate, est.steering_offset,
            est.steering_offset_std, est.stiffness_correlation)


#: (message type, topic) of every per-epoch output, in the order OutputMessages.all() returns them
OUTPUT_TOPICS = ((Vector3Stamped, "~/cornering_stiffness"), (Vector3Stamped, "~/cornering_stiffness_std"),
                 (TwistStamped, "~/model_output"), (TwistStamped, "~/measurement"),
                 (Vector3Stamped, "~/steering_offset"), (Bool, "~/cornering_stiffness_valid"))


class OutputMessages:
    """The output messages, reused for every epoch (``publish()`` serializes at once).

    ``~/cornering_stiffness_std``: x, y = 1-sigma of Cf, Cr; z = the correlation of the two stiffness
    states (ln Cf, ln Cr in the default log mode), so a controller can use the pair's joint uncertainty.
    ``~/steering_offset``: x = the steering-sensor offset (rad, wheel = sensor - offset), y = its 1-sigma.
    """

    def __init__(self, frame_id: str) -> None:
        self.stiffness, self.std, self.offset = Vector3Stamped(), Vector3Stamped(), Vector3Stamped()
        self.model, self.measurement = TwistStamped(), TwistStamped()
        self.valid = Bool()
        for msg in self.stamped():
            msg.header.frame_id = frame_id

    def stamped(self) -> tuple[Any, ...]:
        return self.stiffness, self.std, self.model, self.measurement, self.offset

    def all(self) -> tuple[Any, ...]:
        """The messages in OUTPUT_TOPICS order."""
        return (*self.stamped(), self.valid)

    def fill(self, t: float, values: Sequence[float], valid: bool) -> None:
        """Stamp all with ``t`` and set them from :func:`output_values` and the validity decision."""
        stamp = seconds_to_stamp(t)
        for msg in self.stamped():
            msg.header.stamp = stamp
        self.stiffness.vector.x, self.stiffness.vector.y = values[0], values[1]
        self.std.vector.x, self.std.vector.y, self.std.vector.z = values[2], values[3], values[11]
        self.model.twist.linear.y, self.model.twist.angular.z = values[4], values[5]
        linear, angular = self.measurement.twist.linear, self.measurement.twist.angular
        linear.x, linear.y, angular.z = values[6], values[7], values[8]
        self.offset.vector.x, self.offset.vector.y = values[9], values[10]
        self.valid.data = bool(valid)


def diagnostic_array(stamp: Any, reports: Sequence[HealthReport], hardware_id: str) -> DiagnosticArray:
    """The /diagnostics message: one DiagnosticStatus per health report."""
    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = [DiagnosticStatus(level=bytes([r.level]), name=r.name, message=r.message, hardware_id=hardware_id,
                                     values=[KeyValue(key=k, value=v) for k, v in r.values]) for r in reports]
    return array
