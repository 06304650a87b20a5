"""Cost per filter step of the tuner's inner loop against the C yardstick (DESIGN.md section 5).

Not a test. In one run it

* compiles ``../shared/bench/ekf_reference.c`` (``cc -O2``; the yardstick: plain scalar C of the
  same joint-state EKF) and runs it ``--repeats`` times per model, taking the median ns/step;
* runs ``entries.objective_kernel`` (the function the tuner calls once per candidate Q/R) on the
  same synthetic 3000-step sequence, single-threaded, in a Python loop over candidates with
  the same Q/R schedule as the C, ``--repeats`` times, median ns/step (the first, compiling
  call is excluded);
* prints the ratio kernel / C per model. Target (issue "IPSO tuner"): ratio <= 2.

Sequence (as in the C): d[k] = 0.26 sin(2 pi k 0.2 / 6), z = [0.1 sin(.) + 0.01 sin(7.3 k),
0.45 sin(.) + 0.01 cos(5.1 k)], vx = 2 m/s, dt = 0.2 s. The kernel input has the columns
[t, speed, steering, steering_rate, vy, psi, r] (``layout.E_*``) with ``measurement: yaw_rate``,
so it is the C's 4-state filter; psi (the integral of r) is only used by the extra row for the
default ``heading`` mode (5 states, z = [vy, psi]). The innovation gate is opened (threshold
1e12) so every step does the full update, as the C does.

Rows: euler/linear (eq. 10, the paper's model; with the package's defaults, and with
``config/paper.py``'s options, none of its additions, as in the C), exact/log (the default model), and extra
exact/log/heading (the default measurement), the same with relaxing tires (``vehicle.relaxation_length``:
two more states, a larger matrix exponential; the lags start once the stiffness is known, as they
do on this sequence), a single antenna (``measurement: course``: psi taken as the course, one more
discretisation per step for its speed), plus the parallel batch (``tuning.batch_objective``,
all threads), which the tuner actually uses, as ns per candidate-step.

Run: ``python bench/ekf_bench.py [--repeats N] [--steps N]``; ``bench/run.py`` calls :func:`main`.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from transplanter_ident.config.paper import PAPER_OPTIONS  # noqa: E402
from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, NoiseParams, VehicleParams  # noqa: E402
from transplanter_ident.ekf import entries, joint_ekf, layout  # noqa: E402
from transplanter_ident.tuning.problem import batch_objective  # noqa: E402

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "bench" / "ekf_reference.c"
TARGET_RATIO = 2.0
C_RUNS = {"euler": 800, "exact": 200}  # the C's own suggested run counts


@dataclass(frozen=True)
class Case:
    """One benchmarked filter variant."""

    label: str
    discretization: str
    stiffness_state: str
    measurement: str
    reference: str | None  # C model to compare with
    relaxation: float = 0.0  # m, vehicle.relaxation_length (the slip lags in the state)
    paper: bool = False  # config/paper.py's options: none of the package's additions, as in the C


CASES = (
    Case("euler/linear, z=[vy,r] (paper eq. 10)", "euler", "linear", "yaw_rate", "euler"),
    Case("  the paper's filter alone (config/paper.py)", "euler", "linear", "yaw_rate", "euler", paper=True),
    Case("exact/log, z=[vy,r]", "exact", "log", "yaw_rate", "exact"),
    Case("exact/log, z=[vy,psi] (default, extra)", "exact", "log", "heading", None),
    Case("  with relaxing tires, 0.3 m (extra)", "exact", "log", "heading", None, 0.3),
    Case("  one antenna, z=[course] (extra)", "exact", "log", "course", None),
)


def sequence(steps: int, vx: float = 2.0, dt: float = 0.2) -> np.ndarray:
    """The C's synthetic sequence as kernel input rows [t, speed, steering, steering_rate, vy, psi, r]."""
    k = np.arange(steps, dtype=np.float64)
    phase = 2.0 * math.pi * k * 0.2 / 6.0
    rows = np.zeros((steps, layout.N_EPOCH_COLUMNS))
    rows[:, layout.E_T] = k * dt
    rows[:, layout.E_SPEED] = vx
    rows[:, layout.E_STEERING] = 0.26 * np.sin(phase)
    rows[:, layout.E_VY] = 0.1 * np.sin(phase) + 0.01 * np.sin(7.3 * k)
    rows[:, layout.E_YAW_RATE] = 0.45 * np.sin(phase) + 0.01 * np.cos(5.1 * k)
    rows[:, layout.E_PSI] = np.cumsum(rows[:, layout.E_YAW_RATE]) * dt
    return np.ascontiguousarray(rows)


