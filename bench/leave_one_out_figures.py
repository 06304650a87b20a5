"""The leave-one-bag-out acceptance of issue #13, measured: multi-bag vs default vs single-bag Q/R.

Not a test (about 1.5 min per seed on 2 cores). For each ``--seeds`` seed, simulates one bag of
each of the project's scenarios (sine, step20-ccw, step30-cw, surface-change, multisine,
stiffness-drop, wet-saturating; each its default duration), the GNSS noise scaled by
``--noise-factor`` (1: the simulator's, which equals the default R), and runs what ``tuner BAG...``
runs with its defaults (IPSO, F = 20, k_max = 40, NLL, split Q, Q within ``--q-span`` decades
of the start): the leave-one-bag-out table, i.e. for each bag the final Cf and Cr error with the
default Q/R, Q/R tuned on it alone, and Q/R tuned on the other bags (held out). The acceptance
asks for |others| <= |default| and <= |single| on every bag. A summary over the seeds follows:
bags meeting it, and the held-out |error| pooled over seeds, bags and (Cf, Cr), separately for
the five drives that identify both stiffnesses and the two step steers (which do not: their
final errors swing by tens of points with any change of Q/R).

Run: ``.venv/bin/python bench/leave_one_out_figures.py [--seeds 11 12 13] [--noise-factor 1]
[--q-span 1] [--tune-stiffness-noise]``. The bags are kept in ``$TRANSPLANTER_BENCH_CACHE``
(default <tmp>/transplanter_ident_bench).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_util import default_cache  # bench/ is on sys.path

SCENARIOS = ("sine", "step20-ccw", "step30-cw", "surface-change", "multisine", "stiffness-drop", "wet-saturating")
STEP_STEERS = ("step20-ccw", "step30-cw")


def make_bags(root: Path, seed: int, noise_factor: float) -> list[Path]:
    """One simulated bag per scenario (generated once, then reused)."""
    from transplanter_ident.bags import write_sim_bag
    from transplanter_ident.sim.scenarios import build_config
    from transplanter_ident.sim.simulator import SensorNoise, simulate

    folder = root / f"loo_seed{seed}_noise{noise_factor:g}_v1"
    bags = []
    for scenario in SCENARIOS:
        path = folder / scenario
        if not (path / "metadata.yaml").exists():
            folder.mkdir(parents=True, exist_ok=True)
            base = SensorNoise()
            noise = replace(base, velocity=base.velocity * noise_factor, heading=base.heading * noise_factor)
            write_sim_bag(simulate(replace(build_config(scenario, seed=seed), noise=noise)), path)
        bags.append(path)
    return bags


def holdout_table(bags: list[Path], seed: int, q_span: float, tune_stiffness_noise: bool):  # noqa: ANN201
    """The tuner's leave-one-bag-out table on ``bags`` (its defaults, tuning seed 7 as before)."""
    from transplanter_ident.cli.tuner import load_bag, load_parameters
    from transplanter_ident.tuning.multi import MultiBagProblem, leave_one_out
    from transplanter_ident.tuning.tune import tune_problem

    params = load_parameters([])
    data = [load_bag(str(b), params, truth=True) for b in bags]
    epochs, truths = [d[0] for d in data], [d[1] for d in data]
    problem = MultiBagProblem.from_epochs(params.config, epochs, "nll", tune_stiffness_noise=tune_stiffness_noise,
                                          q_span=q_span)
    outcome = tune_problem(problem, seed=7)
    tuned = ", ".join(f"{n}={10.0**v:.3g}" for n, v in zip(problem.names, outcome.result.position, strict=True))

    def tune(fold: MultiBagProblem, fold_seed: int):  # noqa: ANN202
        return tune_problem(fold, seed=fold_seed).tuned_config

    return leave_one_out(problem, epochs, truths, [b.name for b in bags], tune, outcome.seed), tuned


def summary(tables: list) -> list[str]:  # noqa: ANN001
    """Bags meeting the acceptance, and pooled held-out |error| (default / single / others)."""
    count = sum(t.wins()[0] for t in tables)
    wins = [sum(t.wins()[i] for t in tables) for i in (1, 2, 3)]
    lines = [f"over {len(tables)} seeds: multi-bag <= default on {wins[0]}/{count} bags, <= single-bag (in-sample) "
             f"on {wins[1]}/{count}, <= single-bag tuned on one other bag (median) on {wins[2]}/{count}"]
    for label, keep in (("identifying drives", lambda n: n not in STEP_STEERS), ("step steers", STEP_STEERS.__contains__)):
        errors = np.array([[abs(v) for v in values] for t in tables for r in t.rows if keep(r.name)
                           for values in (r.final_cf, r.final_cr)])
        if not len(errors):
            continue
        excess = errors[:, 2] - errors[:, 0]
        lines.append(f"{label} ({len(errors)} entries, Cf and Cr): median |error| default {100 * np.median(errors[:, 0]):.2f} %, "
                     f"single {100 * np.median(errors[:, 1]):.2f} %, others {100 * np.median(errors[:, 2]):.2f} %; "
                     f"others <= default in {100 * np.mean(excess <= 0):.0f} %, worst excess {100 * excess.max():+.1f} "
                     f"points, excess > 1 point in {int(np.sum(excess > 0.01))}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[11], help="simulation seeds (one table each)")
    parser.add_argument("--noise-factor", type=float, default=1.0, help="GNSS velocity and heading noise x this")
    parser.add_argument("--q-span", type=float, default=1.0, help="tuner --q-span (decades; inf: the whole box)")
    parser.add_argument("--tune-stiffness-noise", action="store_true")
    args = parser.parse_args(argv)
    if not (math.isfinite(args.noise_factor) and args.noise_factor > 0):
        parser.error("--noise-factor must be positive")
    if not args.q_span > 0:
        parser.error("--q-span must be positive")
    tables = []
    for seed in args.seeds:
        table, tuned = holdout_table(make_bags(default_cache(), seed, args.noise_factor), seed, args.q_span,
                                     args.tune_stiffness_noise)
        print(f"seed {seed}, noise x{args.noise_factor:g}, q-span {args.q_span:g}"
              f"{', stiffness noise tuned' if args.tune_stiffness_noise else ', split Q'}; all bags: tuned {tuned}")
        print(table.format(), flush=True)
        tables.append(table)
    print("\n".join(summary(tables)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
