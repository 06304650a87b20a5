"""Benchmark of the `estimator` node's memory under bad traffic (issue #14 item 4: bounded memory).

Not a test. Two estimator processes run side by side in one fresh network namespace with their
own ROS_DOMAIN_ID (test/ros_harness.py), each on topics of its own, for ``--duration`` seconds
(default 600) after ``--warm-up`` seconds (default 60) of the same traffic:

* ``steering-only``: JointState steering at ``--rate`` Hz (default 100) and no GNSS at all: the
  steering buffer must be trimmed (it grew by about 49 MB/h before it was);
* ``distinct-rejections``: at ``--rate`` Hz each, steering beyond ``max_steering`` with a different
  angle every time, and heading quaternions with an infinite entry and other entries that never
  repeat: every rejection's text is new (keyed by the text, the log throttle grew by about 101 MB/h).

Reported per node: RSS (VmRSS in /proc/<pid>/status) after the warm-up and at the end, the growth,
the slope of a least-squares line through samples every 10 s (MB/h), and the messages the node
counted (its /diagnostics). Target: growth <= 5 MB over the 10 minutes, each.

Run: ``python bench/node_memory_bench.py [--duration S] [--warm-up S] [--rate HZ]``; ``bench/run.py`` calls
:func:`main`.
"""

from __future__ import annotations

import argparse
import math
import random
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
for _path in (str(ROOT), str(ROOT / "test")):
    if _path not in sys.path:
        sys.path.insert(0, _path)

import ros_harness  # noqa: E402  (test/ros_harness.py: isolation, the driver process, the node process)

TARGET_MB = 5.0
SAMPLE_PERIOD = 10.0  # s between RSS samples
SCENARIOS = ("steering-only", "distinct-rejections")
T0 = 1_700_000_000.0


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return float(line.split()[1]) / 1024.0
    return math.nan


def _slope_mb_per_h(samples: list[tuple[float, float]]) -> float:
    if len(samples) < 2:
        return math.nan
    ts = [t for t, _ in samples]
    ys = [y for _, y in samples]
    mt, my = sum(ts) / len(ts), sum(ys) / len(ys)
    var = sum((t - mt) ** 2 for t in ts)
    return 3600.0 * sum((t - mt) * (y - my) for t, y in zip(ts, ys, strict=True)) / var if var > 0 else math.nan


def _messages(scenario: str, k: int, rng: random.Random) -> list[tuple[str, Any]]:
    """(role, rclpy message) to publish at tick k of one scenario."""
    from geometry_msgs.msg import QuaternionStamped
    from sensor_msgs.msg import JointState

    t = T0 + 0.01 * k
    sec, nanosec = int(t), round((t - int(t)) * 1e9) % 1_000_000_000
    steer = JointState(name=["front_steering"])
    steer.header.stamp.sec, steer.header.stamp.nanosec = sec, nanosec
    if scenario == "steering-only":
        steer.position = [0.2 * math.sin(0.5 * k * 0.01)]
        return [("steering", steer)]
    steer.position = [1.0 + 0.001 * k]  # beyond max_steering, and a different |angle| in every rejection
    head = QuaternionStamped()
    head.header.stamp.sec, head.header.stamp.nanosec = sec, nanosec
    head.quaternion.x, head.quaternion.y, head.quaternion.z, head.quaternion.w = (
        math.inf, rng.random(), rng.random(), rng.random())
    return [("steering", steer), ("heading", head)]


