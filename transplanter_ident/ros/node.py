"""The `estimator` ROS 2 node: live cornering-stiffness identification (DESIGN.md sections 2, 3, 6).

A thin rclpy shell around the shared core. GNSS velocity, GNSS heading and the steering angle
go, stamp by stamp, into :class:`measurements.EpochAssembler`; each completed epoch goes into
:class:`ekf.JointEKF`, the same conversion and filter that ``replay`` and ``tuner`` run
offline, so the node's outputs equal replay's CSV for the same input.

Subscriptions (qos_profile_sensor_data; names and types are parameters):
    topics.velocity  geometry_msgs/TwistStamped | TwistWithCovarianceStamped   (topics.velocity_type)
    topics.heading   geometry_msgs/QuaternionStamped | sensor_msgs/Imu          (topics.heading_type)
    topics.steering  sensor_msgs/JointState (joint steering.joint_name) | std_msgs/Float64 (topics.steering_type)
Publications, once per processed epoch and stamped with the epoch's time:
    ~/cornering_stiffness      geometry_msgs/Vector3Stamped  x = Cf, y = Cr (N/rad per tire)
    ~/cornering_stiffness_std  geometry_msgs/Vector3Stamped  1-sigma of Cf, Cr
    ~/model_output             geometry_msgs/TwistStamped    linear.y = vy, angular.z = r of the model
    ~/measurement              geometry_msgs/TwistStamped    linear.x = vx, linear.y = vy, angular.z = r at the CG
    /diagnostics               diagnostic_msgs/DiagnosticArray, 1 Hz (levels from transplanter_ident.evaluation.health)
Service: ~/reset (std_srvs/Trigger) restarts the filter and the assembler; so does a backward jump of a
simulated ROS clock (use_sim_time with a replayed bag that loops).

Run:
    ros2 run transplanter_ident estimator --ros-args --params-file config/estimator.yaml
    ros2 launch transplanter_ident estimator.launch.py tuned_params:=/path/tuned.yaml
"""

from __future__ import annotations

import argparse
import gc
import math
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import QuaternionStamped, TwistStamped, TwistWithCovarianceStamped, Vector3Stamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock, ClockType, JumpThreshold
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64
from std_srvs.srv import Trigger

from transplanter_ident.config.params_file import EstimatorParams, ParamsError, flat_to_params, params_to_flat
from transplanter_ident.ekf.joint_ekf import Estimate, JointEKF
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler
from transplanter_ident.epochs.epoch import Epoch, Rejection
from transplanter_ident.epochs.frames import stamp_seconds
from transplanter_ident.evaluation.health import HealthMonitor, HealthReport, HealthThresholds, should_publish
from transplanter_ident.evaluation.windows import Throttle

NODE_NAME = "estimator"
OUTPUT_FRAME_ID = "base_link"  # the body frame at the CG, as replay's output bag (bag_io.OUTPUT_FRAME_ID)

VELOCITY_TYPES: dict[str, tuple[type, Callable[[Any], Any]]] = {
    "TwistStamped": (TwistStamped, lambda msg: msg.twist.linear),
    "TwistWithCovarianceStamped": (TwistWithCovarianceStamped, lambda msg: msg.twist.twist.linear),
}
HEADING_TYPES: dict[str, tuple[type, Callable[[Any], Any]]] = {
    "QuaternionStamped": (QuaternionStamped, lambda msg: msg.quaternion),
    "Imu": (Imu, lambda msg: msg.orientation),
}
STEERING_TYPES: dict[str, type] = {"JointState": JointState, "Float64": Float64}

#: parameters only the node has (params_file does not know them); the rest come from params_to_flat
NODE_PARAMETERS: dict[str, Any] = {
    "topics.velocity_type": "TwistStamped",
    "topics.heading_type": "QuaternionStamped",
    "topics.steering_type": "JointState",
    "diagnostics.stale_timeout": HealthThresholds.stale_timeout,
    "diagnostics.window": HealthThresholds.window,
    "diagnostics.converged_rel_std": HealthThresholds.converged_rel_std,
    "diagnostics.min_steering_rms": HealthThresholds.min_steering_rms,
    "diagnostics.min_yaw_rate_rms": HealthThresholds.min_yaw_rate_rms,
    "diagnostics.period": 1.0,
    "diagnostics.latency_log": "",
}

