"""Tests of the `estimator` node over real Fast DDS, loopback only (DESIGN.md sections 3, 4, 6).

Each ROS test runs the installed ``estimator`` as a separate process next to a driver process
that publishes and listens, both in one fresh network namespace with their own ROS_DOMAIN_ID
(test/ros_harness.py). The test process itself never starts rclpy.
"""

from __future__ import annotations

import ast
import csv
import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import ros_harness
from ros_harness import ROOT, estimator_command, isolated, ros_env, run_scenario, stamp_fields

import transplanter_ident.bags as bag_io
from transplanter_ident.config.parameters import NoiseParams
from transplanter_ident.config.params_file import (
    EstimatorParams,
    ParamsError,
    params_to_flat,
    read_params_file,
)
from transplanter_ident.ekf.joint_ekf import JointEKF
from transplanter_ident.ekf.layout import StepStatus
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler
from transplanter_ident.epochs.frames import quaternion_yaw
from transplanter_ident.evaluation.health import should_publish
from transplanter_ident.sim.signals import sine_steering
from transplanter_ident.sim.simulator import SimConfig, simulate

CONFIG = ROOT / "config" / "estimator.yaml"
VEL, HEAD, STEER = "/gnss/vel", "/gnss/heading", "/steering_angle"
TWIST, QUAT, JOINT = "geometry_msgs/msg/TwistStamped", "geometry_msgs/msg/QuaternionStamped", \
    "sensor_msgs/msg/JointState"
OUT_TYPES = {"stiffness": ("/estimator/cornering_stiffness", "geometry_msgs/msg/Vector3Stamped"),
             "std": ("/estimator/cornering_stiffness_std", "geometry_msgs/msg/Vector3Stamped"),
             "model": ("/estimator/model_output", TWIST),
             "measurement": ("/estimator/measurement", TWIST),
             "offset": ("/estimator/steering_offset", "geometry_msgs/msg/Vector3Stamped"),
             "valid": ("/estimator/cornering_stiffness_valid", "std_msgs/msg/Bool")}
DIAGNOSTICS = ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
PUBLISH_TYPES = [[VEL, TWIST], [HEAD, QUAT], [STEER, JOINT]]


# --------------------------------------------------------------------------- messages and references


def velocity_spec(t: float, east: float, north: float) -> dict[str, Any]:
    return {"topic": VEL, "type": TWIST, "fields": {**stamp_fields(t), "twist.linear.x": east,
                                                    "twist.linear.y": north}}


def heading_spec(t: float, yaw: float) -> dict[str, Any]:
    x, y, z, w = bag_io.yaw_quaternion(yaw)
    return {"topic": HEAD, "type": QUAT, "fields": {**stamp_fields(t), "quaternion.x": x, "quaternion.y": y,
                                                    "quaternion.z": z, "quaternion.w": w}}


def steering_spec(t: float, angle: float, joint: str = "front_steering") -> dict[str, Any]:
    return {"topic": STEER, "type": JOINT, "fields": {**stamp_fields(t), "name": [joint], "position": [angle]}}


def spec_stamp(spec: dict[str, Any]) -> float:
    f = spec["fields"]
    return bag_io.seconds(f["header.stamp.sec"] * bag_io.NS_PER_S + f["header.stamp.nanosec"])


def sim_stream(config: SimConfig, t0: float) -> list[tuple[float, int, dict[str, Any]]]:
    """(time, order, spec) of a simulated run in bag order: steering, then velocity, then heading."""
    result = simulate(config)
    items = []
    for t, angle in zip(result.steering_time.tolist(), result.steering.tolist(), strict=True):
        items.append((t0 + t, 0, steering_spec(t0 + t, angle)))
    for t, (east, north), yaw in zip(result.gnss_time.tolist(), result.velocity_enu.tolist(),
                                     result.heading.tolist(), strict=True):
        items.append((t0 + t, 1, velocity_spec(t0 + t, east, north)))
        items.append((t0 + t, 2, heading_spec(t0 + t, yaw)))
    items.sort(key=lambda item: (item[0], item[1]))
    return items


VELOCITY_FIELDS = {TWIST: "twist.linear", "geometry_msgs/msg/TwistWithCovarianceStamped": "twist.twist.linear"}
ORIENTATION_FIELDS = {QUAT: "quaternion", "sensor_msgs/msg/Imu": "orientation"}
CLOCK = "rosgraph_msgs/msg/Clock"


