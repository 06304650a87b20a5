"""Benchmark of the `estimator` node over Fast DDS: 100 Hz GNSS + 100 Hz steering for 60 s.

Not a test. A driver process publishes a simulated drive (``sine`` scenario, 2 m/s, GNSS velocity
and heading at 100 Hz, steering at 100 Hz) to the installed ``estimator`` in real time, both in
one fresh network namespace with their own ROS_DOMAIN_ID (test/ros_harness.py), and reports:

* per-epoch latency, measured inside the node (``diagnostics.latency_log``): from the entry to
  the callback of the GNSS message that completes the epoch to the return of the last of the
  four output publishes; median and p99 (the node's callbacks take no MessageInfo, which
  rclpy 7.1's EventsExecutor cannot deliver, so DDS reception itself is not seen in the node);
* end-to-end latency, measured in the driver: publish of that GNSS message to reception of
  ``~/cornering_stiffness`` (adds DDS delivery both ways and both executors' scheduling, so it
  bounds the arrival-to-publish latency from above); median and p99;
* the node's CPU, % of one core, from utime + stime in /proc/<pid>/stat over the measured window;
* the node's peak RSS (VmHWM in /proc/<pid>/status).

The yardstick, in the same run and under the same load: a bare rclpy node (FLOOR_NODE) that only
subscribes to the three inputs and publishes one Vector3Stamped per GNSS epoch, spun by the same
executor (``--executor``, default ``events``: the estimator's default). Its CPU is the floor of any
rclpy node at these rates; the estimator's CPU is also reported as a ratio to it.

Targets (issue "The estimator node"): median <= 1 ms, p99 <= 5 ms, CPU <= 10 %, RSS <= 200 MB.
Numba's on-disk cache is filled first. Each run streams the floor node for ``--floor-duration``
seconds, then the estimator for ``--duration`` seconds, each after 3 s of warm-up (not measured);
the figures are the medians over ``--runs`` runs (default 3).

Run: ``python bench/node_bench.py [--runs N] [--duration S] [--floor-duration S] [--executor events|single]``;
``bench/run.py``
calls :func:`main`.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
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

# the latency targets apply to both measures: in the node, and end to end (an upper bound of arrival-to-publish)
TARGETS = {"latency_median_ms": 1.0, "latency_p99_ms": 5.0, "e2e_median_ms": 1.0, "e2e_p99_ms": 5.0,
           "cpu_percent": 10.0, "rss_mb": 200.0}
RATE = 100.0  # Hz, GNSS (velocity and heading) and steering
WARM_UP = 3.0  # s streamed before measuring

FLOOR_NODE = """
import gc
import sys
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from geometry_msgs.msg import QuaternionStamped, TwistStamped, Vector3Stamped
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import JointState

rclpy.init()
node = rclpy.create_node("estimator")
pub = node.create_publisher(Vector3Stamped, "~/cornering_stiffness", 10)
out = Vector3Stamped()


def on_heading(msg):
    out.header.stamp = msg.header.stamp
    pub.publish(out)


node.create_subscription(TwistStamped, "/gnss/vel", lambda msg: None, qos_profile_sensor_data)
node.create_subscription(QuaternionStamped, "/gnss/heading", on_heading, qos_profile_sensor_data)
node.create_subscription(JointState, "/steering_angle", lambda msg: None, qos_profile_sensor_data)
executor = EventsExecutor() if sys.argv[1] == "events" else SingleThreadedExecutor()
executor.add_node(node)
gc.freeze()
try:
    while rclpy.ok():
        executor.spin_once(timeout_sec=0.5)
except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
    pass