_STRUCTURAL = ("topics.", "frames.", "vehicle.", "steering.")
_EKF_OPTIONS = ("ekf.discretization", "ekf.stiffness_state", "ekf.measurement", "ekf.min_speed",
                "ekf.stiffness_bounds", "ekf.gate_threshold", "ekf.max_gated", "ekf.max_interval")

DESCRIPTIONS = {
    "vehicle.mass": "vehicle mass, kg (paper Table 1)",
    "vehicle.lf": "CG to front axle, m",
    "vehicle.lr": "CG to rear axle, m",
    "vehicle.iz": "yaw inertia, kg m^2; <= 0 means m*lf*lr (paper eq. 5)",
    "vehicle.antenna_x": "GNSS antenna ahead of the CG, m",
    "vehicle.antenna_y": "GNSS antenna left of the CG, m",
    "vehicle.max_steering": "steering limit, rad; a sample beyond it is rejected",
    "topics.velocity": "GNSS velocity topic",
    "topics.heading": "GNSS heading topic",
    "topics.steering": "steering angle topic (rad, positive to the left)",
    "topics.velocity_type": "TwistStamped | TwistWithCovarianceStamped (geometry_msgs)",
    "topics.heading_type": "QuaternionStamped (geometry_msgs) | Imu (sensor_msgs)",
    "topics.steering_type": "JointState (sensor_msgs, joint steering.joint_name) | Float64 (std_msgs)",
    "frames.velocity": "enu (linear.x/y = east/north) | ned (north/east)",
    "frames.heading": "enu (ENU yaw) | ned (compass heading, clockwise from north)",
    "steering.joint_name": "joint of a sensor_msgs/JointState that carries the steering angle",
    "ekf.discretization": "exact (zero-order hold) | euler (paper eq. 10)",
    "ekf.stiffness_state": "log | linear (paper)",
    "ekf.measurement": "heading (z = [vy, psi]) | yaw_rate (paper, z = [vy, r])",
    "ekf.process_noise": "diag Q for vy, r, Cf, Cr in the units of the state (settable at run time)",
    "ekf.measurement_noise": "diag R: vy (m/s)^2, heading rad^2 or r (rad/s)^2 (settable at run time)",
    "ekf.heading_process_noise": "Q of the heading state, rad^2 (settable at run time)",
    "ekf.initial_stiffness": "initial Cf, Cr, N/rad (used from the next ~/reset)",
    "ekf.initial_covariance": "diag P0 for vy, r, Cf, Cr in the units of the state (used from the next ~/reset)",
    "ekf.initial_heading_covariance": "P0 of the heading state, rad^2 (used from the next ~/reset)",
    "ekf.min_speed": "m/s: below it, no stiffness update",
    "ekf.stiffness_bounds": "lower and upper clamp of Cf, Cr, N/rad",
    "ekf.gate_threshold": "Mahalanobis d^2 above which an update is gated",
    "ekf.max_gated": "after this many consecutive gated epochs the next one is accepted",
    "ekf.max_interval": "s: a longer GNSS gap re-initialises the motion states",
    "diagnostics.stale_timeout": "s without a message before an input is reported stale (ERROR)",
    "diagnostics.window": "s over which rejections, gating and excitation are judged",
    "diagnostics.converged_rel_std": "relative 1-sigma of Cf and Cr below which they count as converged",
    "diagnostics.min_steering_rms": "rad: steering RMS over the window needed for sufficient excitation",
    "diagnostics.min_yaw_rate_rms": "rad/s: yaw-rate RMS over the window needed for sufficient excitation",
    "diagnostics.period": "s between /diagnostics messages",
    "diagnostics.latency_log": "file to append 't latency_s' per published epoch (empty: off)",
}

_RANGES = {
    "vehicle.mass": (1.0, 1.0e5),
    "vehicle.lf": (0.01, 20.0),
    "vehicle.lr": (0.01, 20.0),
    "vehicle.antenna_x": (-20.0, 20.0),
    "vehicle.antenna_y": (-20.0, 20.0),
    "vehicle.max_steering": (0.001, 1.6),
    "ekf.min_speed": (0.0, 20.0),
    "ekf.max_interval": (0.001, 3600.0),
    "diagnostics.stale_timeout": (0.01, 3600.0),
    "diagnostics.window": (0.1, 3600.0),
    "diagnostics.converged_rel_std": (1.0e-6, 10.0),
    "diagnostics.min_steering_rms": (0.0, 1.6),
    "diagnostics.min_yaw_rate_rms": (0.0, 10.0),
    "diagnostics.period": (0.01, 60.0),
}