def specs_to_samples(specs: list[dict[str, Any]], joint: str = "front_steering",
                     rotate: float = 0.0) -> list[tuple[str, float, tuple[float, ...]]]:
    """The offline view of published messages: bag_io's conversions (stamp ns / 1e9, quaternion yaw).

    Orientation quaternions with a non-finite or zero-norm component are dropped, as the node
    does; std_msgs/Float64 (Float32: rounded) steering takes the last /clock time (the node's ROS time). ``rotate``
    turns the ENU frame by that angle (velocity and heading), for a twin run.
    """
    samples = []
    c, s = math.cos(rotate), math.sin(rotate)
    clock = 0.0
    for spec in specs:
        f = spec["fields"]
        if spec["type"] == CLOCK:
            clock = bag_io.seconds(f["clock.sec"] * bag_io.NS_PER_S + f["clock.nanosec"])
        elif spec["type"] == "std_msgs/msg/Float64":
            samples.append(("steering", clock, (f["data"],)))
        elif spec["type"] == "std_msgs/msg/Float32":
            samples.append(("steering", clock, (float(np.float32(f["data"])),)))
        elif spec["type"] in VELOCITY_FIELDS:
            prefix = VELOCITY_FIELDS[spec["type"]]
            east, north = f[f"{prefix}.x"], f[f"{prefix}.y"]
            samples.append(("velocity", spec_stamp(spec), (c * east - s * north, s * east + c * north)))
        elif spec["type"] in ORIENTATION_FIELDS:
            prefix = ORIENTATION_FIELDS[spec["type"]]
            q = tuple(f[f"{prefix}.{axis}"] for axis in "xyzw")
            if not all(math.isfinite(v) for v in q) or sum(v * v for v in q) < 1e-12:
                continue
            samples.append(("heading", spec_stamp(spec), (quaternion_yaw(*q) + rotate,)))
        elif joint in f["name"]:
            samples.append(("steering", spec_stamp(spec), (f["position"][f["name"].index(joint)],)))
    return samples


def offline_outputs(samples: list, params: EstimatorParams, noise_switch: dict[int, NoiseParams] | None = None,
                    resets: tuple[int, ...] = ()) -> list[dict[str, float]]:
    """What the node should publish: EpochAssembler + JointEKF over the samples, published statuses only.

    ``noise_switch``: sample index -> new noise applied before that sample; ``resets``: sample
    indices before which filter and assembler restart.
    """
    assembler = EpochAssembler(AssemblerSettings.from_params(params))
    ekf = JointEKF(params.config)
    adders = {"velocity": assembler.add_velocity, "heading": assembler.add_heading,
              "steering": assembler.add_steering}
    rows = []
    for index, (topic, stamp, values) in enumerate(samples):
        if noise_switch and index in noise_switch:
            ekf.set_noise(noise_switch[index])
        if index in resets:
            ekf.reset()
            assembler.reset()
        for epoch in adders[topic](stamp, *values):
            est = ekf.step(epoch)
            if should_publish(est.status):
                rows.append({"t": epoch.t, "status": est.status, "cf": est.cornering_stiffness_front,
                             "cr": est.cornering_stiffness_rear, "cf_std": est.cornering_stiffness_front_std,
                             "cr_std": est.cornering_stiffness_rear_std, "vy_model": est.lateral_velocity_model,
                             "r_model": est.yaw_rate_model, "vx": epoch.longitudinal_velocity,
                             "vy_meas": epoch.lateral_velocity, "r_meas": epoch.yaw_rate})
    return rows


def online_outputs(records: dict[str, list]) -> list[dict[str, float]]:
    """The node's output topics joined per epoch (they are published together, in order)."""
    stiff, std, model, meas, offset, valid = (records[k] for k in ("stiffness", "std", "model", "measurement",
                                                                   "offset", "valid"))
    assert len({len(x) for x in (stiff, std, model, meas, offset, valid)}) == 1, [len(x) for x in (stiff, std)]
    rows = []
    for a, b, c, d, e, f in zip(stiff, std, model, meas, offset, valid, strict=True):
        stamps = {json.dumps(m["msg"]["header"]["stamp"]) for m in (a, b, c, d, e)}
        assert len(stamps) == 1, stamps
        stamp = a["msg"]["header"]["stamp"]
        rows.append({"t": bag_io.seconds(stamp["sec"] * bag_io.NS_PER_S + stamp["nanosec"]),
                     "cf": a["msg"]["vector"]["x"], "cr": a["msg"]["vector"]["y"],
                     "cf_std": b["msg"]["vector"]["x"], "cr_std": b["msg"]["vector"]["y"],
                     "vy_model": c["msg"]["twist"]["linear"]["y"], "r_model": c["msg"]["twist"]["angular"]["z"],
                     "vx": d["msg"]["twist"]["linear"]["x"], "vy_meas": d["msg"]["twist"]["linear"]["y"],
                     "r_meas": d["msg"]["twist"]["angular"]["z"], "steering_offset": e["msg"]["vector"]["x"],
                     "correlation": b["msg"]["vector"]["z"], "valid": float(f["msg"]["data"])})
    return rows


COLUMNS = ("cf", "cr", "cf_std", "cr_std", "vy_model", "r_model", "vx", "vy_meas", "r_meas")


def max_relative_difference(online: list[dict], reference: list[dict], columns: tuple[str, ...] = COLUMNS,
                            floor: float = 1e-9) -> float:
    """Largest |a - b| / max(|b|, floor) over the columns; stamps must agree to 2 us."""
    assert len(online) == len(reference), (len(online), len(reference))
    worst = 0.0
    for a, b in zip(online, reference, strict=True):
        assert abs(a["t"] - b["t"]) < 2e-6, (a["t"], b["t"])
        for key in columns:
            worst = max(worst, abs(a[key] - b[key]) / max(abs(b[key]), floor))
    return worst


def assert_all_finite(records: dict[str, list]) -> None:
    for key in OUT_TYPES:
        for item in records.get(key, []):
            msg = item["msg"]
            if "data" in msg:
                continue  # std_msgs/Bool
            values = list(msg["vector"].values()) if "vector" in msg else [
                *msg["twist"]["linear"].values(), *msg["twist"]["angular"].values()]
            assert all(math.isfinite(v) for v in values), (key, msg)


