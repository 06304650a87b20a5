"""Tests of the GNSS/steering -> epoch conversion (transplanter_ident.epochs.assembler)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import NO_NOISE, assembler_settings, epochs_from_result, sim_samples
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad

from transplanter_ident.config.parameters import VehicleParams
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler, assemble
from transplanter_ident.epochs.epoch import Epoch
from transplanter_ident.epochs.frames import quaternion_yaw, wrap_angle
from transplanter_ident.epochs.steering_line import interval_line
from transplanter_ident.sim.simulator import SimConfig, simulate

STEERING_RATE = 50.0  # Hz


def wrap(angle: float) -> float:
    """Wrap to [-pi, pi), as a receiver reports its heading."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def motion_samples(times, east, north, yaw, steering=0.05, *, velocity_frame="enu", heading_frame="enu"):
    """(topic, stamp, values) samples of a GNSS trajectory plus a constant 50 Hz steering stream.

    east, north: ENU ground velocity of the antenna; yaw: ENU yaw (rad, any branch). Each GNSS
    epoch's velocity and heading share its stamp; steering samples come first at equal stamps.
    """
    samples = []
    t_end = float(times[-1])
    steering_times = np.arange(0.0, t_end + 0.5 / STEERING_RATE, 1.0 / STEERING_RATE)
    keyed = [(float(t), 0, ("steering", float(t), (float(steering),))) for t in steering_times]
    for t, e, n, y in zip(times, east, north, yaw, strict=True):
        velocity = (float(e), float(n)) if velocity_frame == "enu" else (float(n), float(e))
        if heading_frame == "enu":
            heading = wrap(float(y))
        else:  # compass heading, clockwise from north, in [0, 2 pi)
            heading = (math.pi / 2.0 - float(y)) % (2.0 * math.pi)
        keyed.append((float(t), 1, ("velocity", float(t), velocity)))
        keyed.append((float(t), 2, ("heading", float(t), (heading,))))
    keyed.sort(key=lambda item: (item[0], item[1]))
    samples = [sample for _, _, sample in keyed]
    return samples


def run(samples, **overrides) -> tuple[list[Epoch], list]:
    assembler = EpochAssembler(AssemblerSettings(**overrides))
    epochs = assemble(assembler, samples)
    return epochs, assembler.drain_rejections()


def body_to_enu(vx, vy, yaw):
    c, s = np.cos(yaw), np.sin(yaw)
    return vx * c - vy * s, vx * s + vy * c


def circle(radius=5.0, vx=2.0, vy=-0.08, yaw0=2.5, duration=10.0, rate=5.0, sign=1.0):
    """A steady circle at the CG: constant body velocity, r = sign * V / R."""
    times = np.arange(0.0, duration + 0.5 / rate, 1.0 / rate)
    yaw_rate = sign * math.hypot(vx, vy) / radius
    yaw = yaw0 + yaw_rate * times
    east, north = body_to_enu(vx, vy, yaw)
    return times, east, north, yaw, yaw_rate


def assert_epochs_close(a: list[Epoch], b: list[Epoch], tol: float, *, heading_modulo_2pi: bool = False):
    assert len(a) == len(b) > 0
    for x, y in zip(a, b, strict=True):
        for name in ("t", "longitudinal_velocity", "lateral_velocity", "yaw_rate", "steering", "steering_rate",
                     "speed"):
            assert getattr(x, name) == pytest.approx(getattr(y, name), rel=0.0, abs=tol), name
        if heading_modulo_2pi:
            assert abs(wrap_angle(x.heading - y.heading)) <= tol
        else:
            assert x.heading == pytest.approx(y.heading, rel=0.0, abs=tol)


# --------------------------------------------------------------------------- frames and geometry


