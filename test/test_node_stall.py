"""A stalled node process delays its epochs and loses none (over real Fast DDS, loopback only).

A busy vehicle computer (or a loaded CI machine) can leave the node unscheduled for a while. Its inputs
hold ``adapters.INPUT_QUEUE_DEPTH`` messages each, so what arrives meanwhile waits for it. Before
session 30 they held 100, and a stall of about 100 steering samples dropped epochs.
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

#: messages published while the node's process is stopped (SIGSTOP): more than the old queue (100) held on
#: any input, sent at once (README: a freeze of about a second loses messages in Fast DDS's transport)
STALLED_MESSAGES = 300
STALL_START = 600  # messages published before the stall


def test_a_stalled_node_delays_epochs_and_loses_none(tmp_path: Path) -> None:
    params = EstimatorParams()
    specs = bag_specs(sample_bag(tmp_path), params)
    assert len(specs) > STALL_START + STALLED_MESSAGES + 300
    stalled = specs[STALL_START:STALL_START + STALLED_MESSAGES]
    assert sum(spec["topic"] == STEER for spec in stalled) > 100  # the old queue would have overflowed
    expected = offline_outputs(specs_to_samples(specs), params)
    # the stalled messages go out at once: a frozen process (SIGSTOP) is not a slow one, and Fast DDS's
    # shared-memory transport drops what reaches a port whose listener stays frozen for about a second
    # (README); a loaded machine must not stretch the freeze towards that
    stall = [{"node_signal": "SIGSTOP"}, *stalled, {"node_signal": "SIGCONT"}]
    result = run_scenario({
        "estimator_args": ["--params-file", str(CONFIG)],
        "record": record_spec(),
        "publish_types": PUBLISH_TYPES,
        "steps": [{"publish": specs[:STALL_START], "pace": 0.002}, {"publish": stall, "pace": 0.0},
                  {"publish": specs[STALL_START + STALLED_MESSAGES:], "pace": 0.002},
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
