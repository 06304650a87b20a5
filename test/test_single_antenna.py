"""A single-antenna receiver (``ekf.measurement: course``): only the velocity's direction, no heading.

The filter's heading state is then the antenna's course (test_course_model.py checks the model); the
estimate is less precise than with a dual-antenna heading (the Cramér-Rao bound of ln Cf on the
identification drive rises ~1.8x at 2 m/s), so the defaults' ``validity.max_rel_std`` (5 %) seldom
passes it; the band must still hold the truth. Required, from 30 s on, over seeds 0-5 (measured in
brackets, session 29):

* the package's simulator, 2 m/s, +-15 deg sine, 120 s: +-2 sigma covers Cf and Cr in >= 95 % of all
  epochs (100 %); final |error| median <= 3 % (1.2 %), worst <= 6 % (2.8 %); with
  ``validity.max_rel_std`` 0.08 valid in >= 50 % (78 %), <= 5 % of those outside +-2 sigma (0);
* the independent simulator (Magic Formula mu 0.8, RK45) with the antenna 0.8 m ahead of and 0.5 m
  left of the CG: covered in >= 95 % (100 %), final median <= 3 % (2.1 %), worst <= 8 % (5.7 %);
* no timing uncertainty stated (``ekf.delay_uncertainty`` 0): never valid, the reason says why; a GNSS
  10 ms late moves the stiffness ~12 % (the tests state 2 ms; 10 ms stated: covered in >= 95 %);
* 1.5 m/s for 300 s from the default prior (1000 N/rad; seed 3 once locked onto Cf = Cr = 1500 +- 4 %
  while the course's errors drove its learned R x100): covered in >= 90 % of the epochs from 60 s on.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from drives import Run, judged_figures, run_course, sine_drive, sine_steering
from helpers import QUICK_TUNE, assembler_settings, course_epochs, run_command
from independent_sim import independent_drive

from transplanter_ident.bags import write_sim_bag
from transplanter_ident.config.parameters import (
    EstimatorConfig,
    FilterOptions,
    ValiditySettings,
    VehicleParams,
)
from transplanter_ident.config.params_file import load_params
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.epochs.assembler import EpochAssembler, assemble
from transplanter_ident.epochs.course import CourseTracker
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.validity import decide_sequence, monitor_for, sample_of
from transplanter_ident.sim.simulator import SimResult, simulate
from transplanter_ident.tuning.problem import searched_names

SEEDS = range(6)
#: the GNSS timing known to 2 ms (1-sigma): one antenna's course cannot show it (validity.setup_reasons)
COURSE = FilterOptions(measurement="course", delay_uncertainty=0.002)
#: a single antenna's estimate is ~1.8x less precise: the validity a user would set for it
RELAXED = ValiditySettings(max_rel_std=0.08)


def course_run(result: SimResult, vehicle: VehicleParams | None = None,
               options: FilterOptions = COURSE) -> tuple[Run, np.ndarray, EstimatorConfig]:
    config = EstimatorConfig(vehicle=vehicle or VehicleParams(), options=options)
    run, epochs = run_course(result, config)
    return run, decide_sequence(config, RELAXED, epochs, run.outputs), config


def coverage(runs: list[Run], start: float) -> float:
    """The share of all epochs from ``start`` on, pooled over the runs, whose +-2 sigma covers both stiffnesses."""
    return float(np.mean(np.concatenate([(lambda c: c[0] & c[1])(r.covered())[r.t >= start] for r in runs])))


def test_the_band_holds_the_truth_on_the_package_simulator() -> None:
    judged = [course_run(simulate(sine_drive(seed)))[:2] for seed in SEEDS]
    runs = [run for run, _ in judged]
    assert coverage(runs, 30.0) >= 0.95
    figures = judged_figures(judged)
    assert figures.median <= 0.03 and max(figures.finals) <= 0.06, figures
    assert figures.valid >= 0.5 and figures.missed <= 0.05, figures


def test_the_band_holds_the_truth_on_the_independent_simulator_with_a_lever_arm() -> None:
    vehicle = VehicleParams(antenna_x=0.8, antenna_y=0.5)
    judged = [course_run(independent_drive(seed, friction=0.8, vehicle=vehicle), vehicle)[:2] for seed in SEEDS]
    runs = [run for run, _ in judged]
    assert coverage(runs, 30.0) >= 0.95
    figures = judged_figures(judged)
    assert figures.median <= 0.03 and max(figures.finals) <= 0.08, figures


def test_a_far_prior_at_low_speed_converges_instead_of_stalling() -> None:
    runs = [course_run(simulate(sine_drive(seed, speed=1.5, duration=300.0)))[0] for seed in (0, 3)]
    assert coverage(runs, 60.0) >= 0.90
    for run in runs:
        assert all(abs(e) <= 0.10 for e in run.final_errors()), run.final_errors()


@pytest.mark.parametrize("uncertainty", [0.0, FilterOptions().delay_uncertainty])
def test_without_a_stated_timing_uncertainty_it_is_never_valid_and_says_why(uncertainty: float) -> None:
    """A GNSS 10 ms late moves the stiffness ~12 % and the course cannot show it (the tuner's delay NLL is flat).

    None stated (the default, < 0: a heading then holds 1 ms, and its delay measure flags 10 ms and more) or 0 alike.
    """
    assert FilterOptions().delay_uncertainty < 0.0
    result = simulate(sine_drive(0, gnss_delay=0.010))
    run, valid, config = course_run(result, options=replace(COURSE, delay_uncertainty=uncertainty))
    assert not valid.any()
    assert max(abs(e) for e in run.final_errors()) > 0.08  # what the reason guards against: wrong, and precise-looking
    assert any("timing" in r for r in monitor_for(config, RELAXED).setup)
    stated = course_run(result, options=replace(COURSE, delay_uncertainty=0.010))[0]  # told the timing's 1-sigma
    assert coverage([stated], 30.0) >= 0.95


def test_the_course_is_not_taken_for_a_misconfigured_heading() -> None:
    """With a dual-antenna heading, a course over ground is an ERROR; told it is a course, no reason names it."""
    result = simulate(sine_drive(0, duration=60.0))
    run, _, config = course_run(result)
    monitor = monitor_for(config, RELAXED)
    epochs = course_epochs(result)
    reasons = set()
    for i in range(len(epochs)):
        reasons.update(monitor.step(sample_of(epochs[i], run.outputs[i], 0)).reasons)
    assert reasons, "the monitor judged nothing"  # it did decide (the start is never valid)
    assert not any("course over ground" in r for r in reasons), reasons
    heading_config = replace(config, options=replace(COURSE, measurement="heading"))
    heading_outputs = run_sequence(heading_config, epochs)  # the same epochs, the course taken as a heading
    monitor = monitor_for(heading_config, RELAXED)
    named = set()
    for i in range(len(epochs)):
        named.update(monitor.step(sample_of(epochs[i], heading_outputs[i], 0)).reasons)
    assert any("course over ground" in r for r in named), named


def test_the_measured_lateral_velocity_is_absent_not_made_up() -> None:
    """One antenna measures no vy: the epochs carry NaN there; the speed is the antenna's |v|."""
    result = simulate(sine_drive(0, duration=20.0))
    epochs = course_epochs(result)
    assert np.all(np.isnan(epochs.lateral_velocity))
    assert np.all(np.abs(np.asarray(epochs.antenna_lateral_velocity)) <= 1e-12)
    speed = np.hypot(result.velocity_enu[:, 0], result.velocity_enu[:, 1])
    assert np.allclose(epochs.longitudinal_velocity, speed[-len(epochs):], rtol=0.0, atol=1e-12)
    assert math.isclose(float(np.median(epochs.longitudinal_velocity)), 2.0, rel_tol=0.02)


def test_the_tuner_tunes_a_course_and_refuses_what_a_course_cannot_calibrate(tmp_path: Path) -> None:
    """Q/R tune without the unused heading R; the calibration searches are refused with the reason (exit 1)."""
    bag = tmp_path / "sine"
    write_sim_bag(simulate(sine_drive(1, duration=40.0)), bag)
    course = tmp_path / "course.yaml"
    course.write_text("estimator:\n  ros__parameters:\n    ekf:\n      measurement: course\n", encoding="utf-8")
    out = tmp_path / "tuned.yaml"
    done = run_command("tuner", bag, "--params-file", course, "-o", out, *QUICK_TUNE)
    assert done.returncode == 0, done.stdout + done.stderr
    tuned = load_params([course, out])
    assert tuned.config.options.course
    assert tuned.config.noise.measurement_noise[1] == EstimatorConfig().noise.measurement_noise[1]  # not searched
    assert searched_names(tuned.config.options) == ("q_vy", "q_r", "q_psi", "r_vy")
    refused = run_command("tuner", bag, "--params-file", course, "-o", tmp_path / "no.yaml", "--estimate-delay",
                          *QUICK_TUNE)
    assert refused.returncode == 1 and "--estimate-delay: not with ekf.measurement course" in refused.stderr
    assert not (tmp_path / "no.yaml").exists()


def test_reversing_through_a_stop_is_told_from_the_course() -> None:
    """Reversing, the velocity points backwards: the epochs keep the vehicle's heading and take a negative speed.

    Synthetic (the simulators drive forwards only): the vehicle points 0.3 rad, drives 1.5 m/s, stops over 2 s,
    reverses at 1 m/s for 6 s, stops and drives on; 5 Hz velocity, 50 Hz steering at 0.
    """
    heading, samples = 0.3, []
    for k in range(0, 50 * 40 + 1):
        t = k / 50.0
        samples.append(("steering", t, (0.0,)))
        if k % 10 == 0:
            speed = float(np.interp(t, [0, 10, 12, 14, 20, 22, 24, 40], [1.5, 1.5, 0.0, -1.0, -1.0, 0.0, 1.5, 1.5]))
            samples.append(("velocity", t, (speed * math.cos(heading), speed * math.sin(heading))))
    assembler = EpochAssembler(assembler_settings(VehicleParams(), course=True))
    epochs = EpochArrays(assemble(assembler, samples))
    t, speed = np.asarray(epochs.t), np.asarray(epochs.speed)
    steady = np.abs(np.asarray(epochs.longitudinal_velocity)) >= 0.3
    assert np.all(speed[(t > 14.5) & (t < 20.0)] < -0.9)  # reversing: the filter holds the stiffness (REVERSING)
    assert np.all(speed[(t > 2.0) & (t < 10.0)] > 1.4) and np.all(speed[t > 25.0] > 1.4)
    off = np.remainder(np.asarray(epochs.heading)[steady] - heading + math.pi, 2.0 * math.pi) - math.pi
    assert np.allclose(off, 0.0, atol=1e-9)  # the vehicle's heading (mod 2 pi, unwrapped through the stops)
    reasons = {r.reason.split(" ")[0] for r in assembler.drain_rejections()}
    assert reasons <= {"yaw"}, reasons  # only the stop's noisy directions may be beyond the yaw-rate limit


def kinematic_samples(legs: list[tuple[float, float, float]], behind_rear_axle: float = 0.0,
                      heading: float = 0.3) -> list:
    """5 Hz velocity and 50 Hz steering samples of a kinematic single-track vehicle (L = 1.1 m) driving ``legs``.

    Each leg is (duration s, signed speed m/s, wheel angle rad), both ramped from the previous leg's over
    its first second. The antenna is ``behind_rear_axle`` m behind the rear axle (it swings out in a turn).
    """
    wheelbase, dt = 1.1, 0.02
    samples: list = []
    speed = angle = t = 0.0
    k = 0
    for duration, leg_speed, leg_angle in legs:
        start_speed, start_angle = speed, angle
        for step in range(round(duration / dt)):
            ramp = min(step * dt, 1.0)
            speed = start_speed + (leg_speed - start_speed) * ramp
            angle = start_angle + (leg_angle - start_angle) * ramp
            yaw_rate = speed * math.tan(angle) / wheelbase
            samples.append(("steering", t, (angle,)))
            if k % 10 == 0:
                swing = -behind_rear_axle * yaw_rate  # the antenna's lateral velocity
                samples.append(("velocity", t, (speed * math.cos(heading) - swing * math.sin(heading),
                                                speed * math.sin(heading) + swing * math.cos(heading))))
            heading += yaw_rate * dt
            t, k = t + dt, k + 1
    return samples


def signed_speeds(samples: list, behind_rear_axle: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The course epochs' times and signed speeds (negative: taken as reversing).

    The assembler is told the antenna is ``behind_rear_axle`` m behind the rear axle (L 1.1 m, as
    kinematic_samples).
    """
    vehicle = replace(VehicleParams(), lf=0.7, lr=0.4, antenna_x=-0.4 - behind_rear_axle)
    epochs = EpochArrays(assemble(EpochAssembler(assembler_settings(vehicle, course=True)), samples))
    return np.asarray(epochs.t), np.asarray(epochs.speed)


def test_a_log_that_starts_reversing_is_told_by_the_steering() -> None:
    """Reversing with the wheels 15 deg left, the course turns right (0.24 rad/s): reversing from 3.5 s on.

    DECISIVE_TURN (30 deg) is promised after the 1 s ramp and about 2.2 s; then forwards again through the stop.
    """
    t, speed = signed_speeds(kinematic_samples([(10.0, -1.0, math.radians(15.0)), (3.0, 0.0, 0.0),
                                                (10.0, 1.5, math.radians(10.0))]))
    assert np.all(speed[(t > 3.5) & (t < 10.0)] < -0.9)
    assert np.all(speed[t > 15.0] > 1.4)


def test_a_pivot_at_a_creep_is_no_reversal_once_the_vehicle_steers() -> None:
    """A 120 deg pivot at 0.2 m/s looks like a reversal through a stop; the next steered turn puts it right.

    The pivot is below REVERSAL_SPEED; 3 s of the next turn (10 deg left at 1.5 m/s) show the vehicle goes
    forwards.
    """
    pivot = math.radians(120.0) / (0.2 * math.tan(math.radians(30.0)) / 1.1)
    t, speed = signed_speeds(kinematic_samples([(10.0, 1.5, 0.0), (pivot + 2.0, 0.2, math.radians(30.0)),
                                                (15.0, 1.5, math.radians(10.0))]))
    assert np.all(speed[(t > 2.0) & (t < 10.0)] > 1.4)
    assert np.any(speed < 0.0)  # the pivot fooled the turn-through-a-stop rule for a while
    assert np.all(speed[t > 12.0 + pivot + 3.0] > 1.4)


def test_steering_hard_never_fakes_a_reversal() -> None:
    """Steering from 30 deg left to 30 deg right and back in 1 s, every 4 s: no reversal faked, either way.

    At 0.6 m/s, forwards and (from a reversing start) backwards. An antenna d behind the rear axle swings out
    against the steering as the wheels turn, by d (tan 30 deg - tan 3 deg) / L: 1.5 m behind is harmless when the
    assembler is not told; 3 m behind is harmless when it is told (vehicle.antenna_x) and takes the swing off,
    and fakes reversals when it is not: the lever arm must be set.
    """
    legs = [(4.0, 0.6, math.radians(30.0) * (-1) ** k) for k in range(20)]
    backwards = [(4.0, -0.6, math.radians(20.0)), *[(duration, -speed, angle) for duration, speed, angle in legs]]
    for behind, told in ((3.0, 3.0), (1.5, 0.0)):
        t, speed = signed_speeds(kinematic_samples(legs, behind_rear_axle=behind), told)
        assert np.all(speed[t > 2.0] > 0.3), (behind, told)
        t, speed = signed_speeds(kinematic_samples(backwards, behind_rear_axle=behind), told)
        assert np.all(speed[t > 4.5] < -0.3), (behind, told)
    t, speed = signed_speeds(kinematic_samples(legs, behind_rear_axle=3.0), 0.0)
    assert np.any(speed < 0.0)


def test_noisy_creeping_never_fakes_a_reversal() -> None:
    """0.4 m/s, three times the default GNSS noise (the course's own noise ~0.15 rad), +-25 deg and +-5 deg sines.

    Seeds 0-2, 60 s each: no epoch taken as reversing (session 30: 21 % of them were, with a rule on the turn
    alone, before the kinematic turn the steering promises had to reach DECISIVE_TURN first).
    """
    for seed in range(3):
        for amplitude, period in ((25.0, 6.0), (5.0, 3.0)):
            config = sine_drive(seed, speed=0.4, duration=60.0, steering=sine_steering(math.radians(amplitude), period))
            noise = replace(config.noise, velocity=3.0 * config.noise.velocity, heading=3.0 * config.noise.heading)
            epochs = course_epochs(simulate(replace(config, noise=noise)))
            assert np.all(np.asarray(epochs.speed) > 0.0), (seed, amplitude)


def test_a_gnss_time_step_restarts_the_run_of_steering() -> None:
    """GNSS stamps stepping back 100 s within a run of steering: the run restarts, reversing is still told.

    Without the restart the run promises a turn over -100 s and never decides; with it, a log that starts
    reversing is told within 4 s of the step (CourseTracker alone).
    """
    samples = kinematic_samples([(10.0, -1.0, math.radians(15.0))])
    tracker = CourseTracker(0.0, 1.1)
    steering, reversing_after = 0.0, []
    for kind, t, values in samples:
        if kind == "steering":
            steering = values[0]
            continue
        stamp = t if t < 2.0 else t - 100.0
        tracker.heading(stamp, *values, steering)
        reversing_after.append((t, tracker.reversing))
    assert all(reversing for t, reversing in reversing_after if t > 6.0)
