"""Health of the online estimator: input rates, staleness, gating, convergence, excitation.

The pure logic behind the node's ``/diagnostics`` (DESIGN.md sections 3 and 6), with no ROS
types: the node feeds :class:`HealthMonitor` with arrival times, rejected samples and the
filter's estimates, and once a second converts :meth:`HealthMonitor.report` into
``diagnostic_msgs/DiagnosticStatus`` entries. Levels are those of DiagnosticStatus (OK, WARN,
ERROR), so a fleet dashboard can aggregate them unchanged.

Times: ``now`` is a monotonic arrival clock in seconds (the node passes ``time.monotonic()``),
used for rates and staleness; the excitation window runs on epoch (data) time, so it means the
same online and on a replayed bag.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from transplanter_ident.config.parameters import check_fields
from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.ekf.layout import StepStatus
from transplanter_ident.epochs import checks
from transplanter_ident.epochs.epoch import Epoch, Rejection
from transplanter_ident.epochs.pairing import PairingStats
from transplanter_ident.evaluation.convergence_report import convergence_report
from transplanter_ident.evaluation.health_report import ERROR, OK, WARN, HealthReport
from transplanter_ident.evaluation.input_health import PairingMonitor, kind_values
from transplanter_ident.evaluation.validity import Decision
from transplanter_ident.evaluation.windows import LatencyStats, RollingRms, TimeWindow

INPUTS = ("velocity", "heading", "steering")

#: statuses after which the filter state changed or was propagated (outputs are published)
PUBLISHED_STATUSES = frozenset({StepStatus.UPDATED, StepStatus.GATED, StepStatus.LOW_SPEED, StepStatus.REVERSING,
                                StepStatus.INITIALISED, StepStatus.GAP, StepStatus.NONLINEAR,
                                StepStatus.REINITIALISED, StepStatus.RESTARTED})
#: statuses where the model was propagated with a measurement (the excitation window counts these)
MOVING_STATUSES = frozenset({StepStatus.UPDATED, StepStatus.GATED, StepStatus.NONLINEAR})


def should_publish(status: StepStatus) -> bool:
    """Whether an epoch with this status produces output messages (never REJECTED_* or DIVERGED)."""
    return status in PUBLISHED_STATUSES


@dataclass(frozen=True)
class HealthThresholds:
    """Where the levels change: the node's ``diagnostics.<field>`` parameters (defaults as in config/schema.py)."""

    stale_timeout: float = 1.0  # s without a message: the input is stale (ERROR)
    window: float = 10.0  # s: recent rejections/gating (arrival time) and excitation (epoch time)
    converged_rel_std: float = 0.05  # std / C below which Cf and Cr count as converged
    min_steering_rms: float = 0.02  # rad: RMS steering over the window needed for excitation
    min_yaw_rate_rms: float = 0.02  # rad/s: RMS yaw rate over the window needed for excitation
    min_window_epochs: int = 5  # fewer moving epochs in the window: excitation unknown (WARN)
    rate_window: float = 5.0  # s of arrivals over which input rates are computed

    def __post_init__(self) -> None:
        check_fields(self, "diagnostics", positive=("stale_timeout", "window", "converged_rel_std", "rate_window"),
                     non_negative=("min_steering_rms", "min_yaw_rate_rms"))
        if self.min_window_epochs < 1:
            raise ValueError(f"diagnostics.min_window_epochs must be >= 1, got {self.min_window_epochs!r}")


class InputMonitor:
    """Arrivals and rejections of one input topic."""

    def __init__(self, name: str, thresholds: HealthThresholds, start: float) -> None:
        self.name = name
        self.start = start
        self.messages = 0
        self.last_arrival: float | None = None
        self.rejected = 0
        self.last_rejection = ""
        self.kinds: Counter = Counter()  # rejections per kind (epochs.checks)
        self._arrivals = TimeWindow(thresholds.rate_window)
        self._rejections = TimeWindow(thresholds.window)

    def set_thresholds(self, thresholds: HealthThresholds) -> None:
        self._arrivals.span = thresholds.rate_window
        self._rejections.span = thresholds.window

    def record(self, now: float) -> None:
        self.messages += 1
        self.last_arrival = now
        self._arrivals.add(now)

    def reject(self, now: float, reason: str, kind: str = "other") -> None:
        self.kinds[kind] += 1
        if kind == checks.SURPLUS:  # a faster stream's samples without a partner: counted, no warning
            return
        self.rejected += 1
        self.last_rejection = reason
        self._rejections.add(now)

    def rate(self, now: float) -> float:
        """Messages per second over the rate window (0 when fewer than two)."""
        times = self._arrivals.times(now)
        if len(times) < 2 or times[-1] <= times[0]:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])

    def age(self, now: float) -> float:
        """Seconds since the last message, or since monitoring started if none yet."""
        return now - (self.start if self.last_arrival is None else self.last_arrival)

    def recent_rejections(self, now: float) -> int:
        return self._rejections.count(now)


