"""A single antenna (``ekf.measurement: course``): what the estimate is worth without a heading.

Not a test (test/test_single_antenna.py asserts the claims on fewer drives). Each row is the
identification drive (2 m/s, +-15 deg sine of 6 s, 5 Hz GNSS, 120 s) changed as it says, from the
package's simulator or the independent one (test/independent_sim.py: Magic Formula tires, RK45),
its velocity and steering streams only, filtered with the defaults and ``ekf.measurement: course``,
``ekf.delay_uncertainty`` as given (one antenna's course cannot show a GNSS timing error, so the
validity needs it stated). From 30 s on, per row over ``--seeds`` seeds: the share of epochs valid
with ``validity.max_rel_std`` 0.05 (the default until session 38) and 0.08 (since), the share of those valid epochs outside
+-2 sigma, the share of all epochs outside it, the final |error| (median, worst) and the final
relative 1-sigma (median, the larger of Cf's and Cr's).

Run: ``.venv/bin/python bench/single_antenna_figures.py [--seeds 6] [--delay-uncertainty 0.002] [ROW ...]``.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import LATE_DROP, run_course, sine_drive, sine_steering  # noqa: E402
from independent_sim import independent_drive  # noqa: E402

from transplanter_ident.config.parameters import (  # noqa: E402
    EstimatorConfig,
    FilterOptions,
    ValiditySettings,
    VehicleParams,
)
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD  # noqa: E402
from transplanter_ident.evaluation.validity import decide_sequence  # noqa: E402
from transplanter_ident.sim.signals import step_steering  # noqa: E402
from transplanter_ident.sim.simulator import SimResult, simulate  # noqa: E402

ARM = VehicleParams(antenna_x=0.8, antenna_y=0.5)
#: row -> (simulator, its overrides, the vehicle the estimator is told)
ROWS: dict[str, tuple[str, dict[str, object], VehicleParams]] = {
    "2 m/s": ("package", {}, VehicleParams()),
    "1.5 m/s, 300 s": ("package", {"speed": 1.5, "duration": 300.0}, VehicleParams()),
    "1.2 m/s, 300 s": ("package", {"speed": 1.2, "duration": 300.0}, VehicleParams()),
    "steering offset 2 deg": ("package", {"steering_offset": math.radians(2.0)}, VehicleParams()),
    "stiffness dropping 40 % at 75 s, 150 s": ("package", {"stiffness": LATE_DROP, "duration": 150.0}, VehicleParams()),
    "paper's step: 20 deg held at 1 m/s, 90 s": ("package", {"speed": 1.0, "duration": 90.0, "steering":
                                                  step_steering(math.radians(20.0), start=2.0, ramp=0.5)},
                                                 VehicleParams()),
    "GNSS 10 Hz": ("package", {"gnss_rate": 10.0}, VehicleParams()),
    "tanh tire mu 0.3, +-25 deg": ("package", {"tire": "saturating", "friction": 0.3,
                                               "steering": sine_steering(math.radians(25.0), 6.0)}, VehicleParams()),
    "tanh tire mu 0.2 (below ekf.min_friction)": ("package", {"tire": "saturating", "friction": 0.2},
                                                  VehicleParams()),
    "GNSS 5 ms late, unset": ("package", {"gnss_delay": 0.005}, VehicleParams()),
    "GNSS 10 ms late, unset": ("package", {"gnss_delay": 0.010}, VehicleParams()),
    "independent mu 0.8, antenna (0.8, 0.5) m": ("independent", {"friction": 0.8}, ARM),
    "independent mu 0.3, antenna (0.8, 0.5) m": ("independent", {"friction": 0.3}, ARM),
    "independent nearly linear tires": ("independent", {"friction": 5.0}, VehicleParams()),
}
LIMITS = (0.05, 0.08)


def drive(name: str, seed: int) -> SimResult:
    simulator, overrides, vehicle = ROWS[name]
    if simulator == "independent":
        return independent_drive(seed, vehicle=vehicle, **overrides)
    return simulate(sine_drive(seed, **overrides))


def row_figures(name: str, seeds: int, delay_uncertainty: float) -> str:
    vehicle = ROWS[name][2]
    config = EstimatorConfig(vehicle=vehicle, options=FilterOptions(measurement="course",
                                                                    delay_uncertainty=delay_uncertainty))
    valid_shares, missed, outside, finals, stds = [[] for _ in LIMITS], [], [], [], []
    for seed in range(seeds):
        run, epochs = run_course(drive(name, seed), config)
        outputs, t = run.outputs, run.t
        after = t >= 30.0
        front, rear = run.covered()
        miss = ~(front & rear)
        for k, limit in enumerate(LIMITS):
            valid = decide_sequence(config, replace(ValiditySettings(), max_rel_std=limit), epochs, outputs) & after
            valid_shares[k].append(float(np.mean(valid[after])))
            if limit == LIMITS[-1]:
                missed.extend(miss[valid].tolist())
        outside.append(float(np.mean(miss[after])))
        finals.extend(abs(e) for e in run.final_errors())
        stds.append(max(outputs[-1, O_CF_STD] / outputs[-1, O_CF], outputs[-1, O_CR_STD] / outputs[-1, O_CR]))
    shares = " ".join(f"{np.mean(v):6.2f}" for v in valid_shares)
    missed_valid = f"{np.mean(missed):6.3f}" if missed else "     -"
    return (f"{shares} {missed_valid} {np.mean(outside):8.3f} {100 * np.median(finals):8.1f} "
            f"{100 * np.max(finals):6.1f} {100 * np.median(stds):7.1f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rows", nargs="*", help="rows to run (default: all)")
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--delay-uncertainty", type=float, default=0.002, help="ekf.delay_uncertainty, s")
    args = parser.parse_args(argv)
    names = args.rows or list(ROWS)
    unknown = [n for n in names if n not in ROWS]
    if unknown:
        parser.error(f"unknown rows {unknown}; rows: {list(ROWS)}")
    print(f"ekf.measurement course, ekf.delay_uncertainty {args.delay_uncertainty:g} s, {args.seeds} seeds, from 30 s")
    print(f"{'row':<42}{'valid@5%':>7}{'@8%':>7} {'missed':>6} {'outside':>8} {'final %':>8} {'worst':>6} "
          f"{'std %':>7}")
    for name in names:
        print(f"{name:<42}{row_figures(name, args.seeds, args.delay_uncertainty)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
