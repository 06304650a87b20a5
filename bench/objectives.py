"""Which tuning objective identifies the stiffness better: ``mae`` (eq. 21) or ``nll``? Measured, not assumed.

Not a test. DESIGN.md section 1 keeps the paper's mae (mean |one-step innovation|) and offers
the Gaussian innovation negative log-likelihood; this benchmark decides between them on the
simulator, whose true Cf and Cr are known. For each scenario and sensor-noise seed it

1. simulates the bag content (``sine`` by default: +-15 deg at 2 m/s, Cf = 8000, Cr = 10000 N/rad);
2. tunes Q/R with IPSO (paper settings, tuner seed fixed) on each objective, from the defaults;
3. replays with the tuned Q/R and takes the final relative stiffness error against the truth.

It prints, per objective, the median over seeds of |final Cf error|, |final Cr error| and their
mean, and which objective is better by how much.

Run: ``python bench/objectives.py [--scenario NAME] [--seeds N] [--duration S]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "test"))

from helpers import simulate_epochs  # noqa: E402 - test/helpers.py: simulator -> epochs, as the bag reader does

from transplanter_ident.config.parameters import EstimatorConfig  # noqa: E402
from transplanter_ident.ekf.joint_ekf import run_sequence  # noqa: E402
from transplanter_ident.evaluation.metrics import stiffness_error  # noqa: E402
from transplanter_ident.sim.scenarios import SCENARIOS, build_config  # noqa: E402
from transplanter_ident.tuning.tune import tune  # noqa: E402

OBJECTIVES = ("mae", "nll")


def main(argv: list[str] | None = None) -> int:
    """Run the comparison and print the table."""
    parser = argparse.ArgumentParser(prog="objectives", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="sine", choices=sorted(SCENARIOS))
    parser.add_argument("--seeds", type=int, default=8, help="sensor-noise seeds (default 8)")
    parser.add_argument("--duration", type=float, help="seconds (default: the scenario's)")
    parser.add_argument("--tuner-seed", type=int, default=1)
    parser.add_argument("--evaluate-on", metavar="NAME", choices=sorted(SCENARIOS),
                        help="measure the stiffness error on this scenario (same noise seed) instead of the tuning "
                             "one: how well the tuned Q/R transfers")
    args = parser.parse_args(argv)
    config = EstimatorConfig()
    errors: dict[str, list[tuple[float, float]]] = {k: [] for k in ("start", *OBJECTIVES)}
    begin = time.perf_counter()
    for seed in range(args.seeds):
        result, epochs = simulate_epochs(build_config(args.scenario, duration=args.duration, seed=100 + seed))
        configs = {"start": config}
        for objective in OBJECTIVES:
            configs[objective] = tune(config, epochs, objective=objective, seed=args.tuner_seed).tuned_config
        if args.evaluate_on:
            result, epochs = simulate_epochs(build_config(args.evaluate_on, seed=100 + seed))
        true_f = np.interp(epochs.t, result.gnss_time, result.truth_cf)
        true_r = np.interp(epochs.t, result.gnss_time, result.truth_cr)
        for key, cfg in configs.items():
            err = stiffness_error(run_sequence(cfg, epochs), true_f, true_r)
            errors[key].append((abs(err.final_front), abs(err.final_rear)))
    where = f", stiffness error measured on {args.evaluate_on}" if args.evaluate_on else ""
    print(f"\nObjective comparison, tuned on scenario {args.scenario}{where}: {args.seeds} sensor-noise seeds, IPSO paper settings, "
          f"tuner seed {args.tuner_seed} ({time.perf_counter() - begin:.0f} s)")
    head = f"{'Q/R':<22}{'median |Cf err|':>17}{'median |Cr err|':>17}{'median mean':>14}{'worst mean':>12}"
    print(head)
    print("-" * len(head))
    score = {}
    for key, rows in errors.items():
        means = [0.5 * (f + r) for f, r in rows]
        score[key] = statistics.median(means)
        label = "defaults (untuned)" if key == "start" else f"tuned on {key}"
        print(f"{label:<22}{100 * statistics.median(f for f, _ in rows):>16.2f}%"
              f"{100 * statistics.median(r for _, r in rows):>16.2f}%{100 * score[key]:>13.2f}%"
              f"{100 * max(means):>11.2f}%")
    print("-" * len(head))
    better, worse = sorted(OBJECTIVES, key=score.get)
    wins = sum(0.5 * (a[0] + a[1]) < 0.5 * (b[0] + b[1]) for a, b in zip(errors[better], errors[worse], strict=True))
    print(f"smaller final stiffness error: {better}, median {100 * score[better]:.2f} % against "
          f"{100 * score[worse]:.2f} % for {worse} ({score[worse] / max(score[better], 1e-12):.1f}x); "
          f"{better} better in {wins} of {args.seeds} seeds")
    return 0


if __name__ == "__main__":
    sys.exit(main())