def filter_arrays(case: Case) -> joint_ekf.FilterArrays:
    """The case's filter with the C's P0 and R; Q is set per candidate."""
    linear = case.stiffness_state == "linear"
    base = PAPER_OPTIONS if case.paper else FilterOptions()
    options = replace(base, discretization=case.discretization, stiffness_state=case.stiffness_state,
                      measurement=case.measurement, gate_threshold=1.0e12)
    p0 = 1.0e6 if linear else 4.0
    noise = NoiseParams(measurement_noise=(4.0e-4, 1.0e-4), initial_covariance=(1.0e-2, 1.0e-2, p0, p0))
    vehicle = VehicleParams(relaxation_length=case.relaxation)
    return joint_ekf.FilterArrays.from_config(EstimatorConfig(vehicle=vehicle, options=options, noise=noise))


def candidate_q(case: Case, arrays: joint_ekf.FilterArrays, i: int) -> np.ndarray:
    """The C's Q schedule: [1e-5, 1e-5, s (1 + i % 7), s] with s = 10 (linear) or 1e-7 (log)."""
    scale = 10.0 if case.stiffness_state == "linear" else 1.0e-7
    q = arrays.process_noise.copy()
    q[layout.X_VY], q[layout.X_R] = 1.0e-5, 1.0e-5
    q[layout.X_THETA_F], q[layout.X_THETA_R] = scale * (1 + i % 7), scale
    return q


def time_kernel(case: Case, rows: np.ndarray, runs: int) -> float:
    """Nanoseconds per filter step of objective_kernel, single thread, ``runs`` candidates."""
    a = filter_arrays(case)
    qs = [candidate_q(case, a, i) for i in range(runs)]

    def one(q: np.ndarray) -> float:
        return entries.objective_kernel(rows, a.initial_state.copy(), a.initial_covariance.copy(), np.zeros(layout.N_MODEL),
                                    np.zeros(layout.N_MEMO), a.vehicle, a.settings, q, a.measurement_noise, layout.MAE)

    one(qs[0])  # compile / load from cache
    start = time.perf_counter()
    total = 0.0
    for q in qs:
        total += one(q)
    elapsed = time.perf_counter() - start
    if not math.isfinite(total):
        raise RuntimeError(f"{case.label}: non-finite objective")
    return elapsed / runs / (len(rows) - 1) * 1e9


def time_batch(case: Case, rows: np.ndarray, runs: int) -> float:
    """Nanoseconds per candidate-step of the parallel batch the tuner calls (all threads)."""
    a = filter_arrays(case)
    qs = np.array([candidate_q(case, a, i) for i in range(runs)])
    rs = np.tile(a.measurement_noise, (runs, 1))
    batch_objective(rows, a.initial_state, a.initial_covariance, a.vehicle, a.settings, qs[:2], rs[:2], layout.MAE)
    start = time.perf_counter()
    batch_objective(rows, a.initial_state, a.initial_covariance, a.vehicle, a.settings, qs, rs, layout.MAE)
    return (time.perf_counter() - start) / runs / (len(rows) - 1) * 1e9