def record_spec(*, diagnostics: bool = False) -> dict[str, list[str]]:
    spec = {key: list(value) for key, value in OUT_TYPES.items()}
    if diagnostics:
        spec["diagnostics"] = list(DIAGNOSTICS)
    return spec


# --------------------------------------------------------------------------- without ROS middleware


def test_every_params_file_key_is_declared() -> None:
    from transplanter_ident.ros.parameters import NODE_PARAMETERS, parameter_defaults

    declared = parameter_defaults()
    assert set(params_to_flat(EstimatorParams())) <= set(declared)
    assert set(read_params_file(CONFIG)) <= set(declared)
    assert {"topics.velocity_type", "topics.heading_type", "topics.steering_type", "diagnostics.stale_timeout",
            "diagnostics.converged_rel_std"} <= set(NODE_PARAMETERS)
    assert declared["diagnostics.stale_timeout"] == 1.0 and declared["diagnostics.converged_rel_std"] == 0.05
    for name, value in declared.items():  # rcl cannot type mixed or empty lists
        if isinstance(value, list):
            assert value and all(isinstance(v, float) for v in value), name


def test_descriptors_read_only_and_ranges() -> None:
    from transplanter_ident.ros.parameters import descriptor_for, is_read_only, parameter_defaults

    defaults = parameter_defaults()
    for name in ("topics.velocity", "topics.steering_type", "frames.heading", "vehicle.mass", "vehicle.lf",
                 "steering.joint_name", "ekf.discretization", "ekf.stiffness_state", "ekf.measurement"):
        assert is_read_only(name), name
    for name in ("ekf.process_noise", "ekf.measurement_noise", "diagnostics.stale_timeout",
                 "diagnostics.converged_rel_std"):
        assert not is_read_only(name), name
    mass = descriptor_for("vehicle.mass", defaults["vehicle.mass"])
    assert mass.read_only and mass.floating_point_range[0].from_value > 0.0 and mass.description
    assert descriptor_for("ekf.max_gated", defaults["ekf.max_gated"]).integer_range


@pytest.mark.parametrize(("key", "value", "reason"), [
    ("ekf.process_noise", [1e-4, 1e-4, 1e-6], "4 entries"),
    ("ekf.process_noise", [1e-4, -1e-4, 1e-6, 1e-6], ">= 0"),
    ("ekf.process_noise", [1e-4, math.nan, 1e-6, 1e-6], "finite"),
    ("ekf.measurement_noise", [0.0, 1e-5], "> 0"),
    ("topics.velocity_type", "NavSatFix", "topics.velocity_type"),
    ("diagnostics.stale_timeout", -1.0, "stale_timeout"),
])
def test_validate_rejects_with_a_reason(key: str, value: Any, reason: str) -> None:
    from transplanter_ident.ros.parameters import parameter_defaults, validate

    flat = parameter_defaults()
    validate(flat)
    flat[key] = value
    with pytest.raises(ParamsError, match=reason):
        validate(flat)


def test_stamp_conversions_round_trip() -> None:
    """Node and bag reader share measurements.stamp_seconds; the node's inverse rounds to the nanosecond."""
    from transplanter_ident.epochs.frames import stamp_seconds
    from transplanter_ident.ros.adapters import seconds_to_stamp

    rng = np.random.default_rng(0)
    for sec, nanosec in zip(rng.integers(0, 2_000_000_000, 200).tolist(), rng.integers(0, 10**9, 200).tolist(),
                            strict=True):
        t = stamp_seconds(sec, nanosec)
        assert t == bag_io.seconds(sec * bag_io.NS_PER_S + nanosec)
        back = seconds_to_stamp(t)
        assert abs((back.sec - sec) * 1e9 + back.nanosec - nanosec) <= 256  # float64 resolution at 2e9 s


def test_launch_file_parses() -> None:
    path = ROOT / "launch" / "estimator.launch.py"
    tree = ast.parse(path.read_text(), filename=str(path))
    compile(tree, str(path), "exec")
    names = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in names
    text = path.read_text()
    for needle in ("get_package_share_directory", "estimator.yaml", "tuned_params", "executable=\"estimator\""):
        assert needle in text, needle


