"""A single antenna (``ekf.measurement: course``) through the node over real Fast DDS and through ``replay``.

The node subscribes to the velocity and the steering only (no heading topic exists), publishes what
``replay`` computes from the same messages, never NaN (the measured vy, absent, carries the filter's
estimate), and its /diagnostics name no heading input and no velocity/heading pairing problem.
"""

from __future__ import annotations

import math
from pathlib import Path

from ros_harness import run_scenario
from test_drivers_node import replay_rows
from test_node import (
    CONFIG,
    HEAD,
    JOINT,
    OUT_TYPES,
    STEER,
    TWIST,
    VEL,
    assert_all_finite,
    bag_specs,
    max_relative_difference,
    online_outputs,
    record_spec,
    sample_bag,
)

from transplanter_ident.config.params_file import load_params

COURSE_FILE = "estimator:\n  ros__parameters:\n    ekf:\n      measurement: course\n    topics:\n      heading: /no/heading\n"


def course_params(tmp_path: Path) -> Path:
    path = tmp_path / "course.yaml"
    path.write_text(COURSE_FILE, encoding="utf-8")
    return path


def test_one_antenna_node_equals_replay_without_a_heading_topic(tmp_path: Path) -> None:
    params_file = course_params(tmp_path)
    params = load_params([CONFIG, params_file])
    assert params.config.options.course
    bag = sample_bag(tmp_path)
    specs = [s for s in bag_specs(bag, load_params([CONFIG])) if s["topic"] != HEAD]
    rows = replay_rows(bag, params_file, tmp_path)  # the bag's heading topic is not /no/heading: not read
    assert len(rows) > 50
    assert all(math.isnan(row["vy_meas"]) for row in rows)  # not measured, and not made up
    assert all(math.isfinite(row["cf"]) and row["cf_std"] > 0.0 for row in rows)

    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG), "--params-file", str(params_file)],
        "record": record_spec(diagnostics=True),
        "publish_types": [[VEL, TWIST], [STEER, JOINT]],
        "steps": [{"publish": specs, "pace": 0.002}, {"wait_for": ["measurement", len(rows), 30.0]}, {"spin": 1.5}],
    }, timeout=240)
    assert result["alive"] and result["returncode"] == 0, result["log"]
    online = online_outputs(result["records"])
    assert len(online) == len(rows), f"{len(online)} of {len(rows)} epochs published\n{result['log']}"
    assert_all_finite(result["records"])
    assert max_relative_difference(online, rows, ("cf", "cr", "cf_std", "cr_std", "vy_model", "r_model", "vx")) <= 1e-9
    assert [row["valid"] for row in online] == [row["valid"] for row in rows]
    statuses = [status for item in result["records"]["diagnostics"] for status in item["msg"]["status"]]
    names = {status["name"] for status in statuses}
    assert any(name.endswith("velocity input") for name in names) and not any("heading input" in n for n in names)
    pairing = [status for status in statuses if status["name"].endswith("GNSS pairing")]
    assert pairing and "course" in pairing[-1]["message"] and pairing[-1]["level"] == 0, pairing[-1]
    assert OUT_TYPES  # the outputs compared above are the pinned ones