@settings(max_examples=60, deadline=None)
@given(
    angle=st.floats(-2.0 * math.pi, 2.0 * math.pi),
    yaw0=st.floats(-math.pi, math.pi),
    yaw_rates=st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=25),
    vx=st.floats(0.2, 3.0),
    vy=st.floats(-0.5, 0.5),
    antenna=st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)),
)
def test_rotating_the_trajectory_leaves_body_quantities_unchanged(angle, yaw0, yaw_rates, vx, vy, antenna):
    """A constant rotation of ENU velocity and heading changes no epoch's vx, vy, r (1e-9); psi shifts by it."""
    dt = 0.2
    times = dt * np.arange(len(yaw_rates) + 1)
    yaw = yaw0 + np.concatenate([[0.0], np.cumsum(np.array(yaw_rates) * dt)])
    body_vx = vx + 0.3 * np.sin(times)  # body velocity varies along the way
    body_vy = vy * np.cos(times)
    east, north = body_to_enu(body_vx, body_vy, yaw)
    c, s = math.cos(angle), math.sin(angle)
    lever = {"antenna_x": antenna[0], "antenna_y": antenna[1]}
    original, rejected = run(motion_samples(times, east, north, yaw), **lever)
    rotated, rejected_rotated = run(motion_samples(times, c * east - s * north, s * east + c * north, yaw + angle),
                                    **lever)
    assert not rejected and not rejected_rotated
    assert len(original) == len(rotated) == len(yaw_rates)
    for a, b in zip(original, rotated, strict=True):
        for name in ("longitudinal_velocity", "lateral_velocity", "yaw_rate", "speed", "steering"):
            assert abs(getattr(a, name) - getattr(b, name)) <= 1e-9, name
        assert abs(wrap_angle(b.heading - a.heading - angle)) <= 1e-9
    # with no lever arm the epochs are the body velocity at each GNSS stamp
    if antenna == (0.0, 0.0):
        np.testing.assert_allclose([e.longitudinal_velocity for e in original], body_vx[1:], atol=1e-9)


def test_steady_circle_gives_v_over_r():
    """Circle of radius 5 m at V = |(2, -0.08)| m/s: r = V / R (1e-9), vy and vx as generated (1e-9)."""
    radius, vx, vy = 5.0, 2.0, -0.08
    times, east, north, yaw, yaw_rate = circle(radius=radius, vx=vx, vy=vy)
    assert yaw_rate == pytest.approx(math.hypot(vx, vy) / radius)
    epochs, rejected = run(motion_samples(times, east, north, yaw))
    assert not rejected
    assert len(epochs) == len(times) - 1
    for epoch in epochs:
        assert epoch.yaw_rate == pytest.approx(math.hypot(vx, vy) / radius, rel=0.0, abs=1e-9)
        assert epoch.lateral_velocity == pytest.approx(vy, rel=0.0, abs=1e-9)
        assert epoch.longitudinal_velocity == pytest.approx(vx, rel=0.0, abs=1e-9)
        assert epoch.speed == pytest.approx(vx, rel=0.0, abs=1e-9)
        assert epoch.steering == pytest.approx(0.05, abs=1e-12)
        assert epoch.steering_rate == pytest.approx(0.0, abs=1e-9)


