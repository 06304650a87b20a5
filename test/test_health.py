"""Tests of transplanter_ident.evaluation.health: rates, windows and the diagnostic levels (no ROS)."""

from __future__ import annotations

import math

import pytest

from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.ekf.layout import StepStatus
from transplanter_ident.epochs.epoch import Epoch, Rejection
from transplanter_ident.evaluation.health import (
    ERROR,
    OK,
    WARN,
    HealthMonitor,
    HealthThresholds,
    InputMonitor,
    should_publish,
)
from transplanter_ident.evaluation.validity import Decision
from transplanter_ident.evaluation.windows import LatencyStats, RollingRms, Throttle, TimeWindow, percentile

TH = HealthThresholds(stale_timeout=1.0, window=10.0, converged_rel_std=0.05, min_steering_rms=0.02,
                      min_yaw_rate_rms=0.02, min_window_epochs=5)


def epoch(t: float, speed: float = 2.0, steering: float = 0.1, yaw_rate: float = 0.2) -> Epoch:
    return Epoch(t=t, longitudinal_velocity=speed, lateral_velocity=0.01, heading=0.0, yaw_rate=yaw_rate,
                 steering=steering, steering_rate=0.0, speed=speed)


def estimate(t: float, status: StepStatus = StepStatus.UPDATED, cf: float = 8000.0, cr: float = 10000.0,
             rel_std: float = 0.01) -> Estimate:
    return Estimate(t=t, status=status, lateral_velocity=0.0, yaw_rate=0.0, cornering_stiffness_front=cf,
                    cornering_stiffness_rear=cr, cornering_stiffness_front_std=rel_std * cf,
                    cornering_stiffness_rear_std=rel_std * cr, lateral_velocity_model=0.0, yaw_rate_model=0.0,
                    innovation=(0.0, 0.0), innovation_covariance=(1.0, 0.0, 1.0),
                    normalized_innovation_squared=0.0)


def by_name(reports: list, name: str):  # noqa: ANN201
    return next(r for r in reports if r.name == f"estimator: {name}")


def fed_monitor(now: float = 100.0, epochs: int = 50, **estimate_args: object) -> HealthMonitor:
    """A monitor that saw 10 Hz inputs and ``epochs`` epochs up to ``now``."""
    monitor = HealthMonitor(TH, now - epochs * 0.1, {"velocity": "/gnss/vel"})
    for k in range(epochs):
        t = now - (epochs - 1 - k) * 0.1
        for name in ("velocity", "heading", "steering"):
            monitor.on_message(name, t)
        monitor.on_estimate(epoch(t), estimate(t, **estimate_args), t)
        monitor.on_validity(Decision(True, (), False))
    return monitor


# --------------------------------------------------------------------------- building blocks


def test_time_window_drops_old_events() -> None:
    window = TimeWindow(1.0)
    for t in (0.0, 0.5, 1.0, 1.6):
        window.add(t)
    assert window.count(1.6) == 2  # 1.0 and 1.6; 0.5 < 1.6 - 1.0
    assert window.count(5.0) == 0


def test_rolling_rms_matches_direct_computation_and_restarts_on_time_reversal() -> None:
    rms = RollingRms(2.0)
    values = [(0.1 * k, math.sin(0.3 * k)) for k in range(100)]
    for t, v in values:
        rms.add(t, v)
    inside = [v for t, v in values if t >= values[-1][0] - 2.0]
    assert rms.rms() == pytest.approx(math.sqrt(sum(v * v for v in inside) / len(inside)), rel=1e-12)
    rms.add(0.0, 3.0)  # a bag restarted
    assert len(rms) == 1 and rms.rms() == pytest.approx(3.0)
    assert math.isnan(RollingRms(1.0).rms())


def test_percentile_interpolates_and_handles_empty() -> None:
    assert percentile([3.0, 1.0, 2.0], 50) == 2.0
    assert percentile([0.0, 10.0], 99) == pytest.approx(9.9)
    assert percentile([5.0], 99) == 5.0
    assert math.isnan(percentile([], 50))
    stats = LatencyStats(size=3)
    for v in (1.0, 2.0, 3.0, 4.0):
        stats.add(v)
    assert len(stats) == 3 and stats.total == 4 and stats.percentile(50) == 3.0