def test_bad_parameters_file_stops_the_node_with_a_reason(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("estimator:\n  ros__parameters:\n    ekf:\n      process_noise: [1.0e-4, 1.0e-4]\n")
    command = isolated(estimator_command("--params-file", str(CONFIG), "--params-file", str(bad)))
    result = subprocess.run(command, env=ros_env(ros_harness.domain_id()), capture_output=True, text=True,
                            timeout=60, cwd=ROOT)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "ekf.process_noise must have 4 entries" in result.stdout + result.stderr


# --------------------------------------------------------------------------- over DDS


def sample_bag(tmp_path: Path) -> Path:
    """A sample bag from bags/ when there is a small one, else a simulated 30 s sine run at 10 Hz GNSS."""
    for name in ("sine", "multisine", "surface-change"):
        candidate = ROOT / "bags" / name
        if (candidate / "metadata.yaml").is_file():
            with bag_io.open_reader(candidate) as reader:
                wanted = {VEL, HEAD, STEER}
                if sum(c.msgcount for c in reader.connections if c.topic in wanted) <= 8000:
                    return candidate
    from transplanter_ident.sim.scenarios import build_config

    path = tmp_path / "sine_bag"
    bag_io.write_sim_bag(simulate(build_config("sine", duration=30.0, gnss_rate=10.0)), path)
    return path


def bag_specs(bag: Path, params: EstimatorParams) -> list[dict[str, Any]]:
    """The bag's input messages in bag order, as dotted-field specs (original stamps and values)."""
    topics = {params.topics.velocity, params.topics.heading, params.topics.steering}
    specs = []
    with bag_io.open_reader(bag) as reader:
        connections = [c for c in reader.connections if c.topic in topics]
        for conn, _log_ns, data in reader.messages(connections=connections):
            msg = bag_io.TYPESTORE.deserialize_cdr(data, conn.msgtype)
            specs.append({"topic": conn.topic, "type": bag_io.normalize_msgtype(conn.msgtype),
                          "fields": _flatten_rosbags(msg)})
    return specs


def _flatten_rosbags(msg: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for field in dataclasses.fields(msg):
        if field.name.startswith("__"):  # rosbags' __msgtype__
            continue
        value = getattr(msg, field.name)
        key = prefix + field.name
        if dataclasses.is_dataclass(value):
            out.update(_flatten_rosbags(value, key + "."))
        elif isinstance(value, np.ndarray):
            out[key] = value.tolist()
        else:
            out[key] = list(value) if isinstance(value, list) else value
    return out


def replay_csv(bag: Path, tmp_path: Path) -> list[dict[str, float]]:
    """Run the `replay` command on the bag with the same parameters; its CSV rows."""
    script = Path(sys.executable).parent / "replay"
    command = [str(script)] if script.is_file() else [sys.executable, "-m", "transplanter_ident.cli.replay"]
    out = tmp_path / "replay.csv"
    result = subprocess.run([*command, str(bag), "--params-file", str(CONFIG), "--csv", str(out), "--quiet"],
                            capture_output=True, text=True, timeout=300, cwd=ROOT,
                            env={**ros_env(ros_harness.domain_id())})
    assert result.returncode == 0, result.stdout + result.stderr
    with out.open() as handle:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(handle)]


@pytest.mark.parametrize("executor", ["events", "single"])
def test_online_equals_offline(tmp_path: Path, executor: str) -> None:
    """The node fed a bag's messages (original stamps, bag order) publishes exactly replay's numbers.

    With either executor of ``estimator --executor``: the EventsExecutor (default) and rclpy's default one.
    """
    from transplanter_ident.ekf.joint_ekf import run_sequence
    from transplanter_ident.ekf.layout import (
        O_CF,
        O_CF_STD,
        O_CORRELATION,
        O_CR,
        O_CR_STD,
        O_OFFSET,
        O_STATUS,
    )
    from transplanter_ident.epochs.assembler import assemble
    from transplanter_ident.epochs.epoch import EpochArrays
    from transplanter_ident.evaluation.validity import decide_sequence

    params = EstimatorParams()
    bag = sample_bag(tmp_path)
    specs = bag_specs(bag, params)
    # what replay does: the bag's samples -> EpochAssembler -> run_sequence (full precision)
    epochs = EpochArrays(assemble(EpochAssembler(AssemblerSettings.from_params(params)), specs_to_samples(specs)))
    outputs = run_sequence(params.config, epochs)
    assert all(should_publish(StepStatus(int(s))) for s in outputs[:, O_STATUS]), "a clean bag publishes every epoch"
    expected = len(epochs)
    assert expected > 50

    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG)],
        "estimator_options": ["--executor", executor],
        "record": record_spec(),
        "publish_types": PUBLISH_TYPES,
        "steps": [{"publish": specs, "pace": 0.002}, {"wait_for": ["measurement", expected, 30.0]}, {"spin": 0.3}],
    }, timeout=240)
    assert result["alive"] and result["returncode"] == 0, result["log"]
    online = online_outputs(result["records"])
    assert len(online) == expected, f"{len(online)} of {expected} epochs published\n{result['log']}"
    assert_all_finite(result["records"])
    valid = decide_sequence(params.config, params.validity, epochs, outputs)
    exact = [{"t": t, "cf": row[O_CF], "cr": row[O_CR], "cf_std": row[O_CF_STD], "cr_std": row[O_CR_STD],
              "steering_offset": row[O_OFFSET], "correlation": row[O_CORRELATION], "valid": float(ok)}
             for t, row, ok in zip(epochs.t.tolist(), outputs, valid, strict=True)]
    worst_exact = max_relative_difference(online, exact, ("cf", "cr", "cf_std", "cr_std", "correlation"))
    assert worst_exact <= 1e-9
    assert [row["valid"] for row in online] == [row["valid"] for row in exact]  # the validity flag too
    assert any(row["valid"] for row in online) and not all(row["valid"] for row in online)
    assert max(abs(a["steering_offset"] - b["steering_offset"]) for a, b in zip(online, exact, strict=True)) <= 1e-12

    csv_rows = replay_csv(bag, tmp_path)  # the `replay` command itself, through bag_io
    worst_csv = max_relative_difference(online, csv_rows)
    print(f"\nonline vs replay CSV ({bag.name}, {len(specs)} messages, {expected} epochs): max relative "
          f"difference {worst_csv:.2e} (the CSV has 10 significant digits); vs run_sequence at full precision "
          f"{worst_exact:.2e}")
    assert worst_csv <= 1e-9
    assert [row["valid"] for row in csv_rows] == [row["valid"] for row in online]  # replay's CSV column `valid`