"""


def _proc_cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime (fields 14, 15)


def _thread_cpu_seconds(pid: int) -> dict[str, float]:
    """CPU seconds per thread name (threads of the same name summed)."""
    out: dict[str, float] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            text = (task / "stat").read_text()
        except OSError:
            continue
        name = text[text.index("(") + 1:text.rindex(")")]
        fields = text.rsplit(")", 1)[1].split()
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


def _proc_status_kb(pid: int, key: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return float(line.split()[1])
    return math.nan


def _stream(duration: float) -> list[tuple[float, Any, Any, Any]]:
    """(stamp, steering, velocity, heading) rclpy messages of a simulated 2 m/s sine drive."""
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import QuaternionStamped, TwistStamped
    from sensor_msgs.msg import JointState

    from transplanter_ident.sim.signals import sine_steering
    from transplanter_ident.sim.simulator import SimConfig, simulate

    config = SimConfig(duration=duration, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0),
                       gnss_rate=RATE, steering_rate=RATE, seed=7)
    result = simulate(config)
    t0 = 1_700_000_000.0
    out = []
    for t, (east, north), yaw, angle in zip(result.gnss_time.tolist(), result.velocity_enu.tolist(),
                                            result.heading.tolist(), result.steering.tolist(), strict=True):
        ns = round((t0 + t) * 1e9)
        stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        steer = JointState(name=["front_steering"], position=[angle])
        steer.header.stamp = stamp
        vel = TwistStamped()
        vel.header.stamp = stamp
        vel.twist.linear.x, vel.twist.linear.y = east, north
        head = QuaternionStamped()
        head.header.stamp = stamp
        head.quaternion.z, head.quaternion.w = math.sin(0.5 * yaw), math.cos(0.5 * yaw)
        out.append((t0 + t, steer, vel, head))
    return out


def drive(args: dict[str, Any]) -> dict[str, Any]:
    """Inside the isolated driver (``run_driver("bench.node_bench:drive")``): stream in real time, measure.

    ``args``: duration (s), floor (true: run FLOOR_NODE instead of the estimator), executor.
    """
    duration = float(args["duration"])
    floor = bool(args.get("floor"))
    executor = str(args.get("executor", "events"))
    tmp = Path(args["_tmp"])
    latency_log = tmp / "latency.txt"
    stream = _stream(duration + WARM_UP + 1.0)
    session = ros_harness.RosSession("node_bench_driver")
    try:
        pub_steer = session.publisher("/steering_angle", "sensor_msgs/msg/JointState", 100)
        pub_vel = session.publisher("/gnss/vel", "geometry_msgs/msg/TwistStamped", 100)
        pub_head = session.publisher("/gnss/heading", "geometry_msgs/msg/QuaternionStamped", 100)
        sent: dict[int, int] = {}  # epoch stamp in ms (the node's float round trip moves it by < 1 us) -> ns
        received: list[tuple[int, int]] = []
        session.subscribe("stiffness", "/estimator/cornering_stiffness", "geometry_msgs/msg/Vector3Stamped",
                          lambda msg: received.append((_ms(msg.header.stamp), time.time_ns())))
        node_counts: dict[str, int] = {}  # messages per input, from the node's last /diagnostics
        if not floor:
            session.subscribe("diagnostics", "/diagnostics", "diagnostic_msgs/msg/DiagnosticArray",
                              lambda msg: node_counts.update(_input_counts(msg)))
        published = 0
        if floor:
            session.start_estimator([], tmp / "floor.log", command=[sys.executable, "-c", FLOOR_NODE, executor])
        else:
            session.start_estimator(["--params-file", str(ROOT / "config" / "estimator.yaml"),
                                     "-p", f"diagnostics.latency_log:={latency_log}"], tmp / "estimator.log",
                                    options=["--executor", executor])
        session.wait_matched(30.0, settle=1.0)
        pid = session.process.pid

        start = time.monotonic()
        measure_from = stream[0][0] + WARM_UP
        cpu0 = wall0 = None
        for k, (t, steer, vel, head) in enumerate(stream):
            if t >= measure_from and cpu0 is None:
                cpu0, wall0, threads0 = _proc_cpu_seconds(pid), time.monotonic(), _thread_cpu_seconds(pid)
            if t > measure_from + duration:
                break
            left = start + k / RATE - time.monotonic()
            if left > 0.0:
                session.spin_for(left)
            pub_steer.publish(steer)
            pub_vel.publish(vel)
            sent[_ms(head.header.stamp)] = time.time_ns()
            pub_head.publish(head)
            published += 1
        cpu1, wall1, threads1 = _proc_cpu_seconds(pid), time.monotonic(), _thread_cpu_seconds(pid)
        rss_kb = _proc_status_kb(pid, "VmHWM")
        session.spin_for(0.5 if floor else 1.5)  # the estimator: one more /diagnostics (1 Hz)
        alive = session.alive()
    finally:
        returncode = session.stop_estimator()
        log = session.log_text()
        session.close()

    in_node = []
    for line in [] if floor else latency_log.read_text().splitlines():
        t, latency = map(float, line.split())
        if t >= measure_from:
            in_node.append(latency)
    first_ms = round(measure_from * 1e3)
    end_to_end = [(when - sent[key]) * 1e-9 for key, when in received if key in sent and key >= first_ms]
    nan = math.nan
    return {"alive": alive, "returncode": returncode, "log": log[-3000:], "epochs": len(in_node),
            "sent_epochs": sum(1 for key in sent if key >= first_ms), "e2e_epochs": len(end_to_end),
            "latency_median_ms": 1e3 * statistics.median(in_node) if in_node else nan,
            "latency_p99_ms": 1e3 * _percentile(in_node, 99.0) if in_node else nan,
            "latency_max_ms": 1e3 * max(in_node) if in_node else nan,
            "e2e_median_ms": 1e3 * statistics.median(end_to_end),
            "e2e_p99_ms": 1e3 * _percentile(end_to_end, 99.0),
            "cpu_percent": 100.0 * (cpu1 - cpu0) / (wall1 - wall0),
            "rss_mb": rss_kb / 1024.0, "wall_s": wall1 - wall0, "published_per_input": published,
            "node_counts": node_counts,
            "cpu_by_thread": {name: 100.0 * (threads1[name] - threads0.get(name, 0.0)) / (wall1 - wall0)
                              for name in threads1 if threads1[name] - threads0.get(name, 0.0) > 0.0}}


def _input_counts(msg: Any) -> dict[str, int]:
    """{'velocity': n, ...}: the 'messages' value of each '<role> input' status of a DiagnosticArray."""
    counts = {}
    for status in msg.status:
        if status.name.endswith(" input"):
            values = {kv.key: kv.value for kv in status.values}
            counts[status.name.split(": ", 1)[-1].removesuffix(" input")] = int(values.get("messages", "0"))
    return counts


def _ms(stamp: Any) -> int:
    return round((stamp.sec * 1_000_000_000 + stamp.nanosec) / 1e6)


def _percentile(values: list[float], q: float) -> float:
    data = sorted(values)
    pos = (len(data) - 1) * q / 100.0
    low = math.floor(pos)
    high = min(low + 1, len(data) - 1)
    return data[low] + (data[high] - data[low]) * (pos - low)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark ``--runs`` times and print per-run figures, medians and targets."""
    parser = argparse.ArgumentParser(prog="node_bench", description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="number of runs (default 3)")
    parser.add_argument("--duration", type=float, default=60.0, help="measured seconds per run (default 60)")
    parser.add_argument("--floor-duration", type=float, default=20.0,
                        help="measured seconds of the bare-rclpy yardstick per run (default 20)")
    parser.add_argument("--executor", choices=("events", "single"), default="events",
                        help="executor of the estimator and of the floor node (default events)")
    args = parser.parse_args(argv)
    print(f"node_bench: {args.runs} run(s) x {args.duration:g} s at {RATE:g} Hz GNSS + {RATE:g} Hz steering; "
          f"estimator: {' '.join(ros_harness.estimator_command(options=['--executor', args.executor]))}; "
          f"network namespace: {'yes' if ros_harness.unshare_works() else 'no (loopback + own domain)'}",
          flush=True)
    # fill numba's on-disk cache first (a stale cache would make the first run compile and inflate its RSS)
    subprocess.run([sys.executable, "-c", "from transplanter_ident.ekf.joint_ekf import warm_up\n"
                    "from transplanter_ident.config.params_file import EstimatorParams\n"
                    "warm_up(EstimatorParams().config)"],
                   check=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    runs = []
    for i in range(args.runs):
        result = {}
        for label, floor, duration in (("floor", True, args.floor_duration), ("estimator", False, args.duration)):
            res = ros_harness.run_driver("bench.node_bench:drive",
                                         {"duration": duration, "floor": floor, "executor": args.executor},
                                         timeout=duration + 120.0)
            if not res["alive"] or res["returncode"] != 0:
                print(f"run {i + 1}: the {label} node failed (rc {res['returncode']})\n{res['log']}", file=sys.stderr)
                return 1
            result[label] = res
        est, base = result["estimator"], result["floor"]
        est["floor_cpu_percent"], est["floor_rss_mb"] = base["cpu_percent"], base["rss_mb"]
        est["cpu_ratio_to_floor"] = est["cpu_percent"] / base["cpu_percent"]
        runs.append(est)
        by_thread = sorted(est["cpu_by_thread"].items(), key=lambda item: -item[1])
        print(f"run {i + 1}: {est['epochs']}/{est['sent_epochs']} epochs published ({est['e2e_epochs']} received by "
              f"the driver); in-node latency median {est['latency_median_ms']:.3f} ms, p99 "
              f"{est['latency_p99_ms']:.3f} ms, max {est['latency_max_ms']:.3f} ms; end-to-end median "
              f"{est['e2e_median_ms']:.3f} ms, p99 {est['e2e_p99_ms']:.3f} ms; CPU {est['cpu_percent']:.1f} % of one "
              f"core ({', '.join(f'{name} {pct:.1f}' for name, pct in by_thread)}); peak RSS {est['rss_mb']:.1f} MB\n"
              f"       inputs taken by the node (best-effort QoS) of {est['published_per_input']} published each: "
              f"{', '.join(f'{k} {v}' for k, v in sorted(est['node_counts'].items())) or 'no /diagnostics'}\n"
              f"       floor (bare rclpy node, {args.floor_duration:g} s): CPU {base['cpu_percent']:.1f} %, peak RSS "
              f"{base['rss_mb']:.1f} MB, end-to-end median {base['e2e_median_ms']:.3f} ms -> estimator/floor CPU "
              f"{est['cpu_ratio_to_floor']:.2f}", flush=True)
    keys = ("latency_median_ms", "latency_p99_ms", "e2e_median_ms", "e2e_p99_ms", "cpu_percent", "rss_mb",
            "floor_cpu_percent", "floor_rss_mb", "cpu_ratio_to_floor")
    medians = {key: statistics.median(r[key] for r in runs) for key in keys}
    print(f"median of {len(runs)} runs:")
    ok = True
    for key, value in medians.items():
        target = TARGETS.get(key)
        verdict = "" if target is None else (f"  (target <= {target:g}: {'met' if value <= target else 'MISSED'})")
        ok &= target is None or value <= target
        print(f"  {key:<20} {value:9.3f}{verdict}")
    print(f"node_bench: targets {'met' if ok else 'missed'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
