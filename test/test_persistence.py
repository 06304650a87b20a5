"""The learned stiffness kept across restarts (issue #11): over real DDS, with the node in its own process."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from ros_harness import ROOT, run_scenario
from test_node import CONFIG, DIAGNOSTICS, PUBLISH_TYPES, bag_specs, online_outputs, record_spec, sample_bag

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions
from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.ekf.joint_ekf import JointEKF
from transplanter_ident.ekf.layout import X_STEERING_GAIN
from transplanter_ident.ekf.persistence import (
    FORMAT_WITHOUT_GAIN,
    Keeper,
    LearnedState,
    PersistenceError,
    key_of,
    load,
    save,
)


def run_node(state: Path, specs: list, *, expected: int, stop_signal: str = "SIGINT") -> dict:
    return run_scenario({
        "estimator_args": ["--params-file", str(CONFIG), "-p", f"persistence.file:={state}",
                           "-p", "persistence.period:=1.0"],
        "record": {**record_spec(), "diagnostics": list(DIAGNOSTICS)},
        "publish_types": PUBLISH_TYPES,
        "steps": [{"publish": specs, "pace": 0.002}, {"wait_for": ["measurement", expected, 60.0]}, {"spin": 1.5}],
        "stop_signal": stop_signal,
    }, timeout=300)


def persistence_status(result: dict) -> str:
    statuses = [s for item in result["records"]["diagnostics"] for s in item["msg"]["status"]
                if s["name"].endswith("persistence")]
    return statuses[-1]["message"] if statuses else ""


@pytest.fixture(scope="module")
def first_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list, dict]:
    """Feed a whole sample drive (600 epochs, 120 s of data), then SIGTERM: the state is saved."""
    tmp = tmp_path_factory.mktemp("persist")
    specs = bag_specs(sample_bag(tmp), EstimatorParams())
    state = tmp / "state" / "estimator.yaml"
    epochs = sum(1 for s in specs if s["topic"] == "/gnss/vel") - 1
    result = run_node(state, specs, expected=epochs, stop_signal="SIGTERM")
    assert result["returncode"] == 0, result["log"]
    return state, specs, result


def test_sigterm_saves_and_a_restart_resumes_within_10_percent(first_run: tuple[Path, list, dict]) -> None:
    state, specs, result = first_run
    assert state.is_file(), result["log"]
    last = online_outputs(result["records"])[-1]
    saved = yaml.safe_load(state.read_text())
    assert saved["key"]["mass"] == 720.0 and math.exp(saved["theta"][0]) == pytest.approx(last["cf"], rel=0.05)
    # restart and feed the first 3 s of the drive again: the first estimate is the saved one
    head = [s for s in specs if s["fields"]["header.stamp.sec"] * 1.0 + s["fields"]["header.stamp.nanosec"] * 1e-9
            <= specs[0]["fields"]["header.stamp.sec"] + 3.0]
    again = run_node(state, head, expected=5)
    assert again["returncode"] == 0, again["log"]
    first = online_outputs(again["records"])[0]
    assert first["cf"] == pytest.approx(last["cf"], rel=0.10) and first["cr"] == pytest.approx(last["cr"], rel=0.10)
    assert first["cf_std"] > 1.5 * last["cf_std"]  # inflated: the surface may have changed
    assert persistence_status(again).startswith(("restored", "saved"))


@pytest.mark.parametrize("damage", ["another vehicle", "out of bounds"])
def test_a_foreign_or_implausible_file_is_refused_with_the_reason(first_run: tuple[Path, list, dict],
                                                                  tmp_path: Path, damage: str) -> None:
    state, specs, _ = first_run
    saved = yaml.safe_load(state.read_text())
    if damage == "another vehicle":
        saved["key"]["mass"] = 650.0
    else:
        saved["theta"] = [math.log(1.0e9), saved["theta"][1]]
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(saved))
    result = run_node(bad, specs[:60], expected=3)
    first = online_outputs(result["records"])[0]
    assert first["cf"] == pytest.approx(1000.0)  # a cold start
    status = next(s["message"] for item in result["records"]["diagnostics"] for s in item["msg"]["status"]
                  if s["name"].endswith("persistence"))
    assert "cold start" in status and ("another vehicle" in status or "outside ekf.stiffness_bounds" in status), status
    assert "mass" in status or "bounds" in status


COVARIANCE = ((1e-4, 0, 0, 0), (0, 1e-4, 0, 0), (0, 0, 1e-6, 0), (0, 0, 0, 1e-6))  # theta_f, theta_r, b, g


def test_a_file_of_the_first_format_is_restored_with_the_gain_at_its_prior(tmp_path: Path) -> None:
    """Format 1 (no g, 3 x 3): theta and b restored (inflated), g 0 with ekf.steering_gain_initial_variance."""
    config = EstimatorConfig()
    path = tmp_path / "old.yaml"
    document = {"key": {**key_of(config), "format": FORMAT_WITHOUT_GAIN}, "stamp": 3.0,
                "theta": [math.log(8000.0), math.log(10000.0)], "offset": 0.01,
                "covariance": [[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 1e-6]]}
    path.write_text(yaml.safe_dump(document))
    restored = load(path, config)
    assert restored.theta == (math.log(8000.0), math.log(10000.0)) and restored.offset == 0.01
    assert restored.gain == 0.0 and len(restored.covariance) == 4
    assert restored.covariance[3][3] == config.noise.steering_gain_initial_variance
    assert restored.covariance[2][2] == pytest.approx(4e-6) and restored.covariance[0][3] == 0.0
    document["covariance"] = [list(row) for row in COVARIANCE]  # a 4 x 4 under the old format is not one
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(PersistenceError, match="3 x 3"):
        load(path, config)


def test_load_refuses_what_does_not_fit(tmp_path: Path) -> None:
    config = EstimatorConfig()
    path = tmp_path / "s.yaml"
    good = LearnedState((math.log(8000.0), math.log(10000.0)), 0.01, COVARIANCE, 1.0, -0.008)
    save(path, config, good)
    restored = load(path, config)
    assert restored.theta == good.theta and restored.covariance[0][0] > 4 * 1e-4  # inflated
    assert restored.gain == good.gain
    save(path, config, LearnedState(good.theta, good.offset, COVARIANCE, 1.0, 0.5))
    with pytest.raises(PersistenceError, match="steering gain error 0.5 is not plausible"):
        load(path, config)
    path.write_text("key: [1, 2\n")
    with pytest.raises(PersistenceError, match="not a saved stiffness state"):
        load(path, config)


WRITER = """
import math, sys
from pathlib import Path
from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.ekf.persistence import LearnedState, save
path, config, k = Path(sys.argv[1]), EstimatorConfig(), 0
print("ready", flush=True)
while True:
    k += 1
    save(path, config, LearnedState((math.log(8000.0 + k), math.log(10000.0)), 0.0,
                                    ((1e-4, 0, 0, 0), (0, 1e-4, 0, 0), (0, 0, 1e-6, 0), (0, 0, 0, 1e-6)), float(k)))
