"""Random drives the estimator is configured right for: is a valid estimate ever confidently wrong?

Not a test (test/test_random_drives.py asserts the pooled coverage on fewer draws). Each draw
(``--draws``, from ``--seed``) is one drive of the project's simulator with
its conditions drawn at random over what a transplanter meets: speed 1-3 m/s; a sine (+-5-25 deg,
period 3-14 s) or a multisine (+-5-20 deg, four periods of 2-16 s) steer; linear tires or tanh tires
of friction 0.3-0.9 (``ekf.min_friction`` is 0.3); Cf 5000-15000 N/rad, Cr 1-1.6 Cf; mass 600-1200
kg, lf 0.5-0.9 m, lr 0.3-0.7 m; GNSS at 5 or 10 Hz, its noise 0.5-1.5x the configured R; a steering
offset of +-2 deg; 180 s. The estimator gets the vehicle's constants and default parameters
otherwise. From 30 s on it prints, per draw, the share of epochs flagged valid, the share of those
whose +-2 sigma misses Cf or Cr, and the final errors; then the pooled figures and the draws whose
valid epochs missed the truth more than 5 % of the time, with their conditions.

Run: ``.venv/bin/python bench/random_drives.py [--draws 40] [--seed 0]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import ValidityFigures, pooled_validity_figures, random_drive  # noqa: E402
from test_validity import epochs_of  # noqa: E402

from transplanter_ident.config.parameters import EstimatorConfig  # noqa: E402
from transplanter_ident.sim.simulator import SimConfig, simulate  # noqa: E402

START = 30.0  # s


def judge(sim: SimConfig) -> ValidityFigures:
    """The drive through the estimator configured with its vehicle: validity and coverage from START on."""
    return pooled_validity_figures([(simulate(sim), EstimatorConfig(vehicle=sim.vehicle))], epochs_of, START)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    for index in range(args.draws):
        sim, what = random_drive(rng, args.seed * 1000 + index)
        figures = judge(sim)
        rows.append((figures, what))
        shown = f"{figures.missed:.2f}" if figures.valid > 0 else "    -"
        print(f"{index:3d} valid {figures.valid:.2f} missed {shown} final |error| Cf {100 * figures.finals[0]:5.1f} % "
              f"Cr {100 * figures.finals[1]:5.1f} % | {what}", flush=True)
    valid = np.array([f.valid for f, _ in rows])
    kept = np.array([f.kept for f, _ in rows])
    missed = float(np.sum(kept * np.array([f.missed for f, _ in rows])) / max(1, kept.sum()))
    print(f"{args.draws} draws: valid {valid.mean():.2f} of the epochs; valid and outside +-2 sigma "
          f"{missed:.3f} of the valid epochs; draws ever valid {int(np.sum(valid > 0))}")
    for figures, what in rows:
        if figures.valid > 0 and figures.missed > 0.05:
            print(f"  missed {figures.missed:.2f} of valid ({figures.valid:.2f} valid), final |error| Cf "
                  f"{100 * figures.finals[0]:.1f} % Cr {100 * figures.finals[1]:.1f} %: {what}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