def drive(args: dict[str, Any]) -> dict[str, Any]:
    """Inside the isolated driver: both nodes, their traffic, RSS samples."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import QuaternionStamped
    from sensor_msgs.msg import JointState

    tmp = Path(args["_tmp"])
    rate, warm_up, duration = float(args["rate"]), float(args["warm_up"]), float(args["duration"])
    session = ros_harness.RosSession("memory_bench_driver")
    procs: dict[str, subprocess.Popen] = {}
    counts: dict[str, dict[str, str]] = {}
    try:
        publishers = {}
        for i, scenario in enumerate(SCENARIOS):
            name = f"estimator_{i}"
            topics = {role: f"/{name}_in/{role}" for role in ("velocity", "heading", "steering")}
            publishers[scenario] = {"steering": session.node.create_publisher(JointState, topics["steering"], 100),
                                    "heading": session.node.create_publisher(QuaternionStamped, topics["heading"],
                                                                             100)}
            command = ros_harness.estimator_command(
                "--params-file", str(ROOT / "config" / "estimator.yaml"), "-r", f"__node:={name}",
                *(arg for role, topic in topics.items() for arg in ("-p", f"topics.{role}:={topic}")))
            log = (tmp / f"{name}.log").open("w")
            procs[scenario] = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT,
                                               preexec_fn=ros_harness._die_with_parent)
            log.close()

        def on_diagnostics(msg: Any) -> None:
            for status in msg.status:
                if status.name.endswith(" input"):
                    node = status.name.split(":")[0]
                    counts.setdefault(node, {})[status.name.split(": ")[1]] = next(
                        (kv.value for kv in status.values if kv.key == "messages"), "?")

        session.node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 100)
        deadline = time.monotonic() + 60.0
        while any(p.get_subscription_count() == 0 for pubs in publishers.values() for p in pubs.values()):
            session.spin_for(0.1)
            if time.monotonic() > deadline:
                raise RuntimeError("the nodes did not come up")
        rng = random.Random(14)
        start = time.monotonic()
        end = start + warm_up + duration
        samples: dict[str, list[tuple[float, float]]] = {s: [] for s in SCENARIOS}
        next_sample = start + warm_up
        k = 0
        while time.monotonic() < end:
            left = start + k / rate - time.monotonic()
            if left > 0.0:
                session.spin_for(left)
            for scenario in SCENARIOS:
                for role, msg in _messages(scenario, k, rng):
                    publishers[scenario][role].publish(msg)
            k += 1
            if time.monotonic() >= next_sample:
                for scenario, proc in procs.items():
                    samples[scenario].append((time.monotonic() - start, _rss_mb(proc.pid)))
                next_sample += SAMPLE_PERIOD
        alive = {s: p.poll() is None for s, p in procs.items()}
        for scenario, proc in procs.items():
            samples[scenario].append((time.monotonic() - start, _rss_mb(proc.pid)))
        session.spin_for(1.5)
    finally:
        for proc in procs.values():
            proc.terminate()
        for proc in procs.values():
            try:
                proc.wait(15)
            except subprocess.TimeoutExpired:
                proc.kill()
        session.close()
    return {"samples": samples, "alive": alive, "ticks": k, "counts": counts,
            "returncodes": {s: p.returncode for s, p in procs.items()},
            "logs": {s: (tmp / f"estimator_{i}.log").read_text()[-1500:] for i, s in enumerate(SCENARIOS)}}


def main(argv: list[str] | None = None) -> int:
    """Run both scenarios side by side and print the RSS growth against the target."""
    parser = argparse.ArgumentParser(prog="node_memory_bench", description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=600.0, help="measured seconds (default 600)")
    parser.add_argument("--warm-up", type=float, default=60.0, help="seconds of traffic before (default 60)")
    parser.add_argument("--rate", type=float, default=100.0, help="messages per second per input (default 100)")
    args = parser.parse_args(argv)
    print(f"node_memory_bench: {args.duration:g} s measured after {args.warm_up:g} s of warm-up, {args.rate:g} Hz; "
          f"scenarios: {', '.join(SCENARIOS)}", flush=True)
    result = ros_harness.run_driver("bench.node_memory_bench:drive", {"rate": args.rate, "warm_up": args.warm_up,
                                                                       "duration": args.duration},
                                    timeout=args.warm_up + args.duration + 300.0)
    ok = True
    for i, scenario in enumerate(SCENARIOS):
        samples = result["samples"][scenario]
        growth = samples[-1][1] - samples[0][1]
        met = result["alive"][scenario] and growth <= TARGET_MB
        ok &= met
        node_counts = result["counts"].get(f"estimator_{i}", {})
        print(f"  {scenario:<20} RSS {samples[0][1]:7.1f} -> {samples[-1][1]:7.1f} MB: growth {growth:+6.2f} MB "
              f"in {samples[-1][0] - samples[0][0]:.0f} s (slope {_slope_mb_per_h(samples):+7.2f} MB/h; target "
              f"<= {TARGET_MB:g} MB: {'met' if met else 'MISSED'}); node alive {result['alive'][scenario]}; "
              f"messages counted by the node: {node_counts or 'n/a'}", flush=True)
        if not result["alive"][scenario]:
            print(result["logs"][scenario], file=sys.stderr)
    print(f"node_memory_bench: {result['ticks']} ticks; targets {'met' if ok else 'missed'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