def test_input_monitor_rate_and_age() -> None:
    monitor = InputMonitor("velocity", TH, start=0.0)
    assert monitor.age(2.5) == 2.5 and monitor.rate(2.5) == 0.0
    for k in range(51):
        monitor.record(10.0 + 0.1 * k)  # 10 Hz
    assert monitor.rate(15.0) == pytest.approx(10.0)
    assert monitor.age(15.5) == pytest.approx(0.5)


def test_thresholds_are_validated() -> None:
    with pytest.raises(ValueError, match="stale_timeout"):
        HealthThresholds(stale_timeout=0.0)
    with pytest.raises(ValueError, match="min_steering_rms"):
        HealthThresholds(min_steering_rms=-1.0)
    with pytest.raises(ValueError, match="converged_rel_std"):
        HealthThresholds(converged_rel_std=math.nan)


def test_should_publish_only_after_a_state_change() -> None:
    published = {s for s in StepStatus if should_publish(s)}
    assert published == {StepStatus.UPDATED, StepStatus.GATED, StepStatus.LOW_SPEED, StepStatus.REVERSING,
                         StepStatus.INITIALISED, StepStatus.GAP, StepStatus.NONLINEAR, StepStatus.REINITIALISED,
                         StepStatus.RESTARTED}


def test_throttle_counts_suppressed_lines() -> None:
    throttle = Throttle(5.0)
    assert throttle.allow("a", 0.0) == (True, 0)
    assert throttle.allow("a", 1.0) == (False, 0)
    assert throttle.allow("b", 1.0) == (True, 0)
    assert throttle.allow("a", 2.0) == (False, 0)
    assert throttle.allow("a", 6.0) == (True, 2)


# --------------------------------------------------------------------------- levels


def test_healthy_run_is_all_ok() -> None:
    reports = fed_monitor().report(100.05)
    levels = {r.name: r.level_name for r in reports}
    assert all(level == "OK" for level in levels.values()), levels
    velocity = by_name(reports, "velocity input")
    assert float(velocity.value("rate_hz")) == pytest.approx(10.0, rel=1e-6)
    assert velocity.value("topic") == "/gnss/vel"


def test_stale_input_is_an_error_and_never_seen_waits_first() -> None:
    monitor = fed_monitor()
    reports = monitor.report(101.5)  # 1.5 s after the last message, timeout 1 s
    steering = by_name(reports, "steering input")
    assert steering.level == ERROR and "stale" in steering.message and steering.value("rate_hz") == "0.00"
    fresh = HealthMonitor(TH, 0.0)
    assert by_name(fresh.report(0.5), "heading input").level == WARN  # within the timeout: waiting
    late = by_name(fresh.report(1.5), "heading input")
    assert late.level == ERROR and "since start" in late.message


def test_rejections_warn_with_the_reason_then_clear_after_the_window() -> None:
    monitor = fed_monitor()
    monitor.on_rejection(Rejection("steering", 99.0, "|0.900| rad beyond max_steering 0.700"), 100.0)
    report = by_name(monitor.report(100.05), "steering input")
    assert report.level == WARN and "beyond max_steering" in report.message
    assert report.value("rejected") == "1"
    for k in range(1, 120):  # keep the input fresh for 12 s
        monitor.on_message("steering", 100.0 + 0.1 * k)
    later = by_name(monitor.report(111.9), "steering input")
    assert later.level == OK and later.value("rejected") == "1" and later.value("rejected_recent") == "0"


def test_epoch_rejections_are_reported_under_measurements() -> None:
    monitor = fed_monitor()
    monitor.on_rejection(Rejection("epoch", 99.0, "no recent steering angle"), 100.0)
    report = by_name(monitor.report(100.05), "measurements")
    assert report.level == WARN and "no recent steering angle" in report.message


