"""Low speed: is the stiffness biased, and does the bias come with the sensor noise?

Not a test. The project's simulator at 1.3 and 2 m/s (+-18 deg sine of 10.9 s, 180 s, linear tires),
``--seeds`` seeds: the mean relative error of Cf and Cr over each drive from 60 s on, averaged over the
seeds with its standard error, with the default sensor noise, a tenth of it and none; and, with the
default noise, the filter started at the true stiffness and the filter without its re-linearised
start (one pass). docs/robustness.md ("The bias comes with the noise") quotes it.

Run: ``.venv/bin/python bench/noise_bias_figures.py [--seeds 16]``
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import TRUE_CF, TRUE_CR, run_drive, sine_drive, sine_steering  # noqa: E402

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, NoiseParams  # noqa: E402
from transplanter_ident.sim.simulator import SensorNoise  # noqa: E402

START = 60.0  # s
CONFIGS = {
    "defaults": EstimatorConfig(),
    "started at the truth": EstimatorConfig(noise=NoiseParams(initial_stiffness=(TRUE_CF, TRUE_CR),
                                                              initial_covariance=(1.0e-2, 1.0e-2, 0.01, 0.01))),
    "one pass": EstimatorConfig(options=FilterOptions(relinearization_window=0.0)),
}


def mean_errors(speed: float, noise_factor: float, config: EstimatorConfig, seeds: int) -> np.ndarray:
    """(seeds, 2): the mean relative error of Cf and Cr from START on, per seed."""
    base = SensorNoise()
    noise = replace(base, velocity=noise_factor * base.velocity, heading=noise_factor * base.heading,
                    steering=noise_factor * base.steering)
    rows = []
    for seed in range(seeds):
        run = run_drive(sine_drive(seed, speed=speed, duration=180.0, noise=noise,
                                   steering=sine_steering(math.radians(18.0), 10.9)), config)
        after = run.t >= START
        rows.append(((run.cf[after] / run.true_cf[after] - 1.0).mean(), (run.cr[after] / run.true_cr[after] - 1.0).mean()))
    return np.array(rows)


def line(label: str, errors: np.ndarray) -> str:
    mean, standard_error = errors.mean(axis=0), errors.std(axis=0) / math.sqrt(len(errors))
    return (f"{label:<44} Cf {100 * mean[0]:+.2f} +- {100 * standard_error[0]:.2f} %   "
            f"Cr {100 * mean[1]:+.2f} +- {100 * standard_error[1]:.2f} %")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=16)
    args = parser.parse_args(argv)
    print(f"mean relative error from {START:g} s on, mean +- standard error over seeds 0-{args.seeds - 1}")
    for speed in (1.3, 2.0):
        for factor in (1.0, 0.1, 0.0):
            seeds = args.seeds if factor > 0.0 else 1  # without noise every seed is the same drive
            print(line(f"{speed} m/s, noise x{factor:g}", mean_errors(speed, factor, CONFIGS["defaults"], seeds)))
        for name in ("started at the truth", "one pass"):
            print(line(f"{speed} m/s, noise x1, {name}", mean_errors(speed, 1.0, CONFIGS[name], args.seeds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
