"""IPSO (eqs. 17-20) against standard PSO (eqs. 15-16) on equal evaluation budgets, median over 20 seeds.

Not a test (slow); test/test_optimize.py has a 5-seed version. For every seed, IPSO runs with the
paper's settings (F = 20, k_max = 40, c1 = 1, c2 = 1.5, c3 = 2, N = 5, N_max = 10, R_d = 10 %
of the box width, lambda = 4, delta = 1e-6); its evaluation count E (initial swarm, updates and
chaotic steps) is the budget of

* standard PSO: same F, k_max = ceil((E - F) / F) and exactly E evaluations;
* IPSO without the detection-radius term (c3 = 0; chaotic search kept), an ablation;
* random search: the best of E uniform samples (the baseline).

Problems (6-D): Rastrigin and Ackley, each centred (optimum at the box centre) and shifted
(optimum moved off the centre: eq. 17's R(k) converges to the box centre, which flatters any
method on a centred optimum), and the tuning objective (eq. 21, mae) of the ``step20-ccw``
sample bag over the log10 Q/R box (no warm start here, to compare the optimisers alone).

Run: ``python bench/ipso_vs_pso.py [--seeds N] [--no-tuning]``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from transplanter_ident.tuning.benchmark_functions import ackley, random_search, rastrigin, shifted  # noqa: E402
from transplanter_ident.tuning.box import Box  # noqa: E402
from transplanter_ident.tuning.pso import IpsoSettings, minimize, pso_for_budget  # noqa: E402

SHIFT = np.array([1.3, -2.1, 0.7, 2.9, -0.4, 1.8])


def problems(with_tuning: bool) -> list[tuple[str, Callable[[np.ndarray], np.ndarray], Box]]:
    """(name, batch objective, box) of every benchmark problem."""
    rastrigin_box, ackley_box = Box.cube(6, -5.12, 5.12), Box.cube(6, -32.768, 32.768)
    rows = [
        ("Rastrigin (centred)", rastrigin, rastrigin_box),
        ("Rastrigin (shifted)", shifted(rastrigin, SHIFT), rastrigin_box),
        ("Ackley (centred)", ackley, ackley_box),
        ("Ackley (shifted)", shifted(ackley, 5.0 * SHIFT), ackley_box),
    ]
    if with_tuning:
        from transplanter_ident.bags.samples import ensure_bag
        from transplanter_ident.cli.tuner import load_bag
        from transplanter_ident.config.params_file import EstimatorParams
        from transplanter_ident.tuning.problem import TuningProblem

        params = EstimatorParams()
        bag = ensure_bag("step20-ccw", ROOT / "bags", Path(tempfile.gettempdir()) / "transplanter_ident_bench")
        epochs, _ = load_bag(str(bag), params)
        problem = TuningProblem.from_epochs(params.config, epochs, "mae", q_span=math.inf)  # the whole box
        rows.append(("step20-ccw tuning (mae, eq. 21)", problem, problem.box))
    return rows


def compare(objective: Callable[[np.ndarray], np.ndarray], box: Box, seeds: range) -> dict[str, list[float]]:
    """Final best fitness per method and seed; 'evaluations' holds the budgets."""
    out: dict[str, list[float]] = {"ipso": [], "pso": [], "ipso_c3_0": [], "random": [], "evaluations": []}
    for seed in seeds:
        ipso = minimize(objective, box, IpsoSettings(), seed)
        budget = ipso.evaluations
        pso = minimize(objective, box, pso_for_budget(budget), seed, max_evaluations=budget)
        ablation = minimize(objective, box, IpsoSettings(c3=0.0), seed, max_evaluations=budget)
        rand = random_search(objective, box, budget, seed)
        assert pso.evaluations == rand.evaluations == budget
        for key, result in (("ipso", ipso), ("pso", pso), ("ipso_c3_0", ablation), ("random", rand)):
            out[key].append(result.fitness)
        out["evaluations"].append(budget)
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the comparison and print the medians."""
    parser = argparse.ArgumentParser(prog="ipso_vs_pso", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=20, help="seeds per problem (default 20)")
    parser.add_argument("--no-tuning", action="store_true", help="skip the step20-ccw tuning problem")
    args = parser.parse_args(argv)
    seeds = range(args.seeds)
    print(f"\nIPSO vs PSO on equal evaluation budgets: median (and IQR) of the final best over {args.seeds} seeds")
    head = (f"{'problem':<32}{'evals':>6}{'IPSO':>29}{'PSO':>29}{'IPSO c3=0':>29}{'random':>29}"
            f"{'IPSO<PSO':>10}{'time':>6}")
    print(head)
    print("-" * len(head))
    for name, objective, box in problems(not args.no_tuning):
        begin = time.perf_counter()
        result = compare(objective, box, seeds)
        wins = sum(a < b for a, b in zip(result["ipso"], result["pso"], strict=True))

        def cell(values: list[float]) -> str:
            q1, q2, q3 = np.percentile(values, [25, 50, 75])
            return f"{q2:.5g} [{q1:.4g}, {q3:.4g}]"

        evals = statistics.median(result["evaluations"])
        print(f"{name:<32}{evals:>6.0f}{cell(result['ipso']):>29}{cell(result['pso']):>29}"
              f"{cell(result['ipso_c3_0']):>29}{cell(result['random']):>29}{wins:>6}/{args.seeds:<3}"
              f"{time.perf_counter() - begin:>5.0f}s", flush=True)
    print("-" * len(head))
    print("evals = median evaluations per run (IPSO's count, chaotic steps included; every method got exactly it); "
          "IPSO<PSO = seeds where IPSO ended lower")
    return 0


if __name__ == "__main__":
    sys.exit(main())
