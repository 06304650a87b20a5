"""Low speed: does the +-2 sigma band cover the truth as often as it claims, in every epoch?

Not a test. Sine drives of the project's simulator at 0.8-1.2 m/s (180 s, linear tires, the
default sensor noise and parameters), ``--seeds`` seeds each: from 30 s on, pooled over the seeds,
the share of epochs whose +-2 sigma covers Cf and Cr (valid or not; 0.954 promised), the RMS and
mean of z = error / std. The speed's errors (ekf/update.py) matter most here: in a turn the heading
integrates the speed over many intervals. README "The speed is a measurement too" quotes it.

Run: ``.venv/bin/python bench/low_speed_figures.py [--seeds 24]``
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import run_drive, sine_drive, sine_steering  # noqa: E402

from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD  # noqa: E402

#: (speed m/s, sine amplitude deg, period s)
DRIVES = ((1.2, 15.0, 6.0), (1.2, 20.0, 10.0), (1.0, 15.0, 6.0), (1.0, 25.0, 14.0), (0.8, 25.0, 14.0))
START = 30.0  # s


def z_scores(speed: float, amplitude: float, period: float, seeds: int) -> np.ndarray:
    """(epochs, 2): z of Cf and Cr from START on, pooled over the seeds."""
    rows = []
    for seed in range(seeds):
        run = run_drive(sine_drive(seed, speed=speed, duration=180.0,
                                   steering=sine_steering(math.radians(amplitude), period)))
        out, kept = run.outputs, run.t >= START
        rows.append(np.column_stack(((out[kept, O_CF] - run.true_cf[kept]) / out[kept, O_CF_STD],
                                     (out[kept, O_CR] - run.true_cr[kept]) / out[kept, O_CR_STD])))
    return np.concatenate(rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=24)
    args = parser.parse_args(argv)
    print(f"seeds 0-{args.seeds - 1}, from {START:.0f} s on; covered = |z| <= 2 (Cf, Cr)")
    for speed, amplitude, period in DRIVES:
        z = z_scores(speed, amplitude, period, args.seeds)
        covered, rms, mean = np.mean(np.abs(z) <= 2.0, axis=0), np.sqrt(np.mean(z * z, axis=0)), np.mean(z, axis=0)
        print(f"{speed:.1f} m/s, +-{amplitude:.0f} deg / {period:.0f} s: covered {covered[0]:.3f} {covered[1]:.3f}  "
              f"rms z {rms[0]:.2f} {rms[1]:.2f}  mean z {mean[0]:+.2f} {mean[1]:+.2f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