def test_speed_is_the_interval_mean_and_vx_the_end_value():
    """Accelerating, vx = 1 + 0.5 t, while turning: epoch vx is vx(t_k), speed the mean over the interval (1e-12)."""
    times = np.arange(0.0, 4.0 + 1e-9, 0.2)
    vx = 1.0 + 0.5 * times
    yaw = 0.4 + 0.3 * times
    east, north = body_to_enu(vx, 0.02, yaw)
    epochs, rejected = run(motion_samples(times, east, north, yaw))
    assert not rejected
    np.testing.assert_allclose([e.longitudinal_velocity for e in epochs], vx[1:], rtol=0.0, atol=1e-12)
    np.testing.assert_allclose([e.speed for e in epochs], 0.5 * (vx[1:] + vx[:-1]), rtol=0.0, atol=1e-12)
    np.testing.assert_allclose([e.lateral_velocity for e in epochs], 0.02, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize(("velocity_frame", "heading_frame"), [("ned", "ned"), ("enu", "ned"), ("ned", "enu")])
def test_frames_give_identical_epochs(velocity_frame, heading_frame):
    """ENU velocity + ENU yaw vs NED velocity (north, east) and/or compass heading: same epochs (1e-12).

    The unwrapped heading may start on another branch (a compass heading is reported in [0, 2 pi)),
    so psi is compared modulo 2 pi; its increments, hence r, are compared exactly.
    """
    times, east, north, yaw, _ = circle(yaw0=-2.9, sign=-1.0)
    reference, rejected = run(motion_samples(times, east, north, yaw))
    other, rejected_other = run(motion_samples(times, east, north, yaw, velocity_frame=velocity_frame,
                                               heading_frame=heading_frame),
                                velocity_frame=velocity_frame, heading_frame=heading_frame)
    assert not rejected and not rejected_other
    assert_epochs_close(reference, other, 1e-12, heading_modulo_2pi=True)
    np.testing.assert_allclose(np.diff([e.heading for e in other]), np.diff([e.heading for e in reference]),
                               rtol=0.0, atol=1e-12)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_heading_wrap_at_pi(sign):
    """Turning through +pi (left) or -pi (right): the epoch heading is continuous and r correct (1e-9)."""
    times, east, north, yaw, yaw_rate = circle(radius=4.0, vx=2.0, vy=0.0, yaw0=sign * 2.6, duration=6.0,
                                               sign=sign)
    wrapped = np.array([wrap(y) for y in yaw])
    assert np.any(np.abs(np.diff(wrapped)) > math.pi)  # the raw sensor heading does jump
    epochs, rejected = run(motion_samples(times, east, north, yaw))
    assert not rejected
    heading = np.array([e.heading for e in epochs])
    np.testing.assert_allclose(heading, yaw[1:], rtol=0.0, atol=1e-9)  # same branch, past +-pi
    assert abs(heading[-1]) > math.pi
    np.testing.assert_allclose([e.yaw_rate for e in epochs], yaw_rate, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose([e.lateral_velocity for e in epochs], 0.0, atol=1e-9)


def test_lever_arm_is_removed_exactly():
    """Antenna at (0.6, 0.2) m, steady turn, no noise: epoch vx, vy = the CG truth (1e-9) after the transient."""
    vehicle = VehicleParams(antenna_x=0.6, antenna_y=0.2)
    config = SimConfig(vehicle=vehicle, duration=8.0, speed=2.0, noise=NO_NOISE,
                       steering=lambda t: np.full(np.shape(t), math.radians(10.0)))
    result = simulate(config)
    epochs = epochs_from_result(result, vehicle)
    index = {float(t): k for k, t in enumerate(result.gnss_time)}
    steady = [e for e in epochs if e.t >= 3.0]
    assert len(steady) >= 20
    for epoch in steady:
        k = index[epoch.t]
        r = result.truth_yaw_rate[k]
        assert abs(r * vehicle.antenna_x) > 0.05  # the lever arm matters here
        assert epoch.yaw_rate == pytest.approx(r, rel=0.0, abs=1e-9)
        assert epoch.lateral_velocity == pytest.approx(result.truth_vy[k], rel=0.0, abs=1e-9)
        assert epoch.longitudinal_velocity == pytest.approx(result.truth_vx[k], rel=0.0, abs=1e-9)
        assert epoch.speed == pytest.approx(result.truth_vx[k], rel=0.0, abs=1e-9)
    # without the compensation the antenna's vy would be off by r * antenna_x
    plain = EpochAssembler(assembler_settings(VehicleParams()))
    uncompensated = [e for e in assemble(plain, sim_samples(result)) if e.t >= 3.0]
    k = index[uncompensated[-1].t]
    assert uncompensated[-1].lateral_velocity == pytest.approx(
        result.truth_vy[k] + result.truth_yaw_rate[k] * vehicle.antenna_x, abs=1e-9)


# --------------------------------------------------------------------------- interval_line


@pytest.mark.parametrize("rate", [3.0, 10.0, 50.0, 173.0])
@pytest.mark.parametrize("phase", [0.0, 0.37])
def test_interval_line_is_exact_for_a_linear_signal(rate, phase):
    """A line 0.3 + 1.7 t sampled at any rate over [-1, 2]: mean and slope over sub-intervals exact (1e-12)."""
    times = (np.arange(0, math.ceil(3.0 * rate)) + phase) / rate - 1.0
    values = 0.3 + 1.7 * times
    for start, end in ((0.0, 0.2), (0.013, 0.05), (0.1, 0.1 + 1.0 / rate)):
        mean, slope = interval_line(times, values, start, end)
        assert mean == pytest.approx(0.3 + 1.7 * 0.5 * (start + end), rel=0.0, abs=1e-12)
        assert slope == pytest.approx(1.7, rel=1e-12)


def test_interval_line_of_a_constant():
    times = np.linspace(-1.0, 1.0, 17)
    mean, slope = interval_line(times, np.full(17, -0.25), 0.05, 0.3)
    assert mean == pytest.approx(-0.25, abs=1e-15)
    assert slope == pytest.approx(0.0, abs=1e-12)
    assert interval_line([0.1], [0.4], 0.0, 0.2) == pytest.approx((0.4, 0.0), abs=1e-15)  # one sample


def test_interval_line_holds_beyond_the_samples():
    # y = t on [0, 1], held at 1 on [1, 2]: mean 0.75; slope = 12 / T^3 * integral (t - 1) y dt = 0.5
    mean, slope = interval_line([0.0, 1.0], [0.0, 1.0], 0.0, 2.0)
    assert (mean, slope) == pytest.approx((0.75, 0.5), abs=1e-14)
    # held at the first sample before it: y = 0 on [-1, 0], t on [0, 1]
    mean, slope = interval_line([0.0, 1.0], [0.0, 1.0], -1.0, 1.0)
    assert (mean, slope) == pytest.approx((0.25, 0.5), abs=1e-14)
    # all samples before the interval: the last value, flat
    assert interval_line([0.0, 0.5], [0.2, 0.3], 1.0, 1.2) == pytest.approx((0.3, 0.0), abs=1e-14)


@settings(max_examples=60, deadline=None)
@given(
    knots=st.lists(st.tuples(st.floats(-0.5, 1.5), st.floats(-1.0, 1.0)), min_size=1, max_size=12,
                   unique_by=lambda k: round(k[0], 6)),
    start=st.floats(-0.2, 0.8),
    span=st.floats(0.01, 0.6),
)
def test_interval_line_is_the_least_squares_line_of_the_interpolant(knots, start, span):
    """Mean = (1/T) int y dt and slope = 12/T^3 int (t - c) y dt of the held linear interpolant (1e-9)."""
    knots = sorted(knots)
    times, values = [k[0] for k in knots], [k[1] for k in knots]
    end = start + span
    centre = 0.5 * (start + end)
    breaks = [t for t in times if start < t < end]
    signal = lambda t: float(np.interp(t, times, values))  # noqa: E731
    area = quad(signal, start, end, points=breaks or None, epsabs=1e-13, epsrel=1e-13, limit=200)[0]
    moment = quad(lambda t: (t - centre) * signal(t), start, end, points=breaks or None, epsabs=1e-13,
                  epsrel=1e-13, limit=200)[0]
    mean, slope = interval_line(times, values, start, end)
    assert mean == pytest.approx(area / span, abs=1e-9)
    assert slope == pytest.approx(12.0 * moment / span**3, abs=1e-9 / span)


def test_steering_ramp_reaches_the_epoch():
    """A steering ramp sampled at 50 Hz: each epoch carries the interval mean and the ramp's slope."""
    times, east, north, yaw, _ = circle()
    samples = [s for s in motion_samples(times, east, north, yaw) if s[0] != "steering"]
    steering = [("steering", t, (0.01 + 0.02 * t,)) for t in np.arange(0.0, 10.0 + 1e-9, 0.02)]
    ordered = sorted(samples + steering, key=lambda s: (s[1], s[0] != "steering"))
    epochs, rejected = run(ordered)
    assert not rejected
    for epoch in epochs:
        assert epoch.steering == pytest.approx(0.01 + 0.02 * (epoch.t - 0.1), abs=1e-12)
        assert epoch.steering_rate == pytest.approx(0.02, rel=1e-9)


# --------------------------------------------------------------------------- bad input (DESIGN.md section 6)


def clean_stream():
    times, east, north, yaw, _ = circle(duration=4.0)
    return motion_samples(times, east, north, yaw)


def insert_after(samples, predicate, extra):
    """Insert ``extra`` right after the first sample matching ``predicate``."""
    for i, sample in enumerate(samples):
        if predicate(sample):
            return samples[: i + 1] + [extra] + samples[i + 1:]
    raise AssertionError("no sample matched")


def at(topic, stamp):
    return lambda s: s[0] == topic and abs(s[1] - stamp) < 1e-9


NAN, INF = float("nan"), float("inf")
BAD_SAMPLES = {
    # name: (inserted after, bad sample, expected topic, words the reason must contain)
    "nan velocity": (at("heading", 1.0), ("velocity", 1.1, (NAN, 0.5)), "velocity", ("non-finite",)),
    "inf velocity": (at("heading", 1.0), ("velocity", 1.1, (0.5, -INF)), "velocity", ("non-finite",)),
    "nan velocity stamp": (at("heading", 1.0), ("velocity", NAN, (0.5, 0.5)), "velocity", ("non-finite",)),
    "nan heading": (at("heading", 1.0), ("heading", 1.1, (NAN,)), "heading", ("non-finite",)),
    "inf heading": (at("heading", 1.0), ("heading", 1.1, (INF,)), "heading", ("non-finite",)),
    "nan steering": (at("heading", 1.0), ("steering", 1.01, (NAN,)), "steering", ("non-finite",)),
    "reversed velocity": (at("heading", 1.0), ("velocity", 0.8, (0.5, 0.5)), "velocity", ("stamp",)),
    "reversed heading": (at("heading", 1.0), ("heading", 0.6, (0.1,)), "heading", ("stamp",)),
    "duplicate velocity": (at("heading", 1.0), ("velocity", 1.0, (0.5, 0.5)), "velocity", ("stamp",)),
    "duplicate heading": (at("heading", 1.0), ("heading", 1.0, (0.1,)), "heading", ("stamp",)),
    "duplicate steering": (at("steering", 1.0), ("steering", 1.0, (0.3,)), "steering", ("stamp",)),
    "reversed steering": (at("steering", 1.0), ("steering", 0.5, (0.05,)), "steering", ("stamp",)),
    "steering beyond limit": (at("heading", 1.0), ("steering", 1.01, (0.75,)), "steering", ("max_steering",)),
    "negative steering beyond limit": (at("heading", 1.0), ("steering", 1.01, (-0.9,)), "steering",
                                       ("max_steering",)),
}


@pytest.mark.parametrize("name", list(BAD_SAMPLES))
def test_bad_sample_is_rejected_and_changes_nothing(name):
    """The bad sample yields no epoch and one Rejection with its topic and reason; every epoch is as without it."""
    after, bad, topic, words = BAD_SAMPLES[name]
    expected, rejected = run(clean_stream())
    assert not rejected
    assembler = EpochAssembler(AssemblerSettings())
    adders = {"velocity": assembler.add_velocity, "heading": assembler.add_heading,
              "steering": assembler.add_steering}
    epochs = []
    for sample in insert_after(clean_stream(), after, bad):
        produced = adders[sample[0]](sample[1], *sample[2])
        if sample is bad:
            assert produced == []
        epochs.extend(produced)
    rejections = assembler.drain_rejections()
    assert len(rejections) == 1, rejections
    rejection = rejections[0]
    assert rejection.topic == topic
    assert rejection.stamp == bad[1] or (math.isnan(bad[1]) and math.isnan(rejection.stamp))
    for word in words:
        assert word in rejection.reason, rejection.reason
    assert assembler.drain_rejections() == []
    # the assembler kept working: the same epochs as the clean stream, to the bit
    assert epochs == expected


def test_duplicate_gnss_sample_before_its_pair_is_reported():
    """A velocity sample repeated before its heading arrives is rejected, not silently dropped."""
    samples = insert_after(clean_stream(), at("velocity", 1.0), ("velocity", 1.0, (0.5, 0.5)))
    expected, _ = run(clean_stream())
    epochs, rejections = run(samples)
    assert epochs == expected
    assert [(r.topic, r.stamp) for r in rejections] == [("velocity", 1.0)]
    assert "stamp" in rejections[0].reason


def test_missing_heading_bridges_the_interval():
    """A velocity whose heading never arrives gives no epoch; the next epoch spans both intervals correctly."""
    samples = [s for s in clean_stream() if not (s[0] == "heading" and abs(s[1] - 1.0) < 1e-9)]
    expected, _ = run(clean_stream())
    epochs, _ = run(samples)
    assert [e.t for e in epochs] == [e.t for e in expected if abs(e.t - 1.0) > 1e-9]
    bridged = next(e for e in epochs if abs(e.t - 1.2) < 1e-9)  # spans [0.8, 1.2]
    assert bridged.yaw_rate == pytest.approx(math.hypot(2.0, -0.08) / 5.0, abs=1e-9)
    assert bridged.lateral_velocity == pytest.approx(-0.08, abs=1e-9)


def test_missing_steering_rejects_the_epoch_then_recovers():
    times, east, north, yaw, _ = circle(duration=4.0)
    samples = [s for s in motion_samples(times, east, north, yaw) if not (s[0] == "steering" and s[1] < 2.0)]
    epochs, rejections = run(samples)
    assert rejections and all(r.topic == "epoch" and "steering" in r.reason for r in rejections)
    assert all(r.stamp < 2.0 for r in rejections)
    assert len(epochs) >= 9 and all(e.t >= 2.0 for e in epochs)
    assert all(e.steering == pytest.approx(0.05) for e in epochs)


def test_heading_quaternions_are_checked_before_conversion() -> None:
    """Non-finite and zero-norm orientations are rejected with their reason; valid ones give their yaw."""
    assembler = EpochAssembler(AssemblerSettings())
    assert assembler.add_heading_quaternion(1.0, 0.0, 0.0, math.inf, 1.0) == []
    assert assembler.add_heading_quaternion(1.1, 0.0, 0.0, 0.0, 0.0) == []
    reasons = [r.reason for r in assembler.drain_rejections()]
    assert reasons[0].startswith("non-finite orientation quaternion")
    assert reasons[1] == "orientation quaternion of zero norm"
    assert math.isnan(quaternion_yaw(0.0, 0.0, 0.0, 0.0)) and math.isnan(quaternion_yaw(0.0, 0.0, math.nan, 1.0))
    yaw = 2.5
    assert quaternion_yaw(0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)) == pytest.approx(yaw, abs=1e-12)
    assembler.add_velocity(2.0, 1.0, 0.0)
    assembler.add_heading_quaternion(2.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
    assert assembler.drain_rejections() == []


@pytest.mark.parametrize(("wait", "uncovered"), [(0.0, 4), (0.25, 3)])
def test_epochs_formed_before_the_steering_covered_them_are_counted(wait: float, uncovered: int) -> None:
    """An epoch formed before a steering sample at or after its end arrived is counted.

    It goes once a GNSS epoch more than ``steering_wait`` later has come (0: the next one); a
    clean stream counts none.
    """
    times, east, north, yaw, _ = circle(duration=2.0)
    clean = EpochAssembler(AssemblerSettings(steering_wait=wait))
    assemble(clean, motion_samples(times, east, north, yaw))
    assert clean.uncovered_epochs == 0
    short = EpochAssembler(AssemblerSettings(steering_wait=wait))  # the steering stops after t = 1.0 s
    epochs = assemble(short, [s for s in motion_samples(times, east, north, yaw)
                              if not (s[0] == "steering" and s[1] > 1.0 + 1e-9)])
    # wait 0: 1.2, 1.4, 1.6 and 1.8 each went when the next GNSS epoch came (2.0 still waits);
    # wait 0.25: 1.2, 1.4 and 1.6 went when the epoch 0.4 s later came (1.8 and 2.0 still wait)
    assert short.uncovered_epochs == uncovered
    assert [round(e.t, 1) for e in epochs][-2:] == [1.2, 1.4]  # the rest had no recent steering at all


@pytest.mark.parametrize("rate", [5.0, 10.0, 20.0])
def test_a_steering_stream_that_lags_the_gnss_by_less_than_the_wait_changes_nothing(rate: float) -> None:
    """Steering samples that arrive up to 0.15 s after the GNSS of the same instant give the in-order epochs.

    With no wait (an epoch goes when the next GNSS epoch comes) the same lag leaves epochs uncovered
    at 10 and 20 Hz GNSS, formed with the steering held over the end of their interval.
    """
    times, east, north, yaw, _ = circle(duration=4.0, rate=rate)
    in_order = motion_samples(times, east, north, yaw, steering=0.0)
    steering = [(t, 0.05 * math.sin(2.0 * t)) for t in np.arange(0.0, times[-1] + 0.01, 0.02)]
    in_order = [s for s in in_order if s[0] != "steering"]
    lag = 0.15

    def feed(arrival_lag: float) -> list[tuple[str, float, tuple[float, ...]]]:
        keyed = [(s[1], 1, s) for s in in_order] + [(t + arrival_lag, 0, ("steering", t, (a,))) for t, a in steering]
        return [sample for *_, sample in sorted(keyed, key=lambda item: (item[0], item[1]))]

    reference = EpochAssembler(AssemblerSettings())
    expected = assemble(reference, feed(0.0))
    assert reference.uncovered_epochs == 0 and len(expected) >= 4.0 * rate - 2
    lagged = EpochAssembler(AssemblerSettings())
    got = assemble(lagged, feed(lag))
    assert lagged.uncovered_epochs == 0
    assert got[:len(expected) - 3] == expected[:len(expected) - 3]  # the last ones still wait for their steering
    impatient = EpochAssembler(AssemblerSettings(steering_wait=0.0))
    hurried = assemble(impatient, feed(lag))
    if rate > 5.0:  # one GNSS period (0.1, 0.05 s) is shorter than the lag
        assert impatient.uncovered_epochs > len(hurried) // 2
        assert any(a.steering != b.steering for a, b in zip(hurried, expected, strict=False))