def test_a_burst_of_messages_is_queued_not_dropped(tmp_path: Path) -> None:
    """A bag's first messages sent at once, without a pause: every epoch, replay's numbers.

    The node's inputs hold ``adapters.INPUT_QUEUE_DEPTH`` messages; qos_profile_sensor_data's 5 would
    drop most of such a burst while the node is busy with the first epochs.
    """
    from transplanter_ident.ros.adapters import INPUT_QUEUE_DEPTH

    params = EstimatorParams()
    specs = bag_specs(sample_bag(tmp_path), params)
    start = spec_stamp(specs[0])
    burst = [spec for spec in specs if spec_stamp(spec) < start + 1.5]
    per_topic = {topic: sum(1 for spec in burst if spec["topic"] == topic) for topic in (VEL, HEAD, STEER)}
    assert 20 <= max(per_topic.values()) < INPUT_QUEUE_DEPTH, per_topic
    expected = offline_outputs(specs_to_samples(burst), params)
    assert len(expected) >= 5
    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG)],
        "record": record_spec(),
        "publish_types": PUBLISH_TYPES,
        "steps": [{"publish": burst, "pace": 0.0}, {"wait_for": ["measurement", len(expected), 30.0]}, {"spin": 0.3}],
    }, timeout=240)
    assert result["alive"] and result["returncode"] == 0, result["log"]
    online = online_outputs(result["records"])
    assert len(online) == len(expected), f"{len(online)} of {len(expected)} epochs published\n{result['log']}"
    assert max_relative_difference(online, expected) <= 1e-9


# --------------------------------------------------------------------------- bad input

BAD_T0 = 1000.0
CLEAN = 1.5  # s of clean data before and after each injection (> diagnostics.window)


def bad_input_plan() -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict[str, Any]]:
    """Scenario steps, every message in publish order, and per-case expectations.

    One continuous simulated drive (10 Hz GNSS, 50 Hz steering, heading oscillating across +-pi)
    is cut into phases; in each, after CLEAN seconds one kind of bad input is injected.
    """
    config = SimConfig(duration=60.0, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0), gnss_rate=10.0,
                       steering_rate=50.0, initial_heading=math.pi - 0.3, seed=3)
    stream = sim_stream(config, BAD_T0)
    cases: list[tuple[str, float, Any]] = [
        ("warm_up", 3.0, None),
        ("nan_velocity", 3.0, "nan_velocity"),
        ("inf_heading", 3.0, "inf_heading"),
        ("nan_inf_steering", 3.0, "nan_inf_steering"),
        ("reversed_stamps", 3.0, "reversed_stamps"),
        ("heading_wrap", 3.0, None),
        ("zero_speed", 3.5, "zero_speed"),
        ("negative_speed", 3.5, "negative_speed"),
        ("steering_limit", 3.0, "steering_limit"),
        ("silenced_steering", 4.5, "silenced_steering"),
        ("tail", 1.0, None),
    ]
    steps: list[dict[str, Any]] = []
    published: list[dict[str, Any]] = []
    start = BAD_T0
    for name, length, kind in cases:
        inject = start + (CLEAN if kind else length)
        end = start + length
        before = [item for item in stream if start <= item[0] < inject]
        after = [item for item in stream if inject <= item[0] < end]
        if kind:
            after = _inject(kind, after, inject)
        for part, label in ((before, f"{name}:start"), (after, f"{name}:inject")):
            steps.append({"mark": label})
            if part:
                base = part[0][0] if label.endswith("start") else inject
                specs = []
                for t, order, spec in part:
                    specs.append({**spec, "at": max(t - base, 0.0) + 0.003 * order})
                steps.append({"publish": specs})
                published.extend(part_spec for _, _, part_spec in part)
        start = end
    steps += [{"mark": "end"}, {"spin": 0.6}]
    return steps, published, {"t_end": start}


def _inject(kind: str, items: list, t: float) -> list:
    """Return ``items`` with the bad input of ``kind`` applied at or after time ``t``."""
    out = []
    gnss_at = min(time for time, order, _ in items if order > 0)
    steer_at = min(time for time, order, _ in items if order == 0)
    for time, order, spec in items:
        f = dict(spec["fields"])
        if kind == "nan_velocity" and order == 1 and time == gnss_at:
            f["twist.linear.x"] = math.nan
        elif kind == "inf_heading" and order == 2 and time == gnss_at:
            f["quaternion.z"] = math.inf
        elif kind == "nan_inf_steering" and order == 0 and steer_at <= time < steer_at + 0.03:
            f["position"] = [math.nan if time == steer_at else math.inf]
        elif kind in ("zero_speed", "negative_speed") and order == 1 and gnss_at <= time < gnss_at + 0.55:
            factor = 0.0 if kind == "zero_speed" else -1.0
            f["twist.linear.x"] *= factor
            f["twist.linear.y"] *= factor
        elif kind == "steering_limit" and order == 0 and steer_at <= time < steer_at + 0.1:
            f["position"] = [1.0]  # rad, beyond vehicle.max_steering = 0.7
        elif kind == "silenced_steering" and order == 0 and time < steer_at + 1.5:
            continue
        out.append((time, order, {**spec, "fields": f}))
        if kind == "reversed_stamps" and time == gnss_at and order == 2:
            old = time - 0.55
            out.append((time + 0.005, 1, velocity_spec(old, 2.0, 0.0)))
            out.append((time + 0.005, 2, heading_spec(old, 3.0)))
            out.append((time + 0.005, 0, steering_spec(old, 0.1)))
    return out