@pytest.mark.parametrize(("status", "speed", "text"), [
    (StepStatus.LOW_SPEED, 0.0, "low speed"),
    (StepStatus.REVERSING, -1.0, "reversing"),
    (StepStatus.GAP, 2.0, "gap"),
])
def test_motion_warnings(status: StepStatus, speed: float, text: str) -> None:
    monitor = fed_monitor()
    monitor.on_estimate(epoch(100.1, speed=speed), estimate(100.1, status), 100.1)
    report = by_name(monitor.report(100.15), "motion")
    assert report.level == WARN and text in report.message.lower()


def test_gating_warns_and_divergence_is_an_error() -> None:
    monitor = fed_monitor()
    monitor.on_estimate(epoch(100.1), estimate(100.1, StepStatus.GATED), 100.1)
    report = by_name(monitor.report(100.15), "measurements")
    assert report.level == WARN and "gated" in report.message and report.value("gated_epochs") == "1"
    monitor.on_estimate(epoch(100.2), estimate(100.2, StepStatus.DIVERGED), 100.2)
    assert by_name(monitor.report(100.25), "measurements").level == ERROR
    monitor.on_estimate(epoch(100.3), estimate(100.3, StepStatus.RESTARTED), 100.3)
    report = by_name(monitor.report(100.35), "measurements")
    assert report.level == ERROR and "re-initialised itself 1 time" in report.message
    assert report.value("restarted_epochs") == "1"


def test_convergence_threshold() -> None:
    assert by_name(fed_monitor(rel_std=0.01).report(100.05), "convergence").level == OK
    loose = by_name(fed_monitor(rel_std=0.2).report(100.05), "convergence")
    assert loose.level == WARN and loose.value("converged") == "false" and "not converged" in loose.message
    assert by_name(HealthMonitor(TH, 0.0).report(0.1), "convergence").level == WARN


def test_excitation_needs_steering_and_yaw_rate() -> None:
    monitor = HealthMonitor(TH, 0.0)
    for k in range(50):
        t = 0.1 * k
        monitor.on_estimate(epoch(t, steering=0.001, yaw_rate=0.0005), estimate(t), t)
    report = by_name(monitor.report(5.0), "excitation")
    assert report.level == WARN and "steering RMS" in report.message and "yaw-rate RMS" in report.message
    for k in range(50, 200):  # 15 s of good excitation: the weak part leaves the 10 s window
        t = 0.1 * k
        monitor.on_estimate(epoch(t, steering=0.1 * math.sin(t), yaw_rate=0.2 * math.sin(t)), estimate(t), t)
    assert by_name(monitor.report(20.0), "excitation").level == OK
    few = HealthMonitor(TH, 0.0)
    few.on_estimate(epoch(0.0), estimate(0.0), 0.0)
    assert "too few" in by_name(few.report(0.1), "excitation").message


def test_low_speed_epochs_do_not_count_as_excitation() -> None:
    monitor = HealthMonitor(TH, 0.0)
    for k in range(50):
        t = 0.1 * k
        monitor.on_estimate(epoch(t, speed=0.0), estimate(t, StepStatus.LOW_SPEED), t)
    assert by_name(monitor.report(5.0), "excitation").value("window_epochs") == "0"


def test_reset_forgets_the_filter_but_not_the_inputs() -> None:
    monitor = fed_monitor()
    monitor.on_estimate(epoch(100.1), estimate(100.1, StepStatus.GATED), 100.1)
    monitor.reset_filter()
    reports = monitor.report(100.15)
    assert by_name(reports, "convergence").message == "no estimate yet"
    assert by_name(reports, "measurements").level == OK
    assert by_name(reports, "velocity input").level == OK


def test_latency_report() -> None:
    monitor = HealthMonitor(TH, 0.0)
    for ms in range(1, 101):
        monitor.on_latency(ms * 1e-4)
    report = by_name(monitor.report(0.0), "latency")
    assert report.level == OK and report.value("epochs") == "100"
    assert float(report.value("median_ms")) == pytest.approx(5.05, abs=1e-3)


def test_thresholds_change_at_run_time() -> None:
    monitor = fed_monitor(rel_std=0.08)
    assert by_name(monitor.report(100.05), "convergence").level == WARN
    monitor.set_thresholds(HealthThresholds(converged_rel_std=0.1))
    assert by_name(monitor.report(100.05), "convergence").level == OK
