"""CMA-ES, standard PSO (eqs. 15-16) and IPSO (eqs. 17-20) on equal budgets, 10 seeds, on a multi-bag objective.

Not a test. The objective is the tuner's: the innovation NLL (default) or eq. (21) (``--objective
mae``) of the default filter (exact/log/heading), averaged over four simulated two-minute drives
with their epoch counts as weights (sine, step20-ccw, step30-cw, surface-change; 600 epochs
each), over the whole log10 Q/R box of eq. (22) (``q_span`` inf: a harder search than the tuner's
default, which keeps Q within a decade of the start). The bags are generated once into
``$TRANSPLANTER_BENCH_CACHE`` (default ``<tmp>/transplanter_ident_bench``) and their epochs
come from the epoch cache.

For every seed, IPSO runs with the paper's settings (F = 20, k_max = 40); its evaluation count E
(initial swarm, updates and chaotic steps) is the budget of

* standard PSO: same F, k_max = ceil((E - F) / F), exactly E evaluations;
* CMA-ES (``cma``): lambda = F, generations until E evaluations are spent.

Two starts: **cold** (no warm start: the optimisers alone) and **warm** (the configured Q/R is
one of the first candidates, as in the tuner). Reported per start: the median over the seeds of
the best objective, the median rank (1 = best of the three on that seed) and the wins. The
candidates run on a process pool (``--jobs``, default the number of cores).

Run: ``python bench/optimizers_bench.py [--seeds N] [--objective nll|mae] [--jobs N]``;
``bench/run.py`` calls :func:`main`.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

from bench_util import ROOT, cached_bag, default_cache  # bench/ is on sys.path

sys.path.insert(0, str(ROOT))

from transplanter_ident.bags.cache import default_cache_dir, load_bag_epochs  # noqa: E402
from transplanter_ident.config.params_file import EstimatorParams  # noqa: E402
from transplanter_ident.tuning.cmaes import CmaesSettings, minimize_cmaes  # noqa: E402
from transplanter_ident.tuning.multi import MultiBagProblem  # noqa: E402
from transplanter_ident.tuning.parallel import default_jobs, open_backend  # noqa: E402
from transplanter_ident.tuning.pso import IpsoSettings, minimize, pso_for_budget  # noqa: E402

BAG_VERSION = "v1"
SCENARIOS = ("sine", "step20-ccw", "step30-cw", "surface-change")
METHODS = ("cmaes", "pso", "ipso")


def ensure_bags(cache: Path) -> list[Path]:
    """The four cached two-minute bags."""
    return [cached_bag(cache, f"opt_120s_{name}_{BAG_VERSION}", ["--scenario", name, "--duration", "120",
                                                                 "--seed", str(200 + i)])
            for i, name in enumerate(SCENARIOS)]


def run_seed(problem: MultiBagProblem, seed: int, warm: bool) -> dict[str, float]:
    """Best objective of each method on one seed, on IPSO's budget."""
    initial = problem.start[None, :] if warm else None
    box = problem.box
    ipso = minimize(problem, box, IpsoSettings(), seed, initial=initial)
    budget = ipso.evaluations
    pso = minimize(problem, box, pso_for_budget(budget), seed, initial=initial, max_evaluations=budget)
    iterations = math.ceil(budget / 20)
    cmaes = minimize_cmaes(problem, box, CmaesSettings(particles=20, iterations=iterations), seed, initial=initial,
                           max_evaluations=budget)
    assert pso.evaluations == cmaes.evaluations == budget
    return {"ipso": ipso.fitness, "pso": pso.fitness, "cmaes": cmaes.fitness, "budget": float(budget)}


def main(argv: list[str] | None = None) -> int:
    """Run every seed for both starts and print the medians."""
    parser = argparse.ArgumentParser(prog="optimizers_bench", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--objective", choices=("nll", "mae"), default="nll")
    parser.add_argument("--jobs", type=int, default=default_jobs())
    parser.add_argument("--cache", type=Path, default=default_cache())
    args = parser.parse_args(argv)

    params = EstimatorParams()
    bags = ensure_bags(args.cache)
    epochs = [load_bag_epochs(str(bag), params, default_cache_dir()).epochs for bag in bags]
    backend = open_backend(args.jobs)
    begin = time.perf_counter()
    try:
        problem = MultiBagProblem.from_epochs(params.config, epochs, args.objective, backend, q_span=math.inf)
        start_value = problem.evaluate_noise(params.config.noise)
        results = {warm: [run_seed(problem, seed, warm) for seed in range(args.seeds)] for warm in (False, True)}
    finally:
        backend.close()
    print(f"\noptimisers on equal budgets: {args.objective} over {len(bags)} bags ({', '.join(SCENARIOS)}; "
          f"{sum(map(len, epochs))} epochs), {args.seeds} seeds, IPSO F = 20, k_max = 40 sets the budget; "
          f"{time.perf_counter() - begin:.0f} s on {args.jobs} jobs ({os.cpu_count()} CPUs)")
    print(f"objective of the starting (default) Q/R: {start_value:.6g}")
    head = f"{'start':<7}{'method':<8}{'median best':>14}{'min':>12}{'max':>12}{'median rank':>13}{'wins':>6}"
    print(head)
    print("-" * len(head))
    for warm, rows in results.items():
        ranks = {m: [] for m in METHODS}
        wins = dict.fromkeys(METHODS, 0)
        for row in rows:
            order = sorted(METHODS, key=lambda m: row[m])
            for rank, method in enumerate(order, 1):
                ranks[method].append(rank)
            wins[order[0]] += 1
        for method in METHODS:
            values = [row[method] for row in rows]
            print(f"{'warm' if warm else 'cold':<7}{method:<8}{statistics.median(values):>14.6g}{min(values):>12.6g}"
                  f"{max(values):>12.6g}{statistics.median(ranks[method]):>13.1f}{wins[method]:>6}")
        budgets = [row["budget"] for row in rows]
        print(f"{'':<7}budget: median {statistics.median(budgets):.0f} evaluations "
              f"(min {min(budgets):.0f}, max {max(budgets):.0f})")
    print("-" * len(head))
    return 0


if __name__ == "__main__":
    sys.exit(main())