# (case, diagnostic status, level, text in its message) the node must report during the case
EXPECTED_DIAGNOSTICS = [
    ("nan_velocity", "estimator: velocity input", 1, "non-finite value"),
    ("inf_heading", "estimator: heading input", 1, "non-finite orientation quaternion"),
    ("nan_inf_steering", "estimator: steering input", 1, "non-finite value"),
    ("reversed_stamps", "estimator: velocity input", 1, "stamp not after"),
    ("reversed_stamps", "estimator: heading input", 1, "stamp not after"),
    ("reversed_stamps", "estimator: steering input", 1, "stamp not after"),
    ("zero_speed", "estimator: motion", 1, "low speed"),
    ("negative_speed", "estimator: motion", 1, "reversing"),
    ("steering_limit", "estimator: steering input", 1, "beyond max_steering"),
    ("silenced_steering", "estimator: steering input", 2, "stale"),
    ("silenced_steering", "estimator: measurements", 1, "no recent steering angle"),
]


def _diagnostics_between(records: list, start: float, end: float) -> list[dict[str, Any]]:
    return [status for item in records if start <= item["t"] <= end for status in item["msg"]["status"]]


def test_bad_input_is_reported_and_never_kills_or_poisons_the_node() -> None:
    steps, published, _ = bad_input_plan()
    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG), "-p", "diagnostics.period:=0.2",
                           "-p", "diagnostics.window:=1.0", "-p", "diagnostics.stale_timeout:=0.5"],
        "record": record_spec(diagnostics=True),
        "publish_types": PUBLISH_TYPES,
        "steps": steps,
    }, timeout=240)
    log = result["log"]
    assert result["alive"], f"the node died\n{log}"
    assert result["returncode"] == 0, log
    records, marks = result["records"], result["marks"]
    assert_all_finite(records)
    assert "Traceback" not in log, log

    # the node behaves exactly like the offline pipeline on the same (bad) messages
    params = EstimatorParams()
    online = online_outputs(records)
    reference = offline_outputs(specs_to_samples(published), params)
    assert max_relative_difference(online, reference) <= 1e-9

    # heading wraps at +-pi: no jump, the same numbers as a twin drive turned by -pi/2 (never near +-pi)
    yaws = [quaternion_yaw(s["fields"]["quaternion.x"], s["fields"]["quaternion.y"],
                                  s["fields"]["quaternion.z"], s["fields"]["quaternion.w"])
            for s in published if s["topic"] == HEAD and math.isfinite(s["fields"]["quaternion.z"])]
    wraps = sum(1 for a, b in zip(yaws, yaws[1:], strict=False) if abs(b - a) > math.pi)
    assert wraps >= 4
    twin = offline_outputs(specs_to_samples(published, rotate=-math.pi / 2), params)
    assert max_relative_difference(online, twin, ("cf", "cr", "cf_std", "cr_std"), floor=1.0) < 1e-6
    assert max(abs(row["r_meas"]) for row in online) < 1.5  # a missed unwrap gives 2 pi / 0.1 s = 63 rad/s

    # /diagnostics reports each case at the right level while it happens
    diagnostics = records["diagnostics"]
    summary: dict[str, list[str]] = {}
    windows = {case: (marks[f"{case}:inject"]["t"], marks[f"{case}:inject"]["t"] + CLEAN + 0.3)
               for case in dict.fromkeys(c for c, *_ in EXPECTED_DIAGNOSTICS)}
    windows["heading_wrap"] = (marks["heading_wrap:start"]["t"], marks["heading_wrap:inject"]["t"])
    for case, (start, end) in windows.items():
        seen = _diagnostics_between(diagnostics, start, end)
        summary[case] = sorted({f"{['OK', 'WARN', 'ERROR', 'STALE'][s['level']]} {s['name']}: {s['message']}"
                                for s in seen if s["level"] > 0
                                and s["name"] not in ("estimator: convergence", "estimator: excitation",
                                                      "estimator: identifiability")})
    print("\ndiagnostics per bad-input case (non-OK lines, convergence/excitation/identifiability omitted):")
    for case, lines in summary.items():
        print(f"  {case}:")
        for line in lines or ["(all OK)"]:
            print(f"    {line}")
    for case, name, level, text in EXPECTED_DIAGNOSTICS:
        start = marks[f"{case}:inject"]["t"]
        seen = _diagnostics_between(diagnostics, start, start + CLEAN + 0.5)
        hits = [s for s in seen if s["name"] == name and s["level"] == level and text in s["message"]]
        assert hits, f"{case}: no {name} at level {level} with '{text}'; saw {summary[case]}"
        if name.endswith(("input", "motion")):  # was OK just before the injection
            before = _diagnostics_between(diagnostics, marks[f"{case}:start"]["t"] + 1.2, start)
            assert before and all(s["level"] == 0 for s in before if s["name"] == name), (case, name, before)
    wrap_start, wrap_end = marks["heading_wrap:start"]["t"], marks["heading_wrap:inject"]["t"]
    during_wrap = _diagnostics_between(diagnostics, wrap_start + 1.2, wrap_end)
    assert during_wrap and all(s["level"] == 0 for s in during_wrap if s["name"].endswith("input"))
    final = [item for item in diagnostics if item["t"] <= marks["end"]["t"]][-1]["msg"]["status"]
    assert {s["name"]: s["level"] for s in final}["estimator: steering input"] == 0  # recovered
    # the windowed Fisher information (issue #11 item 2): a bound, its weak direction and the filter's ratio to it
    known = {v["key"]: v["value"] for v in next(s for s in final if s["name"] == "estimator: identifiability")["values"]}
    assert float(known["memory_s"]) == 60.0 and float(known["crb_weak_rel_std"]) > 0.0
    assert len(known["crb_weak_direction"].split()) == 2 and float(known["published_to_crb_cf"]) > 0.0


