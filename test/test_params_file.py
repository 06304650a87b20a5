"""Tests of transplanter_ident.config.params_file: loading, layering, errors, writing, and the real rcl parser."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

import transplanter_ident.files as cli_util
from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, NoiseParams, VehicleParams
from transplanter_ident.config.params_file import (
    EstimatorParams,
    FrameConfig,
    ParamsError,
    SteeringConfig,
    TopicConfig,
    flat_to_params,
    load_params,
    params_to_flat,
    read_params_file,
)
from transplanter_ident.config.params_writer import write_params_yaml
from transplanter_ident.config.safe_yaml import SEALED_FIRST_LINE, SEALED_LAST_LINE
from transplanter_ident.config.schema import PARAMS
from transplanter_ident.files import OutputError

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_FILE = ROOT / "config" / "estimator.yaml"


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _ekf_file(tmp_path: Path, body: str, name: str = "p.yaml") -> Path:
    return _write(tmp_path / name, f"estimator:\n  ros__parameters:\n{body}")


def _tuned() -> EstimatorParams:
    """Parameters with every section changed from its default."""
    return EstimatorParams(
        config=EstimatorConfig(
            vehicle=VehicleParams(mass=650.0, lf=0.8, lr=0.5, iz=300.0, antenna_x=0.5, antenna_y=-0.1),
            options=FilterOptions(
                discretization="euler",
                stiffness_state="linear",
                measurement="yaw_rate",
                min_speed=0.5,
                stiffness_bounds=(10.0, 5.0e5),
                max_gated=7,
            ),
            noise=NoiseParams(
                process_noise=(2.0e-4, 3.0e-5, 1.0, 0.0),
                measurement_noise=(1.0e-3, 2.5e-7),
                initial_stiffness=(8000.0, 10000.0),
            ),
        ),
        topics=TopicConfig(velocity="/rtk/vel", heading="/rtk/heading", steering="/joint_states"),
        frames=FrameConfig(velocity="ned", heading="ned"),
        steering=SteeringConfig(joint_name="steer joint"),
        extra={"diagnostics.stale_timeout": 2.5, "use_sim_time": True},
    )


def test_default_file_equals_dataclass_defaults() -> None:
    params = load_params([DEFAULT_FILE])
    assert params.config == EstimatorConfig()
    assert params == EstimatorParams(extra={"diagnostics.stale_timeout": 1.0})


def test_default_file_writes_every_number_as_float() -> None:
    def walk(node: object) -> None:
        if isinstance(node, dict):
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)
        else:
            assert not isinstance(node, int) or isinstance(node, bool), f"integer {node!r} in {DEFAULT_FILE}"

    walk(yaml.safe_load(DEFAULT_FILE.read_text()))


def test_second_file_overrides_only_its_keys(tmp_path: Path) -> None:
    override = _ekf_file(tmp_path, "    ekf:\n      process_noise: [1.0e-3, 2.0e-3, 3.0e-3, 4.0e-3]\n")
    params = load_params([DEFAULT_FILE, override])
    assert params.config.noise.process_noise == (1.0e-3, 2.0e-3, 3.0e-3, 4.0e-3)
    expected = params_to_flat(load_params([DEFAULT_FILE]))
    expected["ekf.process_noise"] = [1.0e-3, 2.0e-3, 3.0e-3, 4.0e-3]
    assert params_to_flat(params) == expected


def test_wildcard_and_node_sections(tmp_path: Path) -> None:
    path = _write(
        tmp_path / "w.yaml",
        (
            "/**:\n  ros__parameters:\n    vehicle: {mass: 500.0, lf: 1.0}\n"
            "estimator:\n  ros__parameters:\n    vehicle: {mass: 600.0}\n"
            "other_node:\n  ros__parameters:\n    vehicle: {mass: 1.0}\n"
        ),
    )
    vehicle = load_params([path]).config.vehicle
    assert (vehicle.mass, vehicle.lf) == (600.0, 1.0)
    assert load_params([path], node_name="other_node").config.vehicle.mass == 1.0


def test_ints_and_exponent_notation_are_read_as_floats(tmp_path: Path) -> None:
    path = _ekf_file(tmp_path, "    ekf:\n      process_noise: [1.0, 1e-4, 0.0, 2.0]\n"
                     "      initial_stiffness: [8000, 9000]\n    vehicle: {mass: 700}\n")
    params = load_params([path])
    assert params.config.noise.process_noise == (1.0, 1.0e-4, 0.0, 2.0)
    assert params.config.noise.initial_stiffness == (8000.0, 9000.0)
    assert all(type(v) is float for v in (*params.config.noise.process_noise, *params.config.noise.initial_stiffness))
    assert type(params.config.vehicle.mass) is float


@pytest.mark.parametrize("values", ["[1, 1e-4, 0, 2]", "[1.0e-4, 1.0e-4, 1.0e-6, 0]"])
def test_a_list_mixing_ints_and_floats_is_refused_as_the_node_refuses_it(tmp_path: Path, values: str) -> None:
    """The rcl parser refuses such a list (the node cannot start); offline refuses it too, naming file and key."""
    path = _ekf_file(tmp_path, f"    ekf:\n      process_noise: {values}\n")
    with pytest.raises(ParamsError, match="mixes integers and floats") as info:
        load_params([path])
    assert info.value.key == "ekf.process_noise"
    assert str(info.value).startswith(f"{path}: ekf.process_noise mixes")
    assert "\n" not in str(info.value)


BAD_CASES = {
    "unparsable": ("estimator: [unclosed\n", "invalid YAML"),
    "not_a_mapping": ("- estimator\n- ekf\n", "top level must be a mapping"),
    "no_node_section": ("someone_else:\n  ros__parameters: {a: 1.0}\n", "estimator"),
    "no_ros_parameters": ("estimator:\n  ekf: {min_speed: 1.0}\n", "ros__parameters"),
    "wrong_length": ("    ekf:\n      process_noise: [1.0e-4, 1.0e-4, 1.0e-6]\n", "ekf.process_noise"),
    "not_a_list": ("    ekf:\n      measurement_noise: 1.0\n", "ekf.measurement_noise"),
    "non_numeric": ("    ekf:\n      measurement_noise: [4.0e-4, abc]\n", "ekf.measurement_noise"),
    "bool_entry": ("    ekf:\n      initial_stiffness: [true, 1000.0]\n", "ekf.initial_stiffness"),
    "negative_noise": (
        "    ekf:\n      process_noise: [1.0e-4, -1.0e-4, 1.0e-6, 1.0e-6]\n",
        "ekf.process_noise",
    ),
    "zero_meas_noise": ("    ekf:\n      measurement_noise: [0.0, 1.0e-5]\n", "ekf.measurement_noise"),
    "nan_noise": ("    ekf:\n      heading_process_noise: .nan\n", "ekf.heading_process_noise"),
    "bad_discretization": ("    ekf:\n      discretization: rk4\n", "ekf.discretization"),
    "bad_measurement": ("    ekf:\n      measurement: yawrate\n", "ekf.measurement"),
    "bounds_length": ("    ekf:\n      stiffness_bounds: [1.0, 2.0, 3.0]\n", "ekf.stiffness_bounds"),
    "bounds_order": ("    ekf:\n      stiffness_bounds: [2.0, 1.0]\n", "ekf.stiffness_bounds"),
    "max_gated_float": ("    ekf:\n      max_gated: 2.5\n", "ekf.max_gated"),
    "unknown_ekf_key": ("    ekf:\n      proces_noise: [1.0, 1.0, 1.0, 1.0]\n", "ekf.proces_noise"),
    "unknown_vehicle_key": ("    vehicle:\n      mas: 700.0\n", "vehicle.mas"),
    "negative_mass": ("    vehicle:\n      mass: -720.0\n", "vehicle.mass"),
    "string_mass": ("    vehicle:\n      mass: heavy\n", "vehicle.mass"),
    "empty_value": ("    vehicle:\n      lf:\n", "vehicle.lf"),
    "bad_frame": ("    frames: {velocity: xyz}\n", "frames.velocity"),
    "empty_topic": ("    topics: {heading: ''}\n", "topics.heading"),
}


@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_file_gives_one_line_error_naming_file_and_key(tmp_path: Path, case: str) -> None:
    text, expected = BAD_CASES[case]
    if text.startswith("    "):
        path = _ekf_file(tmp_path, text)
    else:
        path = _write(tmp_path / "p.yaml", text)
    with pytest.raises(ParamsError) as info:
        load_params([DEFAULT_FILE, path])
    message = str(info.value)
    assert "\n" not in message
    assert str(path) in message
    assert expected in message


def test_missing_file_is_named(tmp_path: Path) -> None:
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ParamsError, match=re.escape(str(missing))) as info:
        load_params([DEFAULT_FILE, missing])
    assert "\n" not in str(info.value)


def test_error_in_overridden_file_is_still_reported(tmp_path: Path) -> None:
    bad = _ekf_file(tmp_path, "    ekf:\n      process_noise: [1.0]\n", "bad.yaml")
    good = _ekf_file(tmp_path, "    ekf:\n      process_noise: [1.0, 1.0, 1.0, 1.0]\n", "good.yaml")
    with pytest.raises(ParamsError, match=re.escape(str(bad))):
        load_params([bad, good])


def test_flat_round_trip() -> None:
    tuned = _tuned()
    flat = params_to_flat(tuned)
    assert flat["ekf.process_noise"] == [2.0e-4, 3.0e-5, 1.0, 0.0]
    assert flat_to_params(flat) == tuned
    assert flat_to_params({}) == EstimatorParams()
    assert flat_to_params(params_to_flat(EstimatorParams())) == EstimatorParams()


def test_write_read_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "tuned.yaml"
    write_params_yaml(path, params_to_flat(_tuned()), "bag: x.mcap\nobjective: nll, fitness 1.5")
    text = path.read_text()
    assert text.startswith(f"{SEALED_FIRST_LINE}\n# bag: x.mcap\n# objective: nll, fitness 1.5\nestimator:\n"
                           "  ros__parameters:\n")
    assert text.endswith(f"\n{SEALED_LAST_LINE}\n")  # the seal: a file cut short is refused (issue #14)
    assert load_params([path]) == _tuned()
    # Every number is a float except the integer parameters (kind "int" in the schema).
    integers = {key.rsplit(".", 1)[-1] for key, row in PARAMS.items() if row.kind == "int"}
    assert "max_gated" in integers
    for line in text.splitlines():
        if line.lstrip().startswith("#") or line.strip().split(":", 1)[0] in integers:
            continue
        value = line.split(":", 1)[1]
        assert not re.search(r"(?<![\w.\-+])-?\d+(?![\w.])", value), line
    assert "max_gated: 7\n" in text
    assert "process_noise: [0.0002, 3.0e-05, 1.0, 0.0]" in text


def test_written_subset_layers_over_defaults(tmp_path: Path) -> None:
    path = tmp_path / "tuned.yaml"
    flat = {
        "ekf.process_noise": [1, 2, 3, 4],
        "ekf.measurement_noise": [1e-6, 2e-6],
        "ekf.measurement": "heading",
    }
    write_params_yaml(path, flat, "tuned")
    params = load_params([DEFAULT_FILE, path])
    assert params.config.noise.process_noise == (1.0, 2.0, 3.0, 4.0)
    assert params.config.noise.measurement_noise == (1e-6, 2e-6)
    assert params.config.vehicle == VehicleParams()


def test_writer_rejects_invalid_values_and_writes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    with pytest.raises(ParamsError, match="ekf.process_noise"):
        write_params_yaml(path, {"ekf.process_noise": [1.0, -1.0, 1.0, 1.0]}, "bad")
    assert list(tmp_path.iterdir()) == []


def test_atomic_writer_leaves_no_temp_file_on_failure(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    flat = params_to_flat(EstimatorParams())
    directory = tmp_path / "is_a_dir"
    directory.mkdir()
    with pytest.raises((OSError, OutputError)):
        write_params_yaml(directory, flat, "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["is_a_dir"]
    assert list(directory.iterdir()) == []

    with pytest.raises((OSError, OutputError)):
        write_params_yaml(tmp_path / "missing_dir" / "p.yaml", flat, "x")

    target = _write(tmp_path / "keep.yaml", "old content\n")

    def failing_replace(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(cli_util.os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        write_params_yaml(target, flat, "x")
    assert target.read_text() == "old content\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["is_a_dir", "keep.yaml"]


_RCL_SCRIPT = """
import json, sys
import rclpy
from rclpy.node import Node