def build_reference(work: Path) -> Path:
    """Compile the C yardstick; a clear error if the source or a compiler is missing."""
    if not REFERENCE.is_file():
        raise SystemExit(f"ekf_bench: error: C yardstick not found at {REFERENCE} "
                         "(expected ../shared/bench/ekf_reference.c relative to the repository root)")
    compiler = os.environ.get("CC", "cc")
    if shutil.which(compiler) is None:
        raise SystemExit(f"ekf_bench: error: C compiler {compiler!r} not found (set CC)")
    binary = work / "ekf_reference"
    subprocess.run([compiler, "-O2", "-o", str(binary), str(REFERENCE), "-lm"], check=True)
    return binary


def time_reference(binary: Path, model: str, steps: int, runs: int) -> float:
    """Nanoseconds per step reported by the C yardstick (its last line)."""
    out = subprocess.run([str(binary), "--model", model, "--steps", str(steps), "--runs", str(runs)],
                         check=True, capture_output=True, text=True).stdout
    match = re.search(r"ns_per_step \w+ ([0-9.]+)", out)
    if match is None:
        raise RuntimeError(f"unexpected output of the C yardstick: {out!r}")
    return float(match.group(1))


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table; returns 0 (1 if a target is missed and --strict)."""
    parser = argparse.ArgumentParser(prog="ekf_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=5, help="runs per measurement, median taken (default 5)")
    parser.add_argument("--steps", type=int, default=3000, help="sequence length (default 3000)")
    parser.add_argument("--strict", action="store_true", help="exit 1 when a target is missed")
    args = parser.parse_args(argv)

    rows = sequence(args.steps)
    results = []
    with tempfile.TemporaryDirectory(prefix="ekf_bench_") as tmp:
        binary = build_reference(Path(tmp))
        for case in CASES:
            runs = C_RUNS[case.reference or "exact"] // 4  # Python loop: fewer candidates suffice
            kernel, reference = [], []
            for _ in range(args.repeats):  # interleaved, so drift affects both alike
                kernel.append(time_kernel(case, rows, runs))
                if case.reference:
                    reference.append(time_reference(binary, case.reference, args.steps, C_RUNS[case.reference]))
            batch = statistics.median(time_batch(case, rows, 2 * runs) for _ in range(args.repeats))
            results.append((case, statistics.median(kernel), statistics.median(reference) if reference else None,
                            batch))

    from numba import get_num_threads

    print(f"\nEKF inner-loop benchmark: {args.steps}-step sequence, median of {args.repeats} runs "
          f"(Python {sys.version.split()[0]}, {os.cpu_count()} CPUs, numba threads {get_num_threads()})")
    head = (f"{'model':<42}{'kernel ns/step':>15}{'C ns/step':>11}{'ratio':>8}{'target':>9}"
            f"{'batch ns/cand-step':>20}")
    print(head)
    print("-" * len(head))
    missed = False
    for case, kernel, reference, batch in results:
        if reference is None:
            print(f"{case.label:<42}{kernel:>15.0f}{'-':>11}{'-':>8}{'-':>9}{batch:>20.0f}")
            continue
        ratio = kernel / reference
        ok = ratio <= TARGET_RATIO
        missed |= not ok
        print(f"{case.label:<42}{kernel:>15.0f}{reference:>11.0f}{ratio:>8.2f}{'met' if ok else 'MISSED':>9}"
              f"{batch:>20.0f}")
    print("-" * len(head))
    print(f"ratio = single-thread objective_kernel / C yardstick (target <= {TARGET_RATIO:g}); batch = "
          "tuning.batch_objective over all threads, per candidate-step (what the tuner pays)")
    print(f"the kernel's z=[vy,r] state has {layout.YAW_RATE_STATES} entries (the steering offset, gain and heading "
          "held when not estimated) where the C's has 4; the paper's filter alone is the C's filter in all else")
    return 1 if args.strict and missed else 0


if __name__ == "__main__":
    sys.exit(main())