def test_a_publisher_of_another_type_is_named_in_diagnostics() -> None:
    """A Float64 publisher on the velocity topic never matches; /diagnostics names it, not just 'stale'."""
    wrong = [{"topic": VEL, "type": "std_msgs/msg/Float64", "fields": {"data": 1.0}, "at": 0.1 * i} for i in range(25)]
    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG), "-p", "diagnostics.period:=0.2",
                           "-p", "diagnostics.stale_timeout:=0.5"],
        "record": {"diagnostics": list(DIAGNOSTICS)},
        "publish_types": [[HEAD, QUAT], [STEER, JOINT]],  # one participant cannot have two types on VEL
        "steps": [{"publish": wrong}, {"spin": 0.5}],
    }, timeout=120)
    assert result["alive"] and result["returncode"] == 0, result["log"]
    velocity = [s for item in result["records"]["diagnostics"] for s in item["msg"]["status"]
                if s["name"] == "estimator: velocity input"]
    named = [s for s in velocity if s["level"] == 2 and "sends std_msgs/msg/Float64" in s["message"]]
    assert named, sorted({s["message"] for s in velocity})
    assert "stale: no message on /gnss/vel" in named[-1]["message"]
    assert "topics.velocity_type geometry_msgs/msg/TwistStamped" in named[-1]["message"]


# --------------------------------------------------------------------------- other message types, sim time


#: s from a step's /clock to its other messages (the node must have taken the clock first)
CLOCK_LEAD = 0.02


@pytest.mark.parametrize("steering_type", ["std_msgs/msg/Float64", "std_msgs/msg/Float32"])
def test_use_sim_time_other_message_types_and_a_looping_bag(steering_type: str) -> None:
    """TwistWithCovarianceStamped, Imu and Float64 (or Float32) steering on a /clock; the clock jumping back restarts.

    A Float64 has no stamp: the node takes its ROS time, the last /clock. So the drive goes out one
    10 Hz step at a time (/clock, the steering sample it stamps, the GNSS pair), and the next /clock
    only once the node has published that step's epoch, which it cannot form before it has taken the
    steering sample (a real-time schedule failed once under the suite's load: a stall of the node let
    the next /clock in first). Within a step the steering goes out CLOCK_LEAD after the /clock: two
    topics are two DDS readers, and 2 ms apart they once arrived the other way round under the suite's
    load (a sample stamped with the last step's clock is refused, its epoch never formed, and every
    later wait timed out; the steps now stop at the first, see ros_harness "stop_at_timeout").
    """
    config = SimConfig(duration=6.0, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0), gnss_rate=10.0,
                       steering_rate=10.0, seed=11)
    result = simulate(config)
    t0 = 1_700_000_000.0
    steering_times = result.steering_time.tolist()
    items = []
    for t, angle in zip(result.steering_time.tolist(), result.steering.tolist(), strict=True):
        ns = round((t0 + t) * 1e9)
        items.append((t, 0, {"topic": "/clock", "type": CLOCK,
                             "fields": {"clock.sec": ns // bag_io.NS_PER_S, "clock.nanosec": ns % bag_io.NS_PER_S}}))
        items.append((t, 1, {"topic": STEER, "type": steering_type, "fields": {"data": angle}}))
    for t, (east, north), yaw in zip(result.gnss_time.tolist(), result.velocity_enu.tolist(),
                                     result.heading.tolist(), strict=True):
        stamp = stamp_fields(t0 + t)
        items.append((t, 2, {"topic": VEL, "type": "geometry_msgs/msg/TwistWithCovarianceStamped",
                             "fields": {**stamp, "twist.twist.linear.x": east, "twist.twist.linear.y": north}}))
        x, y, z, w = bag_io.yaw_quaternion(yaw)
        items.append((t, 3, {"topic": HEAD, "type": "sensor_msgs/msg/Imu",
                             "fields": {**stamp, "orientation.x": x, "orientation.y": y, "orientation.z": z,
                                        "orientation.w": w}}))
    items.sort(key=lambda item: (item[0], item[1]))
    one_pass = [spec for _, _, spec in items]
    reference = offline_outputs(specs_to_samples(one_pass), EstimatorParams())
    assert len(reference) > 50
    steps = []
    for loop in range(2):  # the second pass makes the clock jump back
        for start, end in zip([-math.inf, *steering_times[1:]], [*steering_times[1:], math.inf], strict=True):
            messages = [spec for t, _, spec in items if start <= t < end]  # the step's /clock first
            step = [{**message, "at": 0.0 if message["topic"] == "/clock" else CLOCK_LEAD + 0.002 * k}
                    for k, message in enumerate(messages)]
            published = sum(row["t"] < t0 + end - 1e-6 for row in reference)
            steps += [{"publish": step},
                      {"wait_for": ["measurement", loop * len(reference) + published, 20.0]}]
    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG), "-p", "use_sim_time:=true",
                           "-p", "topics.velocity_type:=TwistWithCovarianceStamped", "-p", "topics.heading_type:=Imu",
                           "-p", f"topics.steering_type:={steering_type}"],
        "record": record_spec(),
        "publish_types": [["/clock", CLOCK], [VEL, "geometry_msgs/msg/TwistWithCovarianceStamped"],
                          [HEAD, "sensor_msgs/msg/Imu"], [STEER, steering_type]],
        "steps": [*steps, {"spin": 0.3}],
        "stop_at_timeout": True,
    }, timeout=240)
    assert result["alive"] and result["returncode"] == 0, result["log"]
    assert "timed_out" not in result["results"], (result["results"]["timed_out"], result["log"][-3000:])
    online = online_outputs(result["records"])
    assert max_relative_difference(online, reference + reference) <= 1e-9
    assert "ROS time jumped back" in result["log"]


