"""The `estimator` ROS 2 node: live cornering-stiffness identification (DESIGN.md sections 2, 3, 6).

A thin rclpy shell around the shared core. GNSS velocity, GNSS heading and the steering angle
go, stamp by stamp, into :class:`~transplanter_ident.epochs.assembler.EpochAssembler`; each completed
epoch goes into :class:`~transplanter_ident.ekf.joint_ekf.JointEKF`, the same conversion and filter
that ``replay`` and ``tuner`` run offline, so the node's outputs equal replay's CSV for the same input.
Message types and field extraction are in :mod:`.adapters`, parameters (schema, descriptors,
validation) in :mod:`.parameters`, the command line and the executor in :mod:`.main`.

Subscriptions (``adapters.INPUT_QOS``: best effort, volatile, 100 deep; names and types are parameters):
    topics.velocity  geometry_msgs/TwistStamped | TwistWithCovarianceStamped | nav_msgs/Odometry (topics.velocity_type)
    topics.heading   geometry_msgs/QuaternionStamped | sensor_msgs/Imu | PoseWithCovarianceStamped | nav_msgs/Odometry
                     (topics.heading_type; one Odometry topic may serve velocity and heading: one subscription)
    topics.steering  sensor_msgs/JointState (joint steering.joint_name) | std_msgs/Float64 | Float32 (topics.steering_type;
                     no header: stamped with the node's ROS clock on receipt, as a bag's log time offline)
Publications, once per processed epoch, stamped with the epoch's time and framed ``output.frame_id``:
    ~/cornering_stiffness      geometry_msgs/Vector3Stamped  x = Cf, y = Cr (N/rad per tire)
    ~/cornering_stiffness_std  geometry_msgs/Vector3Stamped  1-sigma of Cf, Cr; z = their states' correlation
    ~/cornering_stiffness_valid std_msgs/Bool                whether the estimate can be trusted (validity.*)
    ~/steering_offset          geometry_msgs/Vector3Stamped  x = steering-sensor offset (rad), y = its 1-sigma
    ~/model_output             geometry_msgs/TwistStamped    linear.y = vy, angular.z = r of the model
    ~/measurement              geometry_msgs/TwistStamped    linear.x = vx, linear.y = vy, angular.z = r at the CG
    /diagnostics               diagnostic_msgs/DiagnosticArray, statuses "<node name>: ..." (transplanter_ident.evaluation.health)
Service: ~/reset (std_srvs/Trigger) restarts the filter and the assembler; so does a backward jump of a
simulated ROS clock (use_sim_time with a replayed bag that loops).
Parameters follow the ros2 demos pattern: a pre-set callback turns integers into floats where floats
are due, an on-set callback only validates, a post-set callback applies.

Run:
    ros2 run transplanter_ident estimator --ros-args --params-file config/estimator.yaml
    ros2 launch transplanter_ident estimator.launch.py tuned_params:=/path/tuned.yaml
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType, JumpThreshold
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32, Float64
from std_srvs.srv import Trigger

from transplanter_ident.config.keys import is_ros_builtin, unknown_key_message
from transplanter_ident.config.params_file import ParamsError, parameter_value
from transplanter_ident.config.schema import PARAMS, SCHEMA
from transplanter_ident.ekf.joint_ekf import Estimate, JointEKF, warm_up
from transplanter_ident.ekf.persistence import Keeper, LearnedState, default_path
from transplanter_ident.epochs import checks
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler
from transplanter_ident.epochs.epoch import Epoch, Rejection
from transplanter_ident.epochs.settings import input_roles
from transplanter_ident.evaluation.health import HealthMonitor, HealthReport, should_publish
from transplanter_ident.evaluation.identifiability_report import identifiability_report
from transplanter_ident.evaluation.validity import monitor_for, sample_of
from transplanter_ident.evaluation.validity import warm_up as warm_up_validity
from transplanter_ident.evaluation.windows import Throttle, reason_class
from transplanter_ident.files import OptionalOutput
from transplanter_ident.ros import adapters
from transplanter_ident.ros.parameters import (
    NodeSettings,
    coerce,
    descriptor_for,
    plain,
    start_values,
    validate,
)
from transplanter_ident.ros.startup import optional_output_report

NODE_NAME = "estimator"
SHUTDOWN_ACK_TIMEOUT = 0.2  # s per output publisher at a clean stop, for reliable subscribers to take the last epoch


class EstimatorNode(Node):
    """Subscriptions and publishers around EpochAssembler + JointEKF."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self._flat = self._declare_parameters()
        self._settings = validate(self._flat)
        params = self._settings.params
        self._ekf = JointEKF(params.config)
        warm_up(params.config)
        warm_up_validity(params.config, params.validity)
        self._assembler = EpochAssembler(AssemblerSettings.from_params(params))
        topics = params.topics
        self._topics = {role: getattr(topics, role) for role in input_roles(params)}  # no heading from one antenna
        self._health = HealthMonitor(self._settings.thresholds, time.monotonic(), self._topics, name=self.get_name(),
                                     inputs=tuple(self._topics))
        self._validity = monitor_for(params.config, params.validity)
        self._rejected = 0  # input samples rejected since the last epoch (validity: suspect input)
        self._keeper = Keeper(default_path(str(parameter_value(params, "persistence.file")), self.get_name()),
                              float(parameter_value(params, "persistence.period")), params.config)
        self._restore_learned_state()
        self._learned: LearnedState | None = None  # the latest valid parameter states, to be saved
        self._throttle = Throttle(5.0)
        self._output_warned = False
        self._joint = params.steering.joint_name
        latency_path = self._settings.latency_log
        self._latency_log = OptionalOutput(latency_path) if latency_path else None  # an I/O error disables it
        self._outputs = adapters.OutputMessages(self._settings.frame_id)
        self._create_publishers()
        self._input_types = self._create_subscriptions()  # (role, resolved topic, 'pkg/msg/Type')
        self.create_service(Trigger, "~/reset", self._on_reset)
        # a replayed bag that restarts (ros2 bag play --loop, use_sim_time) moves ROS time back: start over
        self._jump_handle = self.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1), on_clock_change=False),
            post_callback=self._on_time_jump)
        self.add_pre_set_parameters_callback(self._coerce_parameters)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        # steady clock: diagnostics keep flowing (and report stale inputs) even if a sim clock stops
        self._diagnostics_timer = self.create_timer(self._settings.diagnostics_period, self._publish_diagnostics,
                                                    clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._announce()

    def _announce(self) -> None:
        """One start-up line: the inputs with their message types and the filter's structure."""
        options = self._settings.params.config.options
        inputs = ", ".join(f"{self._topics[role]} ({self._settings.message_types[role].rsplit('/', 1)[-1]})"
                           for role in self._topics)
        self.get_logger().info(f"estimating Cf, Cr from {inputs}; "
                               f"{options.discretization}/{options.stiffness_state}/{options.measurement}")

    def _declare_parameters(self) -> dict[str, Any]:
        """Declare every schema key; unknown overrides are refused and integer overrides of floats converted.

        rclpy ignores overrides of undeclared parameters and refuses an int for a double, so the overrides
        (``--params-file`` and ``-p``) are checked against the schema first (ParamsError names the key).
        """
        values = start_values(self._parameter_overrides)
        for row in SCHEMA:
            self.declare_parameter(row.key, values[row.key], descriptor_for(row.key), ignore_override=True)
        return {row.key: plain(self.get_parameter(row.key).value) for row in SCHEMA}

    def _create_publishers(self) -> None:
        # No default QoS-event handlers on the outputs: each is a waitable the executor rebuilds into its
        # wait set on every wake-up (300 inputs/s), and reliable/volatile outputs suit any plain subscriber.
        quiet = PublisherEventCallbacks(use_default_callbacks=False)
        self._publishers_out = tuple(self.create_publisher(kind, name, 10, event_callbacks=quiet)
                                     for kind, name in adapters.OUTPUT_TOPICS)
        self._pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", 10, event_callbacks=quiet)

    def _create_subscriptions(self) -> list[tuple[str, str, str]]:
        types = self._settings.message_types
        velocity_type, self._feed_velocity = adapters.VELOCITY_TYPES[types["velocity"]]
        heading_type, self._feed_heading = adapters.HEADING_TYPES[types["heading"]]
        steering_type = adapters.STEERING_TYPES[types["steering"]]
        steering_callback = self._on_joint_state if steering_type is JointState else self._on_steering_float
        gnss = [("velocity", velocity_type, self._on_velocity), ("heading", heading_type, self._on_heading)]
        if "heading" not in self._topics:  # a single antenna: its velocity's direction is the heading (a course)
            gnss = gnss[:1]
        elif self._topics["velocity"] == self._topics["heading"]:  # one nav_msgs/Odometry topic (validated)
            gnss = [("velocity", velocity_type, self._on_velocity_and_heading)]
        inputs = []
        # Steering first: the default executor serves waiting subscriptions in creation order (the EventsExecutor
        # in arrival order), and the steering sample at t_k belongs to the interval that the GNSS epoch t_k closes.
        for role, msg_type, callback in (("steering", steering_type, steering_callback), *gnss):
            # best effort + volatile accept every publisher's QoS; a publisher of another type is found in the graph
            events = SubscriptionEventCallbacks(use_default_callbacks=False)
            subscription = self.create_subscription(msg_type, self._topics[role], callback, adapters.INPUT_QOS,
                                                    event_callbacks=events)
            inputs.append((role, subscription.topic_name, adapters.ros_type_name(msg_type)))
        return inputs

    # ------------------------------------------------------------------ inputs

    # The callbacks take no MessageInfo: rclpy 7.1's EventsExecutor fails on such callbacks (SystemError), so a
    # GNSS message's arrival is the entry to its callback (the driver-side end-to-end latency includes the rest).

    def _on_velocity(self, msg: Any) -> None:
        arrival = time.perf_counter()
        self._health.on_message("velocity", time.monotonic())
        self._process(self._feed_velocity(self._assembler, self._stamp(msg.header), msg), arrival)

    def _on_heading(self, msg: Any) -> None:
        arrival = time.perf_counter()
        self._health.on_message("heading", time.monotonic())
        self._process(self._feed_heading(self._assembler, self._stamp(msg.header), msg), arrival)

    def _on_velocity_and_heading(self, msg: Any) -> None:
        """One nav_msgs/Odometry: its twist is the velocity, its orientation the heading of the same epoch."""
        arrival, now = time.perf_counter(), time.monotonic()
        self._health.on_message("velocity", now)
        self._health.on_message("heading", now)
        stamp = self._stamp(msg.header)
        epochs = self._feed_velocity(self._assembler, stamp, msg)
        self._process(epochs + self._feed_heading(self._assembler, stamp, msg), arrival)

    def _on_joint_state(self, msg: JointState) -> None:
        self._health.on_message("steering", time.monotonic())
        stamp = self._stamp(msg.header)
        angle, kind, reason = adapters.joint_position(msg, self._joint)
        if angle is None:
            self._reject(Rejection("steering", stamp, reason, kind))
            return
        self._process(self._assembler.add_steering(stamp, angle), None)

    def _on_steering_float(self, msg: Float64 | Float32) -> None:
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
                                           f"not topics.{role}_type {expected}", "wrong_type"))
                    break

    def _stamp(self, header: Any) -> float:
        """header.stamp in seconds; an unset (zero) stamp means the arrival time, as bag_io uses the log time."""
        stamp = adapters.header_seconds(header)
        return self._now() if stamp is None else stamp

    def _now(self) -> float:
        """The node clock (ROS time: the /clock of a replayed bag with use_sim_time), s."""
        return self.get_clock().now().nanoseconds / 1e9

    # ------------------------------------------------------------------ filter and outputs

    def _process(self, epochs: Sequence[Epoch], arrival: float | None) -> None:
        """Filter and publish the completed epochs; ``arrival``: perf_counter at the GNSS callback's entry."""
        for rejection in self._assembler.drain_rejections():
            self._reject(rejection)
        self._health.on_pairing(self._assembler.pairing, time.monotonic())
        self._health.on_uncovered(self._assembler.uncovered_epochs)
        for epoch in epochs:
            estimate = self._ekf.step(epoch)
            decision = self._validity.step(sample_of(epoch, estimate.row, self._rejected))
            self._rejected = 0
            if decision.valid:
                self._learned = self._ekf.learned_state(epoch.t)
            self._health.on_estimate(epoch, estimate, time.monotonic())
            self._health.on_validity(decision)
            if not should_publish(estimate.status):
                self._warn(("status", estimate.status), f"epoch t={epoch.t:.3f}: {estimate.status.name}, "
                           "nothing published")
                continue
            if self._publish(epoch, estimate, decision.valid) and arrival is not None:
                latency = time.perf_counter() - arrival
                self._health.on_latency(latency)
                if self._latency_log is not None:
                    self._latency_log.write(f"{epoch.t:.9f} {latency:.9f}\n")

    def _publish(self, epoch: Epoch, est: Estimate, valid: bool) -> bool:
        values = adapters.output_values(epoch, est)
        if not all(math.isfinite(v) for v in values):
            self._health.on_unpublished()
            self._warn("nan", f"epoch t={epoch.t:.3f}: non-finite output withheld {values}")
            return False
        self._outputs.fill(epoch.t, values, valid)
        for publisher, msg in zip(self._publishers_out, self._outputs.all(), strict=True):
            publisher.publish(msg)
        return True

    def _reject(self, rejection: Rejection) -> None:
        self._health.on_rejection(rejection, time.monotonic())
        self._rejected += rejection.kind not in checks.NOT_SUSPECT  # not a faster stream's surplus, a publisher check
        topic = self._topics.get(rejection.topic, "GNSS epoch")
        if rejection.kind == checks.SURPLUS:  # a set-up, not a fault: said once, counted in /diagnostics
            self.get_logger().info(f"{rejection.topic} ({topic}): {rejection.reason}", once=True)
            return
        key = reason_class(rejection.reason) if rejection.kind == "other" else rejection.kind  # bounded
        self._warn((rejection.topic, key),
                   f"{rejection.topic} ({topic}) sample at t={rejection.stamp:.3f} rejected: {rejection.reason}")

    def _warn(self, key: object, text: str) -> None:
        allowed, suppressed = self._throttle.allow(key, time.monotonic())
        if allowed:
            more = f" (and {suppressed} more like it)" if suppressed else ""
            self.get_logger().warning(text + more)

    # ------------------------------------------------------------------ diagnostics, reset, parameters

    def _publish_diagnostics(self) -> None:
        self._save_learned_state()
        self._check_publisher_types()
        identifiability = identifiability_report(self.get_name(), self._ekf.recent_information,
                                                 self._health.last_estimate, self._ekf.config.options)
        reports = self._health.report(time.monotonic()) + [identifiability] + self._output_reports()
        self._pub_diagnostics.publish(adapters.diagnostic_array(self.get_clock().now().to_msg(), reports,
                                                                self.get_fully_qualified_name()))
        if self._latency_log is not None:
            self._latency_log.flush()

    def _output_reports(self) -> list[HealthReport]:
        """A status line for each optional output (the latency log): WARN once an I/O error disabled it."""
        log = self._latency_log
        if log is None:
            return []
        report = optional_output_report(f"{self.get_name()}: latency log", log)
        if log.error is not None and not self._output_warned:
            self._output_warned = True
            self.get_logger().warning(report.message)
        return [report]

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._restart()
        self._learned = None
        self._keeper.forget()
        self._health.on_persistence(self._keeper.status)
        self.get_logger().info("filter and assembler restarted, saved state deleted (~/reset)")
        response.success = True
        response.message = "filter and assembler restarted; saved state deleted"
        return response

    def _on_time_jump(self, jump: Any) -> None:
        if not self.get_clock().ros_time_is_active:  # only a simulated clock restarts; wall-clock steps do not
            return
        self._restart()
        self.get_logger().warning(f"ROS time jumped back by {-jump.delta.nanoseconds / 1e9:.3f} s (a replayed bag "
                                  "restarted?): filter and assembler restarted")

    def _restore_learned_state(self) -> None:
        learned = self._keeper.restore()
        if learned is not None:
            self._ekf.restore(learned)
        self.get_logger().info(f"persistence: {self._keeper.status}")
        self._health.on_persistence(self._keeper.status)

    def _save_learned_state(self, *, force: bool = False) -> None:
        if self._learned is not None and (force or self._keeper.due(time.monotonic())):
            self._keeper.save(self._learned, time.monotonic())
            self._health.on_persistence(self._keeper.status)

    def _restart(self) -> None:
        self._ekf.reset()
        self._validity.reset()
        self._rejected = 0
        self._assembler.reset()
        self._health.reset_filter()

    def _coerce_parameters(self, parameters: list[Parameter]) -> list[Parameter]:
        """Pre-set callback: integers become floats where floats are due; an unknown key is named in the log.

        rclpy then refuses the unknown key itself (not declared), but its reason does not name the key.
        """
        for parameter in parameters:
            if parameter.name not in PARAMS and not is_ros_builtin(parameter.name):
                self.get_logger().warning(f"parameter change rejected: {unknown_key_message(parameter.name)}")
        return coerce(parameters)

    def _with_changes(self, parameters: list[Parameter]) -> dict[str, Any]:
        """The current values with ``parameters`` applied (rclpy's own, e.g. use_sim_time, are not ours)."""
        return {**self._flat, **{p.name: plain(p.value) for p in parameters if p.name in PARAMS}}

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """On-set callback: only checks the new values (read-only and ranges are rclpy's, from the descriptors)."""
        try:
            validate(self._with_changes(parameters))
        except ParamsError as exc:
            self.get_logger().warning(f"parameter change rejected: {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        """Post-set callback: the new noise goes to the filter, the new thresholds to the diagnostics."""
        ours = [p for p in parameters if p.name in PARAMS]
        if not ours:
            return
        flat = self._with_changes(ours)
        settings: NodeSettings = validate(flat)
        if settings.params.config.noise != self._settings.params.config.noise:
            self._ekf.set_noise(settings.params.config.noise)
        self._health.set_thresholds(settings.thresholds)
        self._validity.settings = settings.params.validity
        self._flat, self._settings = flat, settings
        changed = ", ".join(f"{p.name}={plain(p.value)}" for p in ours)
        self.get_logger().info(f"parameters set: {changed}")

    def destroy_node(self) -> None:
        """Close the latency log; give reliable subscribers a moment to take the last epoch, then destroy."""
        self._save_learned_state(force=True)
        self.get_logger().info(f"shutting down: {self._health.summary()}")
        if self._latency_log is not None:
            self._latency_log.close()
            self._latency_log = None
        if self.context.ok():
            for publisher in self._publishers_out:
                publisher.wait_for_all_acked(Duration(seconds=SHUTDOWN_ACK_TIMEOUT))
        super().destroy_node()