def parameter_defaults() -> dict[str, Any]:
    """Every parameter the node declares, with its default."""
    flat = params_to_flat(EstimatorParams())
    flat.update(NODE_PARAMETERS)
    return flat


def is_read_only(name: str) -> bool:
    """Topics, frames, vehicle geometry, the filter's structure and the diagnostics period are fixed at start."""
    return (name.startswith(_STRUCTURAL) or name in _EKF_OPTIONS
            or name in ("diagnostics.period", "diagnostics.latency_log"))


def descriptor_for(name: str, default: Any) -> ParameterDescriptor:
    """The ParameterDescriptor the node declares ``name`` with."""
    descriptor = ParameterDescriptor(description=DESCRIPTIONS.get(name, ""), read_only=is_read_only(name))
    if name in _RANGES:
        low, high = _RANGES[name]
        descriptor.floating_point_range = [FloatingPointRange(from_value=low, to_value=high, step=0.0)]
    elif isinstance(default, int) and not isinstance(default, bool):
        descriptor.integer_range = [IntegerRange(from_value=0, to_value=1000, step=1)]
    if name.endswith("_type"):
        choices = {"topics.velocity_type": VELOCITY_TYPES, "topics.heading_type": HEADING_TYPES,
                   "topics.steering_type": STEERING_TYPES}[name]
        descriptor.additional_constraints = "one of " + ", ".join(choices)
    return descriptor


def validate(flat: dict[str, Any]) -> tuple[EstimatorParams, HealthThresholds]:
    """Check a complete set of parameter values; raises ParamsError naming the key and the reason."""
    core = {k: v for k, v in flat.items() if k not in NODE_PARAMETERS}
    params = flat_to_params(core)
    for key, table in (("topics.velocity_type", VELOCITY_TYPES), ("topics.heading_type", HEADING_TYPES),
                       ("topics.steering_type", STEERING_TYPES)):
        if message_type_name(flat[key]) not in table:
            raise ParamsError(f"{key} must be one of {', '.join(table)}, got {flat[key]!r}", key)
    try:
        thresholds = HealthThresholds(
            stale_timeout=float(flat["diagnostics.stale_timeout"]), window=float(flat["diagnostics.window"]),
            converged_rel_std=float(flat["diagnostics.converged_rel_std"]),
            min_steering_rms=float(flat["diagnostics.min_steering_rms"]),
            min_yaw_rate_rms=float(flat["diagnostics.min_yaw_rate_rms"]))
    except ValueError as exc:
        raise ParamsError(str(exc), str(exc).split(" ", 1)[0]) from None
    period = float(flat["diagnostics.period"])
    if not (math.isfinite(period) and period > 0.0):
        raise ParamsError(f"diagnostics.period must be > 0, got {period!r}", "diagnostics.period")
    return params, thresholds


def ros_type_name(msg_type: type) -> str:
    """geometry_msgs.msg.TwistStamped -> 'geometry_msgs/msg/TwistStamped' (as the ROS graph names types)."""
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


def message_type_name(value: str) -> str:
    """'geometry_msgs/msg/TwistStamped', 'geometry_msgs/TwistStamped' or 'TwistStamped' -> 'TwistStamped'."""
    return str(value).rsplit("/", 1)[-1]


def seconds_to_stamp(t: float) -> Time:
    """Float seconds -> builtin_interfaces/Time (nearest nanosecond)."""
    sec = math.floor(t)
    nanosec = round((t - sec) * 1e9)
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return Time(sec=int(sec), nanosec=int(nanosec))


def _plain(value: Any) -> Any:
    """Parameter value as a plain Python value (arrays become lists)."""
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    return list(value)