@dataclass
class _FilterState:
    statuses: Counter = field(default_factory=Counter)
    last_status: StepStatus | None = None
    last_epoch: Epoch | None = None
    last_estimate: Estimate | None = None
    updates: int = 0
    epoch_rejected: int = 0
    last_epoch_rejection: str = ""
    epoch_kinds: Counter = field(default_factory=Counter)
    unpublished: int = 0  # outputs withheld because a value was not finite
    uncovered: int = 0  # epochs formed before the steering covered their interval (assembler)
    validity: Decision = field(default_factory=lambda: Decision(False, ("no estimate yet",), False))


class HealthMonitor:
    """Everything the diagnostics need, fed by the node; :meth:`report` decides the levels."""

    def __init__(self, thresholds: HealthThresholds, now: float, topics: dict[str, str] | None = None,
                 name: str = "estimator", inputs: tuple[str, ...] = INPUTS) -> None:
        self.thresholds = thresholds
        self.topics = dict(topics or {})
        self.name = name  # the node's name: status names read "<name>: velocity input"
        self.inputs = {name: InputMonitor(name, thresholds, now) for name in inputs}  # one antenna: no heading
        self.latency = LatencyStats()
        self._start = now
        self._filter = _FilterState()
        self._steering_rms = RollingRms(thresholds.window)
        self._yaw_rate_rms = RollingRms(thresholds.window)
        self._events = {key: TimeWindow(thresholds.window) for key in ("gated", "rejected", "diverged", "epoch")}
        self._persistence = "off"
        self.pairing = PairingMonitor(thresholds.window)

    def set_thresholds(self, thresholds: HealthThresholds) -> None:
        """New thresholds at run time; the windows keep their samples."""
        self.thresholds = thresholds
        for monitor in self.inputs.values():
            monitor.set_thresholds(thresholds)
        self._steering_rms.span = self._yaw_rate_rms.span = thresholds.window
        for window in self._events.values():
            window.span = thresholds.window
        self.pairing.set_window(thresholds.window)

    @property
    def last_estimate(self) -> Estimate | None:
        """The filter's latest estimate (None before the first or after a reset)."""
        return self._filter.last_estimate

    def reset_filter(self) -> None:
        """Forget the filter's history (after a reset); input statistics carry on."""
        self._filter = _FilterState()
        self._steering_rms.clear()
        self._yaw_rate_rms.clear()
        for window in self._events.values():
            window.clear()

    # ------------------------------------------------------------------ feeding

    def on_message(self, topic: str, now: float) -> None:
        """A message arrived on ``topic`` (velocity, heading or steering)."""
        self.inputs[topic].record(now)

    def on_rejection(self, rejection: Rejection, now: float) -> None:
        """A sample (or an epoch) the assembler, or the node's conversion, did not use."""
        if rejection.topic in self.inputs:
            self.inputs[rejection.topic].reject(now, rejection.reason, rejection.kind)
        else:
            self._filter.epoch_rejected += 1
            self._filter.last_epoch_rejection = rejection.reason
            self._filter.epoch_kinds[rejection.kind] += 1
            self._events["epoch"].add(now)

    def on_estimate(self, epoch: Epoch, estimate: Estimate, now: float) -> None:
        """The filter processed ``epoch``."""
        f = self._filter
        status = estimate.status
        f.statuses[status] += 1
        f.last_status = status
        if status is StepStatus.GATED:
            self._events["gated"].add(now)
        elif status in (StepStatus.REJECTED_INVALID, StepStatus.REJECTED_STAMP):
            self._events["rejected"].add(now)
        elif status in (StepStatus.DIVERGED, StepStatus.RESTARTED):
            self._events["diverged"].add(now)
        if not should_publish(status):
            return
        f.last_epoch = epoch
        f.last_estimate = estimate
        if status is StepStatus.UPDATED:
            f.updates += 1
        if status in MOVING_STATUSES:
            self._steering_rms.add(epoch.t, epoch.steering)
            self._yaw_rate_rms.add(epoch.t, epoch.yaw_rate)

    def on_persistence(self, status: str) -> None:
        """What the persistence of the learned state last did (restored, saved, or why it started cold)."""
        self._persistence = status

    def _persistence_report(self) -> HealthReport:
        status = self._persistence
        refused = status.startswith("cold start:") and "no saved state" not in status
        level = WARN if refused or status.startswith("cannot") else OK
        return HealthReport(f"{self.name}: persistence", level, status, (("status", status),))

    def on_validity(self, decision: Decision) -> None:
        """The validity decision of the latest epoch (evaluation.validity)."""
        self._filter.validity = decision

    def _validity_report(self) -> HealthReport:
        decision = self._filter.validity
        name = f"{self.name}: validity"
        values = (("valid", str(decision.valid).lower()), ("reasons", "; ".join(decision.reasons)))
        if decision.valid:
            return HealthReport(name, OK, "estimate valid", values)
        level = ERROR if decision.hard else WARN
        return HealthReport(name, level, "not valid: " + ("; ".join(decision.reasons) or "waiting (hysteresis)"),
                            values)
    def on_uncovered(self, count: int) -> None:
        """How many epochs the assembler formed before the steering covered their interval."""
        self._filter.uncovered = count

    def on_pairing(self, stats: PairingStats, now: float) -> None:
        """The assembler's running counts of paired and unpaired GNSS samples."""
        self.pairing.update(stats, now)

    def on_unpublished(self) -> None:
        """An output was withheld because it was not finite."""
        self._filter.unpublished += 1

    def on_latency(self, seconds: float) -> None:
        self.latency.add(seconds)

    def summary(self) -> str:
        """Totals: messages per input since start; epochs filtered and published since start or the last reset."""
        received = ", ".join(f"{monitor.messages} {name}" for name, monitor in self.inputs.items())
        f = self._filter
        published = sum(count for status, count in f.statuses.items() if should_publish(status)) - f.unpublished
        return (f"received {received} message(s); {sum(f.statuses.values())} epoch(s) filtered, {published} "
                f"published, {f.unpublished} withheld as not finite, {f.epoch_rejected} dropped before the filter")

    # ------------------------------------------------------------------ levels

    def report(self, now: float) -> list[HealthReport]:
        """The current status lines: one per input, GNSS pairing, motion, measurements, convergence, excitation, latency."""
        reports = [self._input_report(self.inputs[name], now) for name in INPUTS if name in self.inputs]
        pairing = (self.pairing.report(now) if "heading" in self.inputs
                   else (OK, "none: one antenna's velocity gives its course (ekf.measurement course)", ()))
        reports.append(HealthReport(f"{self.name}: GNSS pairing", *pairing))
        convergence = convergence_report(self.name, self._filter.last_estimate, self._filter.updates,
                                         self.thresholds.converged_rel_std)
        reports += [self._motion_report(), self._measurement_report(now), self._validity_report(),
                    self._persistence_report(), convergence, self._excitation_report(), self._latency_report()]
        return reports

    def _input_report(self, monitor: InputMonitor, now: float) -> HealthReport:
        th = self.thresholds
        age = monitor.age(now)
        rate = monitor.rate(now) if age <= th.stale_timeout else 0.0
        recent = monitor.recent_rejections(now)
        topic = self.topics.get(monitor.name, monitor.name)
        values = (("topic", topic), ("rate_hz", f"{rate:.2f}"), ("messages", str(monitor.messages)),
                  ("age_s", f"{age:.3f}" if monitor.last_arrival is not None else "never"),
                  ("rejected", str(monitor.rejected)), ("rejected_recent", str(recent)),
                  ("last_rejection", monitor.last_rejection)) + kind_values(monitor.kinds)
        name = f"{self.name}: {monitor.name} input"
        if age > th.stale_timeout:
            if monitor.last_arrival is None:
                message = f"stale: no message on {topic} since start ({age:.1f} s)"
            else:
                message = f"stale: no message on {topic} for {age:.1f} s (timeout {th.stale_timeout:g} s)"
            if recent:  # e.g. a publisher of another message type
                message += f"; {monitor.last_rejection}"
            return HealthReport(name, ERROR, message, values)
        if recent:
            return HealthReport(name, WARN, f"{recent} rejected in the last {th.window:g} s: {monitor.last_rejection}",
                                values)
        if monitor.last_arrival is None:
            return HealthReport(name, WARN, f"waiting for the first message on {topic}", values)
        return HealthReport(name, OK, f"{rate:.1f} Hz", values)

    def _motion_report(self) -> HealthReport:
        f = self._filter
        name = f"{self.name}: motion"
        if f.last_epoch is None:
            return HealthReport(name, WARN, "no GNSS epoch processed yet", (("status", "none"),))
        speed = f.last_epoch.speed
        values = (("speed_mps", f"{speed:.3f}"), ("status", f.last_status.name if f.last_status else "none"),
                  ("low_speed_epochs", str(f.statuses[StepStatus.LOW_SPEED])),
                  ("reversing_epochs", str(f.statuses[StepStatus.REVERSING])))
        last = f.last_estimate.status if f.last_estimate else None
        if last is StepStatus.REVERSING:
            return HealthReport(name, WARN, f"reversing (vx {speed:.2f} m/s): stiffness held", values)
        if last is StepStatus.LOW_SPEED:
            return HealthReport(name, WARN, f"low speed (|vx| {abs(speed):.2f} m/s below min_speed): stiffness held",
                                values)
        if last is StepStatus.GAP:
            return HealthReport(name, WARN, "GNSS gap longer than max_interval: motion states re-initialised", values)
        return HealthReport(name, OK, f"moving forward at {speed:.2f} m/s", values)

    def _measurement_report(self, now: float) -> HealthReport:
        f = self._filter
        th = self.thresholds
        counts = {key: window.count(now) for key, window in self._events.items()}
        values = tuple((f"{status.name.lower()}_epochs", str(f.statuses[status])) for status in StepStatus)
        values += (("gated_recent", str(counts["gated"])), ("rejected_recent", str(counts["rejected"])),
                   ("diverged_recent", str(counts["diverged"])), ("epochs_dropped", str(f.epoch_rejected)),
                   ("epochs_dropped_recent", str(counts["epoch"])), ("last_epoch_drop", f.last_epoch_rejection),
                   ("outputs_withheld", str(f.unpublished)),
                   ("epochs_steering_uncovered", str(f.uncovered))) + kind_values(f.epoch_kinds)
        name = f"{self.name}: measurements"
        window = f"in the last {th.window:g} s"
        if counts["diverged"]:
            restarts = f"; it re-initialised itself {f.statuses[StepStatus.RESTARTED]} time(s) so far"
            return HealthReport(name, ERROR, f"{counts['diverged']} filter step(s) diverged and were rolled back "
                                f"{window}" + (restarts if f.statuses[StepStatus.RESTARTED] else ""), values)
        problems = []
        if counts["gated"]:
            problems.append(f"{counts['gated']} gated by the innovation test")
        if counts["rejected"]:
            problems.append(f"{counts['rejected']} epoch(s) rejected by the filter")
        if counts["epoch"]:
            problems.append(f"{counts['epoch']} epoch(s) dropped: {f.last_epoch_rejection}")
        if problems:
            return HealthReport(name, WARN, "; ".join(problems) + f" {window}", values)
        if f.last_status is None:
            return HealthReport(name, OK, "no epoch yet", values)
        return HealthReport(name, OK, "measurements accepted", values)

    def _excitation_report(self) -> HealthReport:
        th = self.thresholds
        steer, yaw = self._steering_rms.rms(), self._yaw_rate_rms.rms()
        count = len(self._steering_rms)
        name = f"{self.name}: excitation"
        values = (("steering_rms_rad", f"{steer:.4f}"), ("yaw_rate_rms_radps", f"{yaw:.4f}"),
                  ("window_epochs", str(count)), ("min_steering_rms", f"{th.min_steering_rms:g}"),
                  ("min_yaw_rate_rms", f"{th.min_yaw_rate_rms:g}"))
        if count < th.min_window_epochs:
            return HealthReport(name, WARN, f"too few moving epochs in the last {th.window:g} s ({count})", values)
        short = []
        if steer < th.min_steering_rms:
            short.append(f"steering RMS {steer:.3f} rad < {th.min_steering_rms:g}")
        if yaw < th.min_yaw_rate_rms:
            short.append(f"yaw-rate RMS {yaw:.3f} rad/s < {th.min_yaw_rate_rms:g}")
        if short:
            return HealthReport(name, WARN, "insufficient excitation: " + ", ".join(short), values)
        return HealthReport(name, OK, f"sufficient: steering RMS {steer:.3f} rad, yaw-rate RMS {yaw:.3f} rad/s", values)

    def _latency_report(self) -> HealthReport:
        lat = self.latency
        values = (("epochs", str(lat.total)), ("median_ms", f"{1e3 * lat.percentile(50):.3f}"),
                  ("p99_ms", f"{1e3 * lat.percentile(99):.3f}"), ("max_ms", f"{1e3 * lat.percentile(100):.3f}"))
        if not len(lat):
            return HealthReport(f"{self.name}: latency", OK, "no epoch yet", values)
        return HealthReport(f"{self.name}: latency", OK, f"GNSS callback to publish: median "
                            f"{1e3 * lat.percentile(50):.2f} ms, p99 {1e3 * lat.percentile(99):.2f} ms", values)


