"""What ``tuner --estimate-delay``'s std buys: the estimator at the estimated delay, with and without it.

Not a test (test/test_tuner_delay.py asserts the std's calibration). Groups of ``--bags`` simulated
drives (``--scenario``, 120 s, GNSS ``--delay`` s late, every drive its own seed) are searched together
as ``tuner --estimate-delay`` does (:func:`transplanter_ident.tuning.delay.estimate_delay`, NLL at the
default Q/R); then each drive is filtered at the estimated ``gnss.delay`` with ``ekf.delay_uncertainty``
0 and with the estimate's std, and judged from 30 s on: the share of epochs flagged valid, the share of
those whose +-2 sigma misses Cf or Cr, and the final |error|.

Run: ``.venv/bin/python bench/delay_trust_figures.py [--groups 10] [--bags 1] [--delay 0.04] [--scenario sine]``
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import Run  # noqa: E402
from helpers import sim_samples  # noqa: E402

from transplanter_ident.config.parameters import ValiditySettings  # noqa: E402
from transplanter_ident.config.params_file import EstimatorParams  # noqa: E402
from transplanter_ident.ekf.joint_ekf import run_sequence  # noqa: E402
from transplanter_ident.evaluation.validity import decide_sequence  # noqa: E402
from transplanter_ident.sim.scenarios import build_config  # noqa: E402
from transplanter_ident.sim.simulator import SimResult, simulate  # noqa: E402
from transplanter_ident.tuning.delay import assemble_epochs, estimate_delay, serial_scores, with_delay  # noqa: E402

START = 30.0  # s


def judged(result: SimResult, samples: list, params: EstimatorParams, uncertainty: float) -> tuple[float, float, float]:
    """(valid share, share of valid epochs the band misses (NaN: none valid), worst final |error|) of one drive."""
    config = params.config
    config = replace(config, options=replace(config.options, delay_uncertainty=uncertainty))
    epochs = assemble_epochs(samples, params, params.gnss.delay)
    outputs = run_sequence(config, epochs)
    t = np.asarray(epochs.t)
    run = Run(t, outputs, np.interp(t, result.gnss_time, result.truth_cf), np.interp(t, result.gnss_time, result.truth_cr))
    valid = decide_sequence(config, ValiditySettings(), epochs, outputs)
    after = t >= START
    kept = valid & after
    front, rear = run.covered()
    missed = float(np.mean(~(front & rear)[kept])) if kept.any() else float("nan")
    return float(np.mean(kept[after])), missed, max(abs(e) for e in run.final_errors())


def _mean_missed(drives: list[tuple[float, float, float]]) -> float:
    """The mean over drives of the share of valid epochs missed (drives never valid left out; 0 if none)."""
    shares = [d[1] for d in drives if not math.isnan(d[1])]
    return float(np.mean(shares)) if shares else 0.0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--groups", type=int, default=10)
    parser.add_argument("--bags", type=int, default=1, help="drives searched together (a multi-bag tuner run)")
    parser.add_argument("--delay", type=float, default=0.04, help="s, the GNSS delay of every drive")
    parser.add_argument("--scenario", default="sine")
    args = parser.parse_args(argv)
    params = EstimatorParams()
    rows: dict[str, list[tuple[float, float, float]]] = {"without the std": [], "with the std": []}
    for group in range(args.groups):
        seeds = range(200 + group * args.bags, 200 + (group + 1) * args.bags)
        results = [simulate(build_config(args.scenario, duration=120.0, seed=s, gnss_delay=args.delay)) for s in seeds]
        samples = [sim_samples(r) for r in results]
        estimate = estimate_delay(serial_scores(samples, params, "nll"), "nll")
        at = with_delay(params, estimate.delay)
        line = f"group {group}: delay {1e3 * (estimate.delay - args.delay):+.0f} ms off, std {1e3 * estimate.std:.1f} ms"
        for (name, figures), uncertainty in zip(rows.items(), (0.0, estimate.std), strict=True):
            drives = [judged(r, s, at, uncertainty) for r, s in zip(results, samples, strict=True)]
            figures.extend(drives)
            line += f" | {name}: valid {np.mean([d[0] for d in drives]):.2f}, missed {_mean_missed(drives):.3f}"
        print(line, flush=True)
    for name, figures in rows.items():
        worst = max((d[1] for d in figures if not math.isnan(d[1])), default=0.0)
        print(f"{args.scenario}, {args.bags} bag(s) per search, {args.groups} searches, {name}: valid "
              f"{np.mean([d[0] for d in figures]):.3f}, valid and outside +-2 sigma {_mean_missed(figures):.3f} "
              f"(worst drive {worst:.2f}), final |error| median {100 * np.median([d[2] for d in figures]):.1f} %, "
              f"worst {100 * max(d[2] for d in figures):.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