"""


@pytest.mark.parametrize("delay", [0.05, 0.13, 0.31])
def test_killed_mid_write_leaves_a_whole_file(tmp_path: Path, delay: float) -> None:
    """SIGKILL a process that saves in a loop: the file is always whole; a stale temporary is cleaned up."""
    path = tmp_path / "state.yaml"
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert writer.stdout.readline().strip() == "ready"
    time.sleep(delay)
    writer.send_signal(signal.SIGKILL)
    writer.wait(10)
    learned = load(path, EstimatorConfig())  # whole and consistent, whatever the moment of the kill
    assert learned.theta[0] > math.log(8000.0)
    keeper = Keeper(path, 60.0, EstimatorConfig())
    assert keeper.restore() is not None
    assert not list(tmp_path.glob(".state.yaml.*.tmp"))


@pytest.mark.parametrize("estimated", [True, False])
def test_the_filter_restores_the_gain_only_where_it_estimates_it(estimated: bool) -> None:
    """JointEKF.restore: g and its covariance row back with ekf.estimate_steering_gain; else g 0, row 0."""
    config = replace(EstimatorConfig(), options=FilterOptions(estimate_steering_gain=estimated))
    learned = LearnedState((math.log(8000.0), math.log(10000.0)), 0.01, COVARIANCE, 1.0, -0.008)
    ekf = JointEKF(config)
    ekf.restore(learned)
    assert ekf.state[X_STEERING_GAIN] == (-0.008 if estimated else 0.0)
    assert ekf.covariance[X_STEERING_GAIN, X_STEERING_GAIN] == (1e-6 if estimated else 0.0)
    assert np.isclose(ekf.learned_state(2.0).gain, -0.008 if estimated else 0.0)
