"""A node that falls behind its inputs delays its epochs and loses none (over real Fast DDS, loopback only).

A busy vehicle computer (or a loaded CI machine) can leave the node behind its inputs for a while. Its
inputs hold ``adapters.INPUT_QUEUE_DEPTH`` messages each, so what arrives meanwhile waits for it. Before
session 30 they held 100, and about 100 steering samples queued up dropped epochs (CI: 14 of 300).

A burst models it: 300 messages (over 100 of them steering) sent at once in the middle of a drive, faster
than the node takes them. A stopped process (SIGSTOP) would not: in the full suite Fast DDS's shared-memory
transport lost the whole stopped span in 2 of 4 runs (why, not pinned down; README).
"""

from __future__ import annotations

import re
from pathlib import Path

from ros_harness import run_scenario
from test_node import (
    CONFIG,
    HEAD,
    PUBLISH_TYPES,
    STEER,
    VEL,
    assert_all_finite,
    bag_specs,
    max_relative_difference,
    offline_outputs,
    online_outputs,
    record_spec,
    sample_bag,
    specs_to_samples,
)

from transplanter_ident.config.params_file import EstimatorParams

#: messages sent at once: more steering samples than the old queue (100) held
BURST_MESSAGES = 300
BURST_START = 600  # messages published at the tests' pace before the burst


def test_a_node_behind_its_inputs_delays_epochs_and_loses_none(tmp_path: Path) -> None:
    params = EstimatorParams()
    specs = bag_specs(sample_bag(tmp_path), params)
    assert len(specs) > BURST_START + BURST_MESSAGES + 300
    burst = specs[BURST_START:BURST_START + BURST_MESSAGES]
    assert sum(spec["topic"] == STEER for spec in burst) > 100  # the old queue overflowed (checked: 111 lost)
    expected = offline_outputs(specs_to_samples(specs), params)
    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG)],
        "record": record_spec(),
        "publish_types": PUBLISH_TYPES,
        "steps": [{"publish": specs[:BURST_START], "pace": 0.002}, {"publish": burst, "pace": 0.0},
                  {"publish": specs[BURST_START + BURST_MESSAGES:], "pace": 0.002},
                  {"wait_for": ["measurement", len(expected), 60.0]}, {"spin": 0.3}],
    }, timeout=300)
    assert result["alive"] and result["returncode"] == 0, result["log"]
    summary = re.search(r"shutting down: received (\d+) velocity, (\d+) heading, (\d+) steering message", result["log"])
    assert summary, result["log"]  # the node's last words count what it received, per input
    sent = [sum(spec["topic"] == topic for spec in specs) for topic in (VEL, HEAD, STEER)]
    assert [int(n) for n in summary.groups()] == sent, result["log"]
    online = online_outputs(result["records"])
    assert len(online) == len(expected), f"{len(online)} of {len(expected)} epochs published\n{result['log']}"
    assert_all_finite(result["records"])
    assert max_relative_difference(online, expected) <= 1e-9