args = ["--ros-args"]
for path in sys.argv[1:]:
    args += ["--params-file", path]
rclpy.init(args=args)
try:
    node = Node("estimator", automatically_declare_parameters_from_overrides=True)
    out = {}
    for name, param in node.get_parameters_by_prefix("").items():
        value = param.value
        if isinstance(value, (str, bool, int, float)):
            out[name] = {"value": value, "types": type(value).__name__}
        else:
            out[name] = {"value": list(value), "types": [type(v).__name__ for v in value]}
    node.destroy_node()
finally:
    rclpy.shutdown()
print(json.dumps(out))
"""


def _isolated_command() -> list[str]:
    """`unshare -n` with loopback up when this user may create a network namespace, else nothing."""
    unshare, ip = shutil.which("unshare"), shutil.which("ip")
    if unshare and ip:
        wrapper = [unshare, "-n", "sh", "-c", f'{ip} link set lo up && exec "$0" "$@"']
        if subprocess.run([*wrapper, "true"], capture_output=True, timeout=10).returncode == 0:
            return wrapper
    return []


def _rcl_parameters(paths: list[Path]) -> dict[str, dict]:
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=str(60 + os.getpid() % 40),
        RMW_IMPLEMENTATION="rmw_fastrtps_cpp",
    )
    command = [*_isolated_command(), sys.executable, "-c", _RCL_SCRIPT, *map(str, paths)]
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_written_file_is_accepted_by_rcl_parser(tmp_path: Path) -> None:
    pytest.importorskip("rclpy")
    tuned = tmp_path / "tuned.yaml"
    flat = params_to_flat(_tuned())
    write_params_yaml(tuned, flat, "written by the test")
    subset = tmp_path / "subset.yaml"
    write_params_yaml(subset, {"ekf.process_noise": [1, 2, 3, 4]}, "subset")

    seen = _rcl_parameters([tuned])
    for key, value in flat.items():
        assert seen[key]["value"] == value, key
    assert seen["ekf.process_noise"]["types"] == ["float"] * 4
    assert seen["ekf.max_gated"]["types"] == "int"

    layered = _rcl_parameters([DEFAULT_FILE, subset])
    expected = params_to_flat(load_params([DEFAULT_FILE, subset]))
    assert layered["ekf.process_noise"]["value"] == [1.0, 2.0, 3.0, 4.0]
    file_keys = set(read_params_file(DEFAULT_FILE)) | set(read_params_file(subset))
    assert file_keys <= set(layered)
    for key in file_keys:
        assert layered[key]["value"] == expected[key], key


def test_node_only_message_type_keys_are_accepted_offline(tmp_path) -> None:  # noqa: ANN001
    """A params file written for the node (with topics.*_type) loads in replay and tuner too."""
    path = tmp_path / "node.yaml"
    path.write_text("estimator:\n  ros__parameters:\n    topics:\n      velocity_type: TwistWithCovarianceStamped\n"
                    "      velocity: /fix/vel\n")
    params = load_params([path])
    assert params.topics.velocity == "/fix/vel"
    assert params.extra["topics.velocity_type"] == "TwistWithCovarianceStamped"
    path.write_text("estimator:\n  ros__parameters:\n    topics:\n      velocty: /typo\n")
    with pytest.raises(ParamsError, match="topics.velocty"):
        load_params([path])
