"""The filter's final estimate against the maximum likelihood (ML) of the same drive, both against the truth.

Not a test. When the filter misses the truth, is it the filter, or the data? The ML of (ln Cf, ln Cr)
is the minimum of the innovations' NLL of the filter with the stiffness held fixed (Nelder-Mead;
test_relinearization.maximum_likelihood). For ``--seeds`` drives of the project's sine drive (±15°,
6 s) at ``--speed`` for ``--duration`` s, it prints z = ln(estimate / truth) / the filter's relative
std of both, per seed and their mean and sd. An ML as far off as the filter means the data are.

Run: ``.venv/bin/python bench/maximum_likelihood_figures.py [--speed 1.2] [--duration 180] [--seeds 16]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import TRUE_CF, TRUE_CR, sine_drive  # noqa: E402
from helpers import epochs_from_result  # noqa: E402
from test_relinearization import maximum_likelihood  # noqa: E402

from transplanter_ident.config.parameters import EstimatorConfig  # noqa: E402
from transplanter_ident.ekf.joint_ekf import run_sequence  # noqa: E402
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD  # noqa: E402
from transplanter_ident.epochs.epoch import EpochArrays  # noqa: E402
from transplanter_ident.sim.simulator import simulate  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speed", type=float, default=1.2)
    parser.add_argument("--duration", type=float, default=180.0)
    parser.add_argument("--seeds", type=int, default=16)
    args = parser.parse_args(argv)
    if args.seeds < 1 or not args.speed > 0.0 or not args.duration > 30.0:
        parser.error("--seeds >= 1, --speed > 0 and --duration > 30 s")
    truth = np.log([TRUE_CF, TRUE_CR])
    rows = []
    for seed in range(args.seeds):
        sim = sine_drive(seed, speed=args.speed, duration=args.duration)
        epochs = EpochArrays(epochs_from_result(simulate(sim), sim.vehicle))
        last = run_sequence(EstimatorConfig(vehicle=sim.vehicle), epochs)[-1]
        estimate = np.log([last[O_CF], last[O_CR]])
        std = np.array([last[O_CF_STD] / last[O_CF], last[O_CR_STD] / last[O_CR]])
        rows.append(np.concatenate([(estimate - truth) / std, (maximum_likelihood(epochs, estimate) - truth) / std]))
        print(f"seed {seed:2d}: z filter {rows[-1][0]:+.2f} / {rows[-1][1]:+.2f}, ML {rows[-1][2]:+.2f} / "
              f"{rows[-1][3]:+.2f} (std {100 * std[0]:.1f} / {100 * std[1]:.1f} %)", flush=True)
    z = np.array(rows)
    print(f"{args.speed:g} m/s, {args.duration:g} s, {args.seeds} seeds: z of Cf / Cr, filter mean "
          f"{z[:, 0].mean():+.2f} / {z[:, 1].mean():+.2f} sd {z[:, 0].std():.2f} / {z[:, 1].std():.2f}; ML mean "
          f"{z[:, 2].mean():+.2f} / {z[:, 3].mean():+.2f} sd {z[:, 2].std():.2f} / {z[:, 3].std():.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