class EstimatorNode(Node):
    """Subscriptions and publishers around EpochAssembler + JointEKF."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._names = []
        for name, default in parameter_defaults().items():
            self.declare_parameter(name, default, descriptor_for(name, default))
            self._names.append(name)
        self._flat = {name: _plain(self.get_parameter(name).value) for name in self._names}
        self._params, thresholds = validate(self._flat)

        self._ekf = JointEKF(self._params.config)
        _warm_up(self._params)
        self._assembler = EpochAssembler(AssemblerSettings.from_params(self._params))
        topics = self._params.topics
        self._health = HealthMonitor(thresholds, time.monotonic(),
                                     {"velocity": topics.velocity, "heading": topics.heading,
                                      "steering": topics.steering})
        self._throttle = Throttle(5.0)
        self._joint = self._params.steering.joint_name
        latency_path = self._flat["diagnostics.latency_log"]
        self._latency_log = open(latency_path, "a", encoding="utf-8") if latency_path else None  # noqa: SIM115

        self._outputs = (Vector3Stamped(), Vector3Stamped(), TwistStamped(), TwistStamped())
        for msg in self._outputs:
            msg.header.frame_id = OUTPUT_FRAME_ID
        # No default QoS-event handlers on the outputs: each is a waitable the executor rebuilds into its
        # wait set on every wake-up (300 inputs/s), and reliable/volatile outputs suit any plain subscriber.
        quiet = PublisherEventCallbacks(use_default_callbacks=False)
        self._pub_stiffness = self.create_publisher(Vector3Stamped, "~/cornering_stiffness", 10, event_callbacks=quiet)
        self._pub_std = self.create_publisher(Vector3Stamped, "~/cornering_stiffness_std", 10, event_callbacks=quiet)
        self._pub_model = self.create_publisher(TwistStamped, "~/model_output", 10, event_callbacks=quiet)
        self._pub_measurement = self.create_publisher(TwistStamped, "~/measurement", 10, event_callbacks=quiet)
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10, event_callbacks=quiet)

        velocity_type, self._velocity_of = VELOCITY_TYPES[message_type_name(self._flat["topics.velocity_type"])]
        heading_type, self._orientation_of = HEADING_TYPES[message_type_name(self._flat["topics.heading_type"])]
        steering_type = STEERING_TYPES[message_type_name(self._flat["topics.steering_type"])]
        steering_callback = self._on_joint_state if steering_type is JointState else self._on_steering_float
        self._input_types: list[tuple[str, str, str]] = []  # (role, resolved topic, 'pkg/msg/Type')
        # Steering first: the default executor serves waiting subscriptions in creation order (the EventsExecutor
        # in arrival order), and the steering sample at t_k belongs to the interval that the GNSS epoch t_k closes.
        for role, msg_type, topic, callback in (("steering", steering_type, topics.steering, steering_callback),
                                                ("velocity", velocity_type, topics.velocity, self._on_velocity),
                                                ("heading", heading_type, topics.heading, self._on_heading)):
            # best effort + volatile accept every publisher's QoS; a publisher of another type is found in the graph
            events = SubscriptionEventCallbacks(use_default_callbacks=False)
            subscription = self.create_subscription(msg_type, topic, callback, qos_profile_sensor_data,
                                                    event_callbacks=events)
            self._input_types.append((role, subscription.topic_name, ros_type_name(msg_type)))
        self.create_service(Trigger, "~/reset", self._on_reset)
        # a replayed bag that restarts (ros2 bag play --loop, use_sim_time) moves ROS time back: start over
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1), on_clock_change=False),
            post_callback=self._on_time_jump)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        # steady clock: diagnostics keep flowing (and report stale inputs) even if a sim clock stops
        self._diagnostics_timer = self.create_timer(float(self._flat["diagnostics.period"]), self._publish_diagnostics,
                                                    clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f"estimating Cf, Cr from {topics.velocity} ({velocity_type.__name__}), {topics.heading} "
            f"({heading_type.__name__}), {topics.steering} ({steering_type.__name__}); "
            f"{self._params.config.options.discretization}/{self._params.config.options.stiffness_state}/"
            f"{self._params.config.options.measurement}")

    # ------------------------------------------------------------------ inputs

    # The callbacks take no MessageInfo: rclpy 7.1's EventsExecutor fails on such callbacks (SystemError), so a
    # GNSS message's arrival is the entry to its callback (the driver-side end-to-end latency includes the rest).

    def _on_velocity(self, msg: Any) -> None:
        arrival = time.perf_counter()
        self._health.on_message("velocity", time.monotonic())
        v = self._velocity_of(msg)
        self._process(self._assembler.add_velocity(self._stamp(msg.header), v.x, v.y), arrival)

    def _on_heading(self, msg: Any) -> None:
        arrival = time.perf_counter()
        self._health.on_message("heading", time.monotonic())
        q = self._orientation_of(msg)
        self._process(self._assembler.add_heading_quaternion(self._stamp(msg.header), q.x, q.y, q.z, q.w), arrival)

    def _on_joint_state(self, msg: JointState) -> None:
        self._health.on_message("steering", time.monotonic())
        stamp = self._stamp(msg.header)
        try:
            index = msg.name.index(self._joint)
            angle = msg.position[index]
        except (ValueError, IndexError):
            self._reject(Rejection("steering", stamp, f"joint '{self._joint}' has no position in the JointState"))
            return
        self._process(self._assembler.add_steering(stamp, angle), None)

    def _on_steering_float(self, msg: Float64) -> None:
        self._health.on_message("steering", time.monotonic())
        self._process(self._assembler.add_steering(self._now(), msg.data), None)

    def _check_publisher_types(self) -> None:
        """Report a publisher of another message type on an input topic, once per diagnostics period.

        DDS never matches it and Fast DDS raises no incompatible-type event, so the input would
        otherwise only look stale.
        """
        for role, topic, expected in self._input_types:
            for info in self.get_publishers_info_by_topic(topic):
                if info.topic_type != expected:
                    self._reject(Rejection(role, self._now(), f"a publisher on {topic} sends {info.topic_type}, "
                                           f"not topics.{role}_type {expected}"))
                    break

    def _stamp(self, header: Any) -> float:
        """header.stamp in seconds; an unset (zero) stamp means the arrival time, as bag_io uses the log time."""
        if header.stamp.sec == 0 and header.stamp.nanosec == 0:
            return self._now()
        return stamp_seconds(header.stamp.sec, header.stamp.nanosec)

    def _now(self) -> float:
        """The node clock (ROS time: the /clock of a replayed bag with use_sim_time), s."""
        return self.get_clock().now().nanoseconds / 1e9

    # ------------------------------------------------------------------ filter and outputs

    def _process(self, epochs: Sequence[Epoch], arrival: float | None) -> None:
        """Filter and publish the completed epochs; ``arrival``: perf_counter at the GNSS callback's entry."""
        for rejection in self._assembler.drain_rejections():
            self._reject(rejection)
        for epoch in epochs:
            estimate = self._ekf.step(epoch)
            self._health.on_estimate(epoch, estimate, time.monotonic())
            if not should_publish(estimate.status):
                self._warn(("status", estimate.status), f"epoch t={epoch.t:.3f}: {estimate.status.name}, "
                           "nothing published")
                continue
            if self._publish(epoch, estimate) and arrival is not None:
                latency = time.perf_counter() - arrival
                self._health.on_latency(latency)
                if self._latency_log is not None:
                    self._latency_log.write(f"{epoch.t:.9f} {latency:.9f}\n")

    def _publish(self, epoch: Epoch, est: Estimate) -> bool:
        values = (est.cornering_stiffness_front, est.cornering_stiffness_rear, est.cornering_stiffness_front_std,
                  est.cornering_stiffness_rear_std, est.lateral_velocity_model, est.yaw_rate_model,
                  epoch.longitudinal_velocity, epoch.lateral_velocity, epoch.yaw_rate)
        if not all(math.isfinite(v) for v in values):
            self._health.on_unpublished()
            self._warn("nan", f"epoch t={epoch.t:.3f}: non-finite output withheld {values}")
            return False
        stamp = seconds_to_stamp(epoch.t)
        stiffness, std, model, measurement = self._outputs  # reused: publish() serializes at once
        for msg in self._outputs:
            msg.header.stamp = stamp
        stiffness.vector.x, stiffness.vector.y = values[0], values[1]
        std.vector.x, std.vector.y = values[2], values[3]
        model.twist.linear.y, model.twist.angular.z = values[4], values[5]
        measurement.twist.linear.x, measurement.twist.linear.y, measurement.twist.angular.z = values[6:9]
        self._pub_stiffness.publish(stiffness)
        self._pub_std.publish(std)
        self._pub_model.publish(model)
        self._pub_measurement.publish(measurement)
        return True

    def _reject(self, rejection: Rejection) -> None:
        self._health.on_rejection(rejection, time.monotonic())
        topic = {"velocity": self._params.topics.velocity, "heading": self._params.topics.heading,
                 "steering": self._params.topics.steering}.get(rejection.topic, "GNSS epoch")
        self._warn((rejection.topic, rejection.reason),
                   f"{rejection.topic} ({topic}) sample at t={rejection.stamp:.3f} rejected: {rejection.reason}")

    def _warn(self, key: object, text: str) -> None:
        allowed, suppressed = self._throttle.allow(key, time.monotonic())
        if allowed:
            more = f" (and {suppressed} more like it)" if suppressed else ""
            self.get_logger().warning(text + more)

    # ------------------------------------------------------------------ diagnostics, reset, parameters

    def _publish_diagnostics(self) -> None:
        self._check_publisher_types()
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [_to_status(report, self.get_fully_qualified_name())
                        for report in self._health.report(time.monotonic())]
        self._pub_diagnostics.publish(array)
        if self._latency_log is not None:
            self._latency_log.flush()

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._restart()
        self.get_logger().info("filter and assembler restarted (~/reset)")
        response.success = True
        response.message = "filter and assembler restarted"
        return response

    def _on_time_jump(self, jump: Any) -> None:
        if not self.get_clock().ros_time_is_active:  # only a simulated clock restarts; wall-clock steps do not
            return
        self._restart()
        self.get_logger().warning(f"ROS time jumped back by {-jump.delta.nanoseconds / 1e9:.3f} s (a replayed bag "
                                  "restarted?): filter and assembler restarted")

    def _restart(self) -> None:
        self._ekf.reset()
        self._assembler.reset()
        self._health.reset_filter()

    def _on_set_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        flat = dict(self._flat)
        for parameter in parameters:
            flat[parameter.name] = _plain(parameter.value)
        try:
            params, thresholds = validate(flat)
        except ParamsError as exc:
            self.get_logger().warning(f"parameter change rejected: {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        if params.config.noise != self._params.config.noise:
            self._ekf.set_noise(params.config.noise)
        self._health.set_thresholds(thresholds)
        changed = ", ".join(f"{p.name}={_plain(p.value)}" for p in parameters)
        self.get_logger().info(f"parameters set: {changed}")
        self._flat, self._params = flat, params
        return SetParametersResult(successful=True)

    def destroy_node(self) -> None:
        if self._latency_log is not None:
            self._latency_log.close()
            self._latency_log = None
        super().destroy_node()


def _to_status(report: HealthReport, hardware_id: str) -> DiagnosticStatus:
    return DiagnosticStatus(level=bytes([report.level]), name=report.name, message=report.message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in report.values])


