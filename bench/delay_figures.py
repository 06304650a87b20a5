"""Figures of ``tuner --estimate-delay`` (issue #13 item 4): the estimated gnss.delay on simulated drives.

Not a test (test/test_tuner_delay.py asserts the 10 ms acceptance on fewer seeds). For each true
delay (0, 40, 80, 120 ms; -40, -80 ms: the steering stamped that late) and each of ``--seeds`` seeds
(every drive its own seed: seeds ``i * N .. i * N + N - 1`` for the i-th delay), a scenario is
simulated with its GNSS stamped that late and :func:`transplanter_ident.tuning.delay.search_delay` runs on the tuner's objective (NLL
at the default Q/R) over the drive's samples, as ``tuner --estimate-delay`` does on one bag.
Prints the error (estimate - truth, ms) per delay and seed, and the median and worst |error|; and
the estimate's std (the NLL's curvature, what the tuner writes as ``ekf.delay_uncertainty``): its
median, and how often +-2 std covers the truth (0.95 claimed).

Run: ``.venv/bin/python bench/delay_figures.py [--scenario sine multisine] [--duration 120] [--seeds 10] [--cold]``
(``--cold``: without the warm start, the filter starting from ``ekf.initial_stiffness`` at every delay).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from helpers import sim_samples  # noqa: E402

from transplanter_ident.config.params_file import EstimatorParams  # noqa: E402
from transplanter_ident.sim.scenarios import build_config  # noqa: E402
from transplanter_ident.sim.simulator import simulate  # noqa: E402
from transplanter_ident.tuning.delay import estimate_delay, serial_scores  # noqa: E402

TRUE_DELAYS = (0.0, 0.04, 0.08, 0.12, -0.04, -0.08)  # negative: the steering stamped late


def errors_ms(scenario: str, duration: float, seeds: int, warm: bool) -> dict[float, list[tuple[float, float]]]:
    """(estimate - truth, the estimate's std) in ms per true delay, one entry per seed."""
    params = EstimatorParams()
    table: dict[float, list[tuple[float, float]]] = {}
    for index, true in enumerate(TRUE_DELAYS):
        for seed in range(index * seeds, (index + 1) * seeds):
            samples = sim_samples(simulate(build_config(scenario, duration=duration, seed=seed, gnss_delay=true)))
            estimate = estimate_delay(serial_scores([samples], params, "nll", warm=warm), "nll")
            table.setdefault(true, []).append((1e3 * (estimate.delay - true), 1e3 * estimate.std))
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", nargs="+", default=["sine", "multisine"])
    parser.add_argument("--duration", type=float, default=120.0)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--cold", action="store_true")
    args = parser.parse_args(argv)
    for scenario in args.scenario:
        start = time.perf_counter()
        table = errors_ms(scenario, args.duration, args.seeds, warm=not args.cold)
        for true, errors in table.items():
            print(f"{scenario} {args.duration:g} s, true {1e3 * true:.0f} ms: estimate - truth (ms) "
                  + " ".join(f"{e:+.0f}" for e, _ in errors))
        every = np.array([e for errors in table.values() for e, _ in errors])
        std = np.array([s for errors in table.values() for _, s in errors])
        print(f"{scenario}: median error {np.median(every):+.1f} ms, median |error| {np.median(np.abs(every)):.1f} ms, "
              f"worst |error| {np.max(np.abs(every)):.0f} ms, within 10 ms {np.sum(np.abs(every) <= 10.0)}/{len(every)}; "
              f"std median {np.median(std):.2f} ms, |error| <= 2 std {np.sum(np.abs(every) <= 2.0 * std)}/{len(every)}, "
              f"<= 3 std {np.sum(np.abs(every) <= 3.0 * std)}/{len(every)} ({time.perf_counter() - start:.0f} s)",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