# --------------------------------------------------------------------------- run-time parameters and reset


def test_parameters_at_run_time_and_reset() -> None:
    config = SimConfig(duration=36.0, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0), gnss_rate=10.0,
                       steering_rate=50.0, seed=5)
    specs = [spec for _, _, spec in sim_stream(config, 500.0)]
    first = [s for s in specs if spec_stamp(s) < 512.0]
    second = [s for s in specs if 512.0 <= spec_stamp(s) < 524.0]
    third = [s for s in specs if spec_stamp(s) >= 524.0]
    params = EstimatorParams()
    n1 = len(offline_outputs(specs_to_samples(first), params))
    n12 = len(offline_outputs(specs_to_samples(first + second), params))
    new_q = [1.0e-3, 1.0e-3, 1.0e-4, 1.0e-4]
    default_q = list(params.config.noise.process_noise)
    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG)],
        "record": record_spec(),
        "publish_types": PUBLISH_TYPES,
        "steps": [
            {"publish": first, "pace": 0.002}, {"wait_for": ["measurement", n1, 20.0]},
            {"set_parameters": {"ekf.process_noise": new_q}, "as": "valid"},
            {"get_parameters": ["ekf.process_noise"], "as": "after_valid"},
            {"set_parameters": {"ekf.process_noise": [1.0e-4, 1.0e-4, 1.0e-6]}, "as": "wrong_length"},
            {"set_parameters": {"ekf.process_noise": [1.0e-4, -1.0e-4, 1.0e-6, 1.0e-6]}, "as": "negative"},
            {"set_parameters": {"ekf.process_noise": [1.0e-4, math.nan, 1.0e-6, 1.0e-6]}, "as": "nan"},
            {"set_parameters": {"ekf.measurement_noise": [0.0, 1.2e-5]}, "as": "zero_r"},
            {"set_parameters": {"vehicle.mass": 800.0}, "as": "read_only"},
            {"set_parameters": {"diagnostics.converged_rel_std": -0.1}, "as": "bad_threshold"},
            {"get_parameters": ["ekf.process_noise", "vehicle.mass"], "as": "after_rejected"},
            {"publish": second, "pace": 0.002}, {"wait_for": ["measurement", n12, 20.0]},
            {"trigger": "/estimator/reset", "as": "reset"},
            {"publish": third, "pace": 0.002}, {"spin": 0.5},
        ],
    }, timeout=240)
    assert result["alive"] and result["returncode"] == 0, result["log"]
    res = result["results"]
    assert res["valid"] == [{"successful": True, "reason": ""}]
    assert res["after_valid"]["ekf.process_noise"] == new_q
    expected_reasons = {"wrong_length": "4 entries", "negative": ">= 0", "nan": "finite", "zero_r": "> 0",
                        "read_only": "read-only", "bad_threshold": "converged_rel_std"}
    for key, reason in expected_reasons.items():
        assert not res[key][0]["successful"], key
        assert reason in res[key][0]["reason"], (key, res[key][0]["reason"])
    assert res["after_rejected"] == {"ekf.process_noise": new_q, "vehicle.mass": 720.0}
    assert res["reset"]["success"]

    online = online_outputs(result["records"])
    samples = specs_to_samples(first + second + third)
    switch_at = len(specs_to_samples(first))
    reset_at = len(specs_to_samples(first + second))
    new_noise = dataclasses.replace(params.config.noise, process_noise=tuple(new_q))
    reference = offline_outputs(samples, params, noise_switch={switch_at: new_noise}, resets=(reset_at,))
    assert max_relative_difference(online, reference) <= 1e-9
    unchanged = offline_outputs(samples, params, resets=(reset_at,))
    effect = max(abs(a["cf_std"] / b["cf_std"] - 1.0) for a, b in zip(online[n1:n12], unchanged[n1:n12],
                                                                         strict=True))
    assert effect > 0.05, "the new process noise had no visible effect"
    assert default_q != new_q
    after_reset = online[n12]
    assert after_reset["cf"] == pytest.approx(params.config.noise.initial_stiffness[0], rel=1e-9)
    print(f"\nrun-time parameters: reasons {[res[k][0]['reason'] for k in expected_reasons]}; "
          f"Cf std changed by up to {100 * effect:.0f} % after the new Q; first Cf after ~/reset "
          f"{after_reset['cf']:.3f}")