def _warm_up(params: EstimatorParams) -> None:
    """Run the compiled filter step once on a throwaway filter, so the first real epoch is not slow."""
    ekf = JointEKF(params.config)
    for t in (0.0, 0.1):
        ekf.step(Epoch(t=t, longitudinal_velocity=1.0, lateral_velocity=0.0, heading=0.0, yaw_rate=0.0,
                       steering=0.0, steering_rate=0.0, speed=1.0))


EXECUTORS = ("events", "single")
SPIN_PERIOD = 0.5  # s; spin_once returns on work, on shutdown, or after this


def build_parser() -> argparse.ArgumentParser:
    """Command line of `estimator`; ROS arguments follow `--ros-args`."""
    parser = argparse.ArgumentParser(
        prog="estimator",
        description="Online cornering-stiffness estimator (ROS 2 node): GNSS velocity, heading and steering in, "
        "~/cornering_stiffness, ~/cornering_stiffness_std, ~/model_output, ~/measurement and /diagnostics out.",
        epilog="ROS arguments: estimator --ros-args --params-file config/estimator.yaml "
        "[--params-file tuned.yaml] [-r __ns:=/NS] [-p topics.velocity:=/gnss/vel ...] [-p use_sim_time:=true]",
    )
    parser.add_argument("--executor", choices=EXECUTORS, default="events",
                        help="events: rclpy's EventsExecutor (rclpy.experimental; about half the CPU of the default "
                        "at 300 inputs/s); single: rclpy's SingleThreadedExecutor (default: %(default)s)")
    return parser


def make_executor(kind: str) -> Any:
    """The executor that spins the node: ``events`` (EventsExecutor) or ``single`` (SingleThreadedExecutor)."""
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    return SingleThreadedExecutor()


def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C / SIGTERM; returns the process exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    split = args.index("--ros-args") if "--ros-args" in args else len(args)
    try:
        options = build_parser().parse_args(args[:split])
    except SystemExit as exc:
        return int(exc.code or 0)
    rclpy.init(args=["estimator", *args[split:]])
    node = None
    try:
        node = EstimatorNode()
        executor = make_executor(options.executor)
        executor.add_node(node)
        gc.collect()
        gc.freeze()  # the ~10^5 start-up objects (rclpy, numba) never die: keep the collector off them
        while rclpy.ok():  # not executor.spin(): in rclpy 7.1 EventsExecutor.spin() busy-waits and serves nothing
            executor.spin_once(timeout_sec=SPIN_PERIOD)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ParamsError, InvalidParameterValueException, InvalidParameterTypeException, OSError) as exc:
        rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {exc}")
        return 1
    except Exception:
        if rclpy.ok():
            raise
        # a signal shut the context down between two waits (rclpy raises RCLError then): a clean stop
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
