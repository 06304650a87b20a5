"""Message adapters of the `estimator` node: input QoS and types, field extraction, output and diagnostics messages.

:data:`INPUT_QOS` is the inputs' QoS. The tables map each input message type the schema allows
(``topics.*_type``, config/schema.py) to its rclpy class and to the function that feeds one message's fields to the
:class:`~transplanter_ident.epochs.assembler.EpochAssembler`, exactly as the bag reader does
(:mod:`transplanter_ident.bags.messages`): a TwistWithCovarianceStamped or Odometry velocity with its
covariance diagonal (the drivers' invalid markers), an Odometry twist as a body-frame velocity, every
orientation as a quaternion (the assembler checks its norm), a JointState through the shared
duplicate-name check. The rest converts between ROS messages and the plain values of the numerics
(stamps in float seconds, outputs of an epoch, :class:`~transplanter_ident.evaluation.health.HealthReport`
lines). No node, no callbacks here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import (
    PoseWithCovarianceStamped,
    QuaternionStamped,
    TwistStamped,
    TwistWithCovarianceStamped,
    Vector3Stamped,
)
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Bool, Float32, Float64

from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.epochs.assembler import EpochAssembler
from transplanter_ident.epochs.checks import joint_angle
from transplanter_ident.epochs.epoch import Epoch
from transplanter_ident.epochs.frames import YAW_VARIANCE_IMU, YAW_VARIANCE_POSE, stamp_seconds
from transplanter_ident.evaluation.health_report import HealthReport

#: messages each input holds while the node is busy: 20 s of 50 Hz steering, so a stall of the node's process
#: (a busy vehicle computer) delays epochs instead of dropping samples (qos_profile_sensor_data holds 5). A frozen
#: (stopped) process's transport holds less: Fast DDS's shared memory about a second's worth (README).
INPUT_QUEUE_DEPTH = 1000
#: the inputs' QoS: best effort and volatile accept every publisher's QoS (as qos_profile_sensor_data), deeper
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=INPUT_QUEUE_DEPTH,
                       reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)

#: (assembler, stamp s, message) -> the epochs the sample completes
Feeder = Callable[[EpochAssembler, float, Any], list[Epoch]]


def _twist(assembler: EpochAssembler, stamp: float, msg: TwistStamped) -> list[Epoch]:
    v = msg.twist.linear
    return assembler.add_velocity(stamp, v.x, v.y)


def _twist_cov(assembler: EpochAssembler, stamp: float, msg: Any) -> list[Epoch]:
    v, c = msg.twist.twist.linear, msg.twist.covariance
    return assembler.add_velocity(stamp, v.x, v.y, float(c[0]), float(c[7]))


def _odometry_twist(assembler: EpochAssembler, stamp: float, msg: Odometry) -> list[Epoch]:
    v, c = msg.twist.twist.linear, msg.twist.covariance
    return assembler.add_body_velocity(stamp, v.x, v.y, float(c[0]), float(c[7]))


def _orientation(field: Callable[[Any], Any], yaw_variance: Callable[[Any], float] | None = None) -> Feeder:
    def feed(assembler: EpochAssembler, stamp: float, msg: Any) -> list[Epoch]:
        q = field(msg)
        variance = float(yaw_variance(msg)) if yaw_variance is not None else 0.0
        return assembler.add_heading_quaternion(stamp, q.x, q.y, q.z, q.w, variance)

    return feed


def _imu_yaw_variance(msg: Imu) -> float:
    return msg.orientation_covariance[YAW_VARIANCE_IMU]


def _pose_yaw_variance(msg: Any) -> float:
    return msg.pose.covariance[YAW_VARIANCE_POSE]


#: topics.velocity_type -> (class, feeder)
VELOCITY_TYPES: dict[str, tuple[type, Feeder]] = {
    "geometry_msgs/msg/TwistStamped": (TwistStamped, _twist),
    "geometry_msgs/msg/TwistWithCovarianceStamped": (TwistWithCovarianceStamped, _twist_cov),
    "nav_msgs/msg/Odometry": (Odometry, _odometry_twist),
}
#: topics.heading_type -> (class, feeder of the orientation)
HEADING_TYPES: dict[str, tuple[type, Feeder]] = {
    "geometry_msgs/msg/QuaternionStamped": (QuaternionStamped, _orientation(lambda msg: msg.quaternion)),
    "sensor_msgs/msg/Imu": (Imu, _orientation(lambda msg: msg.orientation, _imu_yaw_variance)),
    "geometry_msgs/msg/PoseWithCovarianceStamped": (PoseWithCovarianceStamped,
                                                    _orientation(lambda msg: msg.pose.pose.orientation,
                                                                 _pose_yaw_variance)),
    "nav_msgs/msg/Odometry": (Odometry, _orientation(lambda msg: msg.pose.pose.orientation, _pose_yaw_variance)),
}
#: topics.steering_type -> class (a JointState carries a stamp and joints, a Float64 or Float32 only the angle)
STEERING_TYPES: dict[str, type] = {"sensor_msgs/msg/JointState": JointState, "std_msgs/msg/Float64": Float64,
                                   "std_msgs/msg/Float32": Float32}


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


def joint_position(msg: JointState, joint: str) -> tuple[float | None, str, str]:
    """(position of ``joint``, "", "") or (None, kind, reason): missing joint or position, duplicate names."""
    return joint_angle(msg.name, msg.position, joint)


def output_values(epoch: Epoch, est: Estimate) -> tuple[float, ...]:
    """What one epoch publishes (OutputMessages.fill reads them in this order).

    Cf, Cr, their 1-sigma, the model's vy and r, the measured vx, vy, r, the steering offset and its
    1-sigma, and the correlation of the two stiffness states. A single antenna measures no vy
    (``ekf.measurement: course``): the filter's estimate of it stands in.
    """
    measured_vy = epoch.lateral_velocity if math.isfinite(epoch.lateral_velocity) else est.lateral_velocity
    return (est.cornering_stiffness_front, est.cornering_stiffness_rear, est.cornering_stiffness_front_std,
            est.cornering_stiffness_rear_std, est.lateral_velocity_model, est.yaw_rate_model,
            epoch.longitudinal_velocity, measured_vy, epoch.yaw_rate, est.steering_offset,
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
