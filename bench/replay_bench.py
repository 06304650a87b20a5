"""Benchmark of `replay` on a 1-hour, 20 Hz simulated bag (~72k epochs, ~468k messages).

Not a test. Measures, as medians of ``--runs`` runs (default 3), in the same session:

* ``replay BAG --csv OUT.csv --quiet``, run as a subprocess (imports, bag reading, epoch
  assembly, the filter, the CSV): wall time and peak RSS (``ru_maxrss`` of that child, via wait4);
* the yardstick: a bare rosbags read of the same bag that deserializes every message with the
  Jazzy typestore, also as a subprocess (its imports included);
* their ratio. Targets: ratio <= 1.5 (issue #13, item 8; it was 2 in issue "Bags in and out") and
  replay wall <= 10 s.

The bag is generated once with ``simulate --scenario sine --duration 3600 --gnss-rate 20`` and
cached in ``$TRANSPLANTER_BENCH_CACHE`` (default: ``<tmp>/transplanter_ident_bench``). A short
warm-up replay fills numba's on-disk cache first, so compilation is not timed.

Run: ``python bench/replay_bench.py [--runs N] [--duration S]``; ``bench/run.py`` calls :func:`main`.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_util import ROOT, cached_bag, child_env, command, default_cache  # bench/ is on sys.path

BAG_VERSION = "v1"  # bump when simulate's output changes in a way that matters here
TARGET_RATIO = 1.5
TARGET_WALL = 10.0

BASELINE = r"""
import sys
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
store = get_typestore(Stores.ROS2_JAZZY)
count = 0
with Reader(sys.argv[1]) as reader:
    for connection, _, data in reader.messages():
        store.deserialize_cdr(data, connection.msgtype)
        count += 1
print(count)
"""


def _measure(argv: list[str], log: Path) -> tuple[float, float]:
    """(wall s, peak RSS MiB) of one child process; raises if it fails."""
    with open(log, "w") as out:
        start = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=child_env(), cwd=ROOT)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed ({proc.returncode}):\n{log.read_text()[-2000:]}")
    return wall, usage.ru_maxrss / 1024.0  # Linux: KiB


def ensure_bag(cache: Path, duration: float) -> Path:
    """The cached benchmark bag (generated on first use; takes ~10-20 s)."""
    return cached_bag(cache, f"replay_{int(duration)}s_20hz_{BAG_VERSION}",
                      ["--scenario", "sine", "--duration", str(duration), "--gnss-rate", "20", "--steering-rate", "50",
                       "--seed", "0"])


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table; returns 0 (1 if a target is missed and --strict)."""
    parser = argparse.ArgumentParser(prog="replay_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3, help="runs per measurement (default 3)")
    parser.add_argument("--duration", type=float, default=3600.0, help="bag duration, s (default 3600)")
    parser.add_argument("--cache", type=Path, default=default_cache())
    parser.add_argument("--strict", action="store_true", help="exit 1 when a target is missed")
    args = parser.parse_args(argv)

    bag = ensure_bag(args.cache, args.duration)
    with tempfile.TemporaryDirectory(prefix="replay_bench_") as tmp:
        work = Path(tmp)
        warm = work / "warm"
        subprocess.run([*command("simulate"), "-o", str(warm), "--duration", "5"], check=True, env=child_env(),
                       cwd=ROOT, stdout=subprocess.DEVNULL)
        _measure([*command("replay"), str(warm), "--quiet"], work / "warm.log")

        baseline_argv = [sys.executable, "-c", BASELINE, str(bag)]
        replay_argv = [*command("replay"), str(bag), "--csv", str(work / "out.csv"), "--quiet"]
        base, rep = [], []
        for _ in range(args.runs):  # interleaved, so drift affects both alike
            base.append(_measure(baseline_argv, work / "baseline.log"))
            rep.append(_measure(replay_argv, work / "replay.log"))
        messages = int((work / "baseline.log").read_text().split()[-1])
        epochs = sum(1 for _ in open(work / "out.csv")) - 1

    def med(rows: list[tuple[float, float]], i: int) -> float:
        return statistics.median(r[i] for r in rows)

    ratios = [r[0] / b[0] for b, r in zip(base, rep, strict=True)]
    ratio = statistics.median(ratios)
    wall = med(rep, 0)
    print(f"\nreplay benchmark: {bag.name}: {messages} messages, {epochs} epochs; median of {args.runs} runs "
          f"(Python {sys.version.split()[0]}, {os.cpu_count()} CPUs)")
    head = f"{'measurement':<44}{'wall [s]':>10}{'min':>8}{'max':>8}{'peak RSS [MiB]':>16}"
    print(head)
    print("-" * len(head))
    for label, rows in (("bare rosbags read + deserialize (all msgs)", base), ("replay --csv (subprocess)", rep)):
        walls = [r[0] for r in rows]
        print(f"{label:<44}{med(rows, 0):>10.2f}{min(walls):>8.2f}{max(walls):>8.2f}{med(rows, 1):>16.0f}")
    print("-" * len(head))
    ok_ratio, ok_wall = ratio <= TARGET_RATIO, wall <= TARGET_WALL
    print(f"ratio replay / bare read (median of per-run ratios): {ratio:.2f}  "
          f"(target <= {TARGET_RATIO:g}: {'met' if ok_ratio else 'MISSED'})")
    print(f"replay wall: {wall:.2f} s  (target <= {TARGET_WALL:g} s: {'met' if ok_wall else 'MISSED'})")
    print(f"replay throughput: {messages / wall / 1e3:.0f} k messages/s, {epochs / wall / 1e3:.1f} k epochs/s")
    return 1 if args.strict and not (ok_ratio and ok_wall) else 0


if __name__ == "__main__":
    sys.exit(main())
