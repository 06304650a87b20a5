"""A steering sensor knocked mid-drive: its offset steps at 60 s of the 180 s identification drive.

Not a test. For steps of 0.25-2 deg, ``--seeds`` seeds, with ``ekf.change_offset_variance`` at its
default and at 0 (the alarm re-opens the stiffness only): from 60 s on, the share of epochs valid, the
share of those outside +-2 sigma, the change alarms, and the median and worst final error (the worse
of Cf and Cr). docs/real_sensors.md ("A steering sensor knocked or re-mounted") quotes it;
test/test_change.py asserts seeds 0-5 (its ``knocked_sensor`` drive is the one used here).

Run: ``.venv/bin/python bench/knocked_sensor_figures.py [--seeds 8]``
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from test_change import knocked_sensor  # noqa: E402

from transplanter_ident.config.parameters import FilterOptions  # noqa: E402
from transplanter_ident.ekf.layout import O_CHANGE  # noqa: E402

STEPS = (0.0, 0.25, 0.5, 1.0, 2.0)  # deg


def figures(step: float, options: FilterOptions, seeds: int) -> str:
    valid, covered, alarms, finals = [], [], 0, []
    for seed in range(seeds):
        v, c, run = knocked_sensor(step, seed, options)
        valid.append(v)
        covered.append(c)
        alarms += int(np.count_nonzero(run.outputs[run.t >= 60.0, O_CHANGE] > 0.0))
        finals.append(max(abs(e) for e in run.final_errors()))
    v, c = np.concatenate(valid), np.concatenate(covered)
    missed = (v & ~c).sum() / max(int(v.sum()), 1)
    return (f"valid {v.mean():5.2f}  outside +-2 sigma {missed:6.3f}  alarms {alarms:4d}  "
            f"final error median {100 * np.median(finals):4.1f} % worst {100 * max(finals):4.1f} %")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    args = parser.parse_args(argv)
    variants = {"defaults": FilterOptions(), "change_offset_variance 0": replace(FilterOptions(),
                                                                                change_offset_variance=0.0)}
    print(f"steering offset stepping at 60 s of 180 s, seeds 0-{args.seeds - 1}, from 60 s on")
    for step in STEPS:
        for name, options in variants.items():
            print(f"{step:4.2f} deg, {name:<26} {figures(step, options, args.seeds)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
