"""The `replay` command end to end: real MCAP bags, the console scripts run as subprocesses."""

from __future__ import annotations

import csv
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
from helpers import run_command as run
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.rosbag2 import Reader, StoragePlugin
from rosbags.rosbag2 import Writer as RosbagsWriter
from rosbags.typesys import Stores, get_typestore

from transplanter_ident.evaluation.metrics import CSV_COLUMNS
from transplanter_ident.files import Progress
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.simulator import simulate

ROOT = Path(__file__).resolve().parents[1]
TS = get_typestore(Stores.ROS2_JAZZY)  # independent of bag_io's own typestore object
T = TS.types
TOLERANCE = 0.06  # the foundation's identification tolerance, each of Cf and Cr


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    return rows[0], np.array(rows[1:], dtype=float)


def assert_clean_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    assert result.returncode != 0
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("replay: error: "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.fixture(scope="module")
def sine_bag(tmp_path_factory) -> Path:
    bag = tmp_path_factory.mktemp("sim") / "sine"
    result = run("simulate", "-o", bag, "--scenario", "sine", "--seed", "1")
    assert result.returncode == 0, result.stderr
    return bag


@pytest.fixture(scope="module")
def sine_csv(sine_bag: Path, tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("csv") / "sine.csv"
    result = run("replay", sine_bag, "--csv", out)
    assert result.returncode == 0, result.stderr
    return out, result


def test_round_trip_identifies_the_stiffness(sine_csv) -> None:
    path, result = sine_csv
    header, rows = read_csv(path)
    assert header == list(CSV_COLUMNS)
    assert header == ["t", "vx", "vy_meas", "r_meas", "delta", "vy_model", "r_model", "cf", "cr", "cf_std",
                      "cr_std", "steering_offset", "valid"]
    assert rows.shape == (600, 13)
    assert set(np.unique(rows[:, 12])) == {0.0, 1.0} and rows[-1, 12] == 1.0  # valid: not at first, at the end
    assert abs(rows[-1, 11]) < 0.002  # the simulated drive has no steering offset (rad)
    assert np.all(np.diff(rows[:, 0]) > 0)
    cf, cr = rows[-1, 7], rows[-1, 8]
    assert abs(cf / 8000.0 - 1.0) < TOLERANCE, cf
    assert abs(cr / 10000.0 - 1.0) < TOLERANCE, cr
    out = result.stdout
    assert "Max err vy" in out and "Mean err r" in out and "EKF" in out
    assert "Stiffness error vs ground truth" in out and "final Cf" in out
    assert "Rejected samples: none" in out


def test_output_bag_matches_csv(sine_bag: Path, tmp_path: Path) -> None:
    out_bag, out_csv = tmp_path / "out", tmp_path / "out.csv"
    result = run("replay", sine_bag, "-o", out_bag, "--csv", out_csv)
    assert result.returncode == 0, result.stderr
    _, rows = read_csv(out_csv)
    with Reader(out_bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        stiffness = [(t, TS.deserialize_cdr(d, c.msgtype)) for c, t, d in reader.messages()
                     if c.topic == "/estimator/cornering_stiffness"]
        model = [TS.deserialize_cdr(d, c.msgtype) for c, _, d in reader.messages()
                 if c.topic == "/estimator/model_output"]
    assert types == {"/estimator/cornering_stiffness": "geometry_msgs/msg/Vector3Stamped",
                     "/estimator/cornering_stiffness_std": "geometry_msgs/msg/Vector3Stamped",
                     "/estimator/model_output": "geometry_msgs/msg/TwistStamped",
                     "/estimator/measurement": "geometry_msgs/msg/TwistStamped"}
    assert len(stiffness) == len(rows)
    log_ns, last = stiffness[-1]
    assert last.header.stamp.sec * 10**9 + last.header.stamp.nanosec == log_ns
    assert log_ns / 1e9 == pytest.approx(rows[-1, 0], abs=1e-6)
    assert last.vector.x == pytest.approx(rows[-1, 7], rel=1e-9)
    assert model[-1].twist.linear.y == pytest.approx(rows[-1, 5], rel=1e-9, abs=1e-12)
    again = run("replay", sine_bag, "-o", out_bag)
    assert_clean_error(again, "already exists")


# --------------------------------------------------------------------------- independent writers


def _events(result, start_ns: int):
    """(log_ns, topic, msgtype, msg) in the order simulate writes them: steering, then GNSS, then truth."""
    header = T["std_msgs/msg/Header"]
    stamp = T["builtin_interfaces/msg/Time"]
    v3, quat = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]

    def hdr(ns: int, frame: str):
        return header(stamp=stamp(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    events = []
    for t, angle in zip(result.steering_time, result.steering, strict=True):
        ns = start_ns + round(t * 1e9)
        msg = T["sensor_msgs/msg/JointState"](header=hdr(ns, ""), name=["front_steering"],
                                              position=np.array([angle]), velocity=np.zeros(0), effort=np.zeros(0))
        events.append((ns, 0, "/steering_angle", "sensor_msgs/msg/JointState", msg))
    for i, t in enumerate(result.gnss_time):
        ns = start_ns + round(t * 1e9)
        east, north = result.velocity_enu[i]
        twist = T["geometry_msgs/msg/Twist"](linear=v3(x=east, y=north, z=0.0), angular=v3(x=0.0, y=0.0, z=0.0))
        events.append((ns, 1, "/gnss/vel", "geometry_msgs/msg/TwistStamped",
                       T["geometry_msgs/msg/TwistStamped"](header=hdr(ns, "gnss_link"), twist=twist)))
        yaw = float(result.heading[i])
        events.append((ns, 2, "/gnss/heading", "geometry_msgs/msg/QuaternionStamped",
                       T["geometry_msgs/msg/QuaternionStamped"](
                           header=hdr(ns, "gnss_link"),
                           quaternion=quat(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw)))))
        events.append((ns, 3, "/sim/cornering_stiffness", "geometry_msgs/msg/Vector3Stamped",
                       T["geometry_msgs/msg/Vector3Stamped"](
                           header=hdr(ns, "base_link"),
                           vector=v3(x=result.truth_cf[i], y=result.truth_cr[i], z=0.0))))
    events.sort(key=lambda e: (e[0], e[1]))
    return events


def _write_with_mcap_library(path: Path, events) -> None:
    with open(path, "wb") as handle:
        writer = McapWriter(handle, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="test_replay")
        schemas: dict[str, int] = {}
        channels: dict[str, int] = {}
        for seq, (ns, _, topic, msgtype, msg) in enumerate(events):
            if msgtype not in schemas:
                text, _ = TS.generate_msgdef(msgtype, ros_version=2)
                schemas[msgtype] = writer.register_schema(name=msgtype, encoding="ros2msg", data=text.encode())
            if topic not in channels:
                channels[topic] = writer.register_channel(topic=topic, message_encoding="cdr",
                                                          schema_id=schemas[msgtype])
            writer.add_message(channels[topic], log_time=ns, data=bytes(TS.serialize_cdr(msg, msgtype)),
                               publish_time=ns, sequence=seq)
        writer.finish()


def _write_with_rosbags_writer(path: Path, events) -> None:
    with RosbagsWriter(path, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for ns, _, topic, msgtype, msg in events:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=TS)
            writer.write(connections[topic], ns, TS.serialize_cdr(msg, msgtype))


def test_bags_from_other_writers_give_the_same_numbers(tmp_path: Path) -> None:
    ours = tmp_path / "ours"
    made = run("simulate", "-o", ours, "--scenario", "sine", "--duration", "40", "--seed", "7")
    assert made.returncode == 0, made.stderr
    result = simulate(build_config("sine", duration=40.0, seed=7))
    events = _events(result, start_ns=1_700_000_000 * 10**9)
    single_file = tmp_path / "by_mcap.mcap"
    _write_with_mcap_library(single_file, events)
    directory = tmp_path / "by_rosbags"
    _write_with_rosbags_writer(directory, events)

    outputs = {}
    for name, bag in (("ours", ours), ("mcap", single_file), ("rosbags", directory)):
        out = tmp_path / f"{name}.csv"
        replayed = run("replay", bag, "--csv", out)
        assert replayed.returncode == 0, replayed.stderr
        outputs[name] = (out.read_text(), replayed.stdout.splitlines()[1:5])
    assert outputs["mcap"] == outputs["ours"]
    assert outputs["rosbags"] == outputs["ours"]
    assert len(outputs["ours"][0].splitlines()) == 1 + 200  # header + 200 epochs from 201 GNSS samples


# --------------------------------------------------------------------------- parameters


def test_layered_params_file_changes_the_result(sine_bag: Path, sine_csv, tmp_path: Path) -> None:
    base_csv = sine_csv[0]
    override = tmp_path / "noisy.yaml"
    override.write_text("estimator:\n  ros__parameters:\n    ekf:\n"
                        "      process_noise: [1.0e-4, 1.0e-4, 1.0e-4, 1.0e-4]\n")
    layered = tmp_path / "layered.csv"
    result = run("replay", sine_bag, "--params-file", ROOT / "config" / "estimator.yaml", "--params-file", override,
                 "--csv", layered)
    assert result.returncode == 0, result.stderr
    defaults = tmp_path / "defaults.csv"
    assert run("replay", sine_bag, "--params-file", ROOT / "config" / "estimator.yaml", "--csv",
               defaults).returncode == 0
    assert defaults.read_text() == base_csv.read_text()  # the file holds the built-in defaults
    _, base = read_csv(base_csv)
    _, changed = read_csv(layered)
    assert base.shape == changed.shape
    np.testing.assert_array_equal(base[:, :5], changed[:, :5])  # same measurements
    assert abs(changed[-1, 7] - base[-1, 7]) > 1.0  # different stiffness


def test_bad_params_file(sine_bag: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("estimator:\n  ros__parameters:\n    ekf:\n      process_noise: [1.0, -2.0]\n")
    assert_clean_error(run("replay", sine_bag, "--params-file", bad), "bad.yaml", "process_noise")


# --------------------------------------------------------------------------- bad bags


@pytest.fixture()
def short_bag(tmp_path: Path) -> Path:
    bag = tmp_path / "short"
    assert run("simulate", "-o", bag, "--duration", "20").returncode == 0
    return bag


def test_missing_topic(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    assert run("simulate", "-o", bag, "--duration", "10", "--steering-topic", "/elsewhere").returncode == 0
    assert_clean_error(run("replay", bag), "no topic /steering_angle", "topics.steering")


def test_truncated_mcap(short_bag: Path) -> None:
    mcap = short_bag / "short.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    assert_clean_error(run("replay", short_bag), str(short_bag), "truncated or corrupt")
    assert_clean_error(run("replay", mcap), str(mcap), "truncated or corrupt")


def test_empty_bag(tmp_path: Path) -> None:
    bag = tmp_path / "empty"
    with RosbagsWriter(bag, version=9, storage_plugin=StoragePlugin.MCAP):
        pass
    assert_clean_error(run("replay", bag), "empty")
    empty_file = tmp_path / "zero.mcap"
    empty_file.write_bytes(b"")
    assert_clean_error(run("replay", empty_file), "empty")


def test_wrong_message_type(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with RosbagsWriter(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection("/gnss/vel", "std_msgs/msg/Float64", typestore=TS)
        writer.write(conn, 1, TS.serialize_cdr(T["std_msgs/msg/Float64"](data=1.0), "std_msgs/msg/Float64"))
        conn = writer.add_connection("/gnss/heading", "std_msgs/msg/Float64", typestore=TS)
        writer.write(conn, 1, TS.serialize_cdr(T["std_msgs/msg/Float64"](data=1.0), "std_msgs/msg/Float64"))
    assert_clean_error(run("replay", bag), "/gnss/vel", "std_msgs/msg/Float64", "TwistStamped")


def test_nonexistent_path(tmp_path: Path) -> None:
    assert_clean_error(run("replay", tmp_path / "nope"), "no such file or directory")


def test_debug_shows_the_traceback(tmp_path: Path) -> None:
    result = run("replay", tmp_path / "nope", "--debug")
    assert result.returncode != 0
    assert "Traceback" in result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith("replay: error: ")


def test_unwritable_csv_leaves_nothing(sine_bag: Path, tmp_path: Path) -> None:
    target = tmp_path / "missing_dir" / "out.csv"
    assert_clean_error(run("replay", sine_bag, "--csv", target), "does not exist")
    assert not (tmp_path / "missing_dir").exists()


def test_rejected_samples_are_summarised(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    # a 30 deg steer with a 0.5 rad limit: every steering sample past the ramp is rejected
    assert run("simulate", "-o", bag, "--scenario", "step30-cw", "--duration", "20").returncode == 0
    params = tmp_path / "p.yaml"
    params.write_text("estimator:\n  ros__parameters:\n    vehicle:\n      max_steering: 0.5\n")
    result = run("replay", bag, "--params-file", params)
    assert result.returncode == 0, result.stderr
    assert "steering: beyond max_steering 0.500" in result.stdout


# --------------------------------------------------------------------------- progress


class _Stream:
    def __init__(self, tty: bool) -> None:
        self.lines: list[str] = []
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty

    def write(self, text: str) -> None:
        self.lines.extend(line for line in text.splitlines() if line)

    def flush(self) -> None:
        pass


@pytest.mark.parametrize(("total", "tty", "expected"), [(5_000, True, 0), (50_000, False, 0), (50_000, True, 11),
                                                         (200_000, False, 11)])
def test_progress_reports_every_ten_percent(total: int, tty: bool, expected: int) -> None:
    stream = _Stream(tty)
    progress = Progress(total, "reading", stream=stream)
    for count in range(1, total + 1):
        progress.update(count)
    progress.done()
    assert len(stream.lines) == expected
    if expected:
        assert stream.lines[0].startswith("reading:  10 %") and stream.lines[-1].startswith("reading: done")
