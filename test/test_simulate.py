"""The `simulate` command and the scenarios: real MCAP bags, the console script run as a subprocess."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from helpers import run_command as run
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from transplanter_ident.epochs.frames import wrap_angle
from transplanter_ident.sim.scenarios import SCENARIOS, build_config
from transplanter_ident.sim.simulator import SensorNoise, SimConfig, simulate

ROOT = Path(__file__).resolve().parents[1]
TS = get_typestore(Stores.ROS2_JAZZY)


def topics(bag: Path) -> dict[str, tuple[str, int]]:
    with Reader(bag) as reader:
        return {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}


def messages(bag: Path, topic: str) -> list:
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [TS.deserialize_cdr(d, c.msgtype) for c, _, d in reader.messages(connections=conns)]


REQUIRED = ("step20-ccw", "step30-cw", "sine", "surface-change")


def test_scenarios_are_data() -> None:
    assert set(REQUIRED) <= set(SCENARIOS)
    for name, scenario in SCENARIOS.items():
        config = scenario.build(scenario.default_duration)
        assert isinstance(config, SimConfig), name
        assert scenario.description


def test_scenario_physics() -> None:
    t = np.linspace(0.0, 90.0, 901)
    step20 = build_config("step20-ccw")
    assert step20.speed == pytest.approx(1.0)
    assert np.max(step20.steering(t)) == pytest.approx(math.radians(20.0))
    step30 = build_config("step30-cw")
    assert np.min(step30.steering(t)) == pytest.approx(-math.radians(30.0))
    assert step30.stiffness.front[0] < step20.stiffness.front[0]  # field: lower stiffness
    sine = build_config("sine")
    assert sine.speed == 2.0 and np.max(np.abs(sine.steering(t))) == pytest.approx(math.radians(15.0), rel=1e-3)
    change = build_config("surface-change", duration=100.0)
    cf, cr = change.stiffness.at(np.array([10.0, 90.0]))
    assert cf[1] < 0.6 * cf[0] and cr[1] < 0.6 * cr[0]
    assert build_config("sine", tire="saturating").tire == "saturating"
    lever = build_config("sine", antenna_x=0.5, gnss_rate=10.0, seed=4)
    assert lever.vehicle.antenna_x == 0.5 and lever.gnss_rate == 10.0 and lever.seed == 4
    with pytest.raises(ValueError, match="unknown scenario"):
        build_config("nope")


def test_default_bag_has_the_pinned_topics_and_truth(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    result = run("simulate", "-o", bag, "--scenario", "step20-ccw", "--duration", "30")
    assert result.returncode == 0, result.stderr
    assert "wrote" in result.stdout
    assert topics(bag) == {
        "/gnss/vel": ("geometry_msgs/msg/TwistStamped", 151),
        "/gnss/heading": ("geometry_msgs/msg/QuaternionStamped", 151),
        "/steering_angle": ("sensor_msgs/msg/JointState", 1501),
        "/sim/cornering_stiffness": ("geometry_msgs/msg/Vector3Stamped", 151),
        "/sim/body_velocity": ("geometry_msgs/msg/TwistStamped", 151),
    }
    joint = messages(bag, "/steering_angle")[-1]
    assert list(joint.name) == ["front_steering"]
    assert joint.position[0] == pytest.approx(math.radians(20.0), abs=0.01)  # left: positive
    truth = messages(bag, "/sim/cornering_stiffness")[-1]
    assert (truth.vector.x, truth.vector.y) == (8000.0, 10000.0)
    body = messages(bag, "/sim/body_velocity")[-1]
    assert body.twist.linear.x == pytest.approx(1.0) and body.twist.angular.z > 0.2  # counter-clockwise


def test_alternative_types_frames_and_topics(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    result = run("simulate", "-o", bag, "--duration", "10", "--velocity-type", "twist-cov", "--heading-type", "imu",
                 "--steering-type", "float64", "--velocity-frame", "ned", "--heading-frame", "ned",
                 "--velocity-topic", "/fix/vel", "--no-truth", "--gnss-rate", "10", "--steering-rate", "20",
                 "--tire", "saturating", "--antenna-x", "0.5")
    assert result.returncode == 0, result.stderr
    assert "vehicle.antenna_x 0.5" in result.stdout and "frames.velocity ned" in result.stdout
    assert topics(bag) == {
        "/fix/vel": ("geometry_msgs/msg/TwistWithCovarianceStamped", 101),
        "/gnss/heading": ("sensor_msgs/msg/Imu", 101),
        "/steering_angle": ("std_msgs/msg/Float64", 201),
    }
    heading = messages(bag, "/gnss/heading")[0]
    q = heading.orientation
    compass = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y**2 + q.z**2))
    assert compass == pytest.approx(math.pi / 2, abs=0.02)  # ENU yaw 0 (east) is compass 90 deg


def test_seed_reproducible_and_compression(tmp_path: Path) -> None:
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    for bag, extra in ((a, []), (b, []), (c, ["--compress"])):
        assert run("simulate", "-o", bag, "--duration", "20", "--seed", "5", *extra).returncode == 0
    assert (a / "a.mcap").read_bytes().replace(b"a.mcap", b"") == (b / "b.mcap").read_bytes().replace(b"b.mcap", b"")
    assert (c / "c.mcap").stat().st_size < 0.6 * (a / "a.mcap").stat().st_size
    assert [m.position[0] for m in messages(a, "/steering_angle")] == [
        m.position[0] for m in messages(c, "/steering_angle")]


def test_existing_output_needs_force(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    assert run("simulate", "-o", bag, "--duration", "5").returncode == 0
    again = run("simulate", "-o", bag, "--duration", "5")
    assert again.returncode != 0 and "already exists" in again.stderr and "Traceback" not in again.stderr
    forced = run("simulate", "-o", bag, "--duration", "8", "--force")
    assert forced.returncode == 0, forced.stderr
    assert topics(bag)["/gnss/vel"][1] == 41
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]


@pytest.mark.parametrize("args", [("--duration", "-1"), ("--speed", "0"), ("--gnss-rate", "nan")])
def test_bad_options_are_one_line_errors(tmp_path: Path, args: tuple[str, str]) -> None:
    result = run("simulate", "-o", tmp_path / "bag", *args)
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and result.stderr.startswith("simulate: error: ")
    assert not (tmp_path / "bag").exists()


def test_unknown_scenario_is_a_usage_error(tmp_path: Path) -> None:
    result = run("simulate", "-o", tmp_path / "bag", "--scenario", "nope")
    assert result.returncode == 2 and "invalid choice" in result.stderr


def test_imperfection_flags_write_a_late_offset_gnss_first_bag(tmp_path: Path) -> None:
    """--steering-offset, --gnss-delay and --gnss-first shape the bag as they say (test_real_sensors.py uses them)."""
    bag = tmp_path / "imperfect"
    result = run("simulate", "-o", bag, "--scenario", "stiffness-drop", "--duration", "30", "--seed", "2",
                 "--steering-offset", "0.01", "--gnss-delay", "0.08", "--gnss-first")
    assert result.returncode == 0, result.stderr
    velocity = messages(bag, "/gnss/vel")
    truth = messages(bag, "/sim/cornering_stiffness")
    late = [(v.header.stamp.sec - t.header.stamp.sec) * 1e9 + v.header.stamp.nanosec - t.header.stamp.nanosec
            for v, t in zip(velocity, truth, strict=True)]
    assert np.allclose(late, 0.08e9, atol=2.0)  # every GNSS message 80 ms after the motion it describes
    steering = [m.position[0] for m in messages(bag, "/steering_angle")]
    plain = tmp_path / "plain"
    assert run("simulate", "-o", plain, "--scenario", "stiffness-drop", "--duration", "30",
               "--seed", "2").returncode == 0
    reference = [m.position[0] for m in messages(plain, "/steering_angle")]
    np.testing.assert_allclose(np.array(steering) - np.array(reference), 0.01, atol=1e-12)
    with Reader(bag) as reader:  # at equal log times the GNSS message comes first
        order = [(c.topic, t) for c, t, _ in reader.messages()]
    first_tie = next(i for i in range(1, len(order)) if order[i][1] == order[i - 1][1]
                     and {order[i][0], order[i - 1][0]} == {"/gnss/heading", "/steering_angle"})
    assert order[first_tie][0] == "/steering_angle"


def _headings(bag: Path) -> np.ndarray:
    return np.array([2.0 * math.atan2(m.quaternion.z, m.quaternion.w) for m in messages(bag, "/gnss/heading")])


def _steering(bag: Path) -> np.ndarray:
    return np.array([m.position[0] for m in messages(bag, "/steering_angle")])


@pytest.mark.parametrize(("flags", "change", "read", "simulated", "apart"), [
    (("--gnss-correlation-time", "2"), lambda c: replace(c, noise=SensorNoise(correlation_time=2.0)), _headings,
     lambda r: r.heading, 1e-4),  # Gauss-Markov errors (test_sim.py)
    (("--relaxation-length", "0.3"), lambda c: replace(c, relaxation_length=0.3), _headings,
     lambda r: r.heading, 1e-3),  # tires lagging their slip
    (("--steering-scale", "1.03"), lambda c: replace(c, steering_scale=1.03), _steering,
     lambda r: r.steering, 1e-3),  # the steering sensor's gain error
    (("--steering-play", "0.005"), lambda c: replace(c, steering_play=0.005), _steering,
     lambda r: r.steering, 2e-3),  # the steering linkage's play: the sensor 2.5 mrad ahead of the wheels
], ids=["gnss-correlation-time", "relaxation-length", "steering-scale", "steering-play"])
def test_an_imperfection_flag_gives_the_simulators_drive(tmp_path: Path, flags, change, read, simulated,  # noqa: ANN001
                                                         apart: float) -> None:
    """The bag's headings (or steering angles) are the simulator's with the imperfection, and differ from without."""
    bag = tmp_path / "imperfect"
    result = run("simulate", "-o", bag, "--scenario", "sine", "--duration", "20", "--seed", "3", *flags)
    assert result.returncode == 0, result.stderr
    config = build_config("sine", duration=20.0, seed=3)
    recorded = read(bag)
    np.testing.assert_allclose(wrap_angle(recorded - simulated(simulate(change(config)))), 0.0, atol=1e-9)
    assert np.max(np.abs(wrap_angle(recorded - simulated(simulate(config))))) > apart


@pytest.mark.parametrize(("flag", "field"), [("--relaxation-length", "relaxation_length"),
                                             ("--steering-scale", "steering_scale")])
def test_a_bad_imperfection_value_is_refused(tmp_path: Path, flag: str, field: str) -> None:
    refused = run("simulate", "-o", tmp_path / "bad", flag, "-1")
    assert refused.returncode != 0 and field in refused.stderr
