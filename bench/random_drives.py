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

``--independent``: the drives come from the simulator that shares no code with the package's
(test/independent_sim.py: adaptive RK45, Magic Formula tires of friction 0.3-0.9, or 5 for a nearly
linear tire, the project's sensor noise): sine steers only, speed, stiffness, vehicle and GNSS rate
drawn as above, and an antenna lever arm (x -0.5-1.0 m, y +-0.6 m) the estimator is told.

``--course``: one antenna (``ekf.measurement: course``, the velocity and steering streams only; the GNSS
timing stated to 2 ms as ``ekf.delay_uncertainty``, and ``validity.max_rel_std`` 0.08 for its precision).

``--relaxation LOW HIGH``: every drive's tires relax over a length drawn from [LOW, HIGH] m (from a
generator of its own, so the other conditions are those of the same seed without it) that the
estimator is not told; each draw is then also judged without the validity's relaxation check
(``validity.max_relaxation_*`` 100), and the pooled line says both.

Run: ``.venv/bin/python bench/random_drives.py [--draws 40] [--seed 0] [--independent] [--course]
[--relaxation LOW HIGH]``
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import ValidityFigures, judged_figures, pooled_validity_figures, random_drive, run_course  # noqa: E402
from independent_sim import independent_drive  # noqa: E402
from test_validity import epochs_of  # noqa: E402

from transplanter_ident.config.parameters import (  # noqa: E402
    EstimatorConfig,
    FilterOptions,
    ValiditySettings,
    VehicleParams,
)
from transplanter_ident.evaluation.validity import decide_sequence  # noqa: E402
from transplanter_ident.sim.simulator import SimResult, simulate  # noqa: E402

START = 30.0  # s


def independent_random_drive(rng: np.random.Generator, seed: int,
                             relaxation: float = 0.0) -> tuple[SimResult, VehicleParams, str]:
    """A sine drive of the independent simulator with its conditions drawn from ``rng``, its vehicle, a line."""
    speed, amplitude, period = rng.uniform(1.0, 3.0), rng.uniform(5.0, 25.0), rng.uniform(3.0, 14.0)
    friction = 5.0 if rng.random() < 0.4 else rng.uniform(0.3, 0.9)
    cf = rng.uniform(5000.0, 15000.0)
    cr = cf * rng.uniform(1.0, 1.6)
    vehicle = VehicleParams(mass=rng.uniform(600.0, 1200.0), lf=rng.uniform(0.5, 0.9), lr=rng.uniform(0.3, 0.7),
                            antenna_x=rng.uniform(-0.5, 1.0), antenna_y=rng.uniform(-0.6, 0.6))
    rate = float(rng.choice([5.0, 10.0]))
    result = independent_drive(seed, speed=speed, amplitude_deg=amplitude, period=period, duration=180.0,
                               gnss_rate=rate, friction=friction, cf=cf, cr=cr, vehicle=vehicle,
                               relaxation_length=relaxation)
    return result, vehicle, (f"{speed:.1f} m/s, sine +-{amplitude:.0f} deg/{period:.1f} s, Magic Formula mu "
                             f"{friction:.2f}, Cf {cf:.0f} Cr {cr:.0f}, m {vehicle.mass:.0f} lf {vehicle.lf:.2f} lr "
                             f"{vehicle.lr:.2f}, antenna {vehicle.antenna_x:+.2f}/{vehicle.antenna_y:+.2f} m, "
                             f"{rate:.0f} Hz")


#: the validity without the relaxation check (``--relaxation``'s comparison)
UNCHECKED = ValiditySettings(max_relaxation_sigmas=100.0, max_relaxation_shift=100.0)


#: ``--course``: a single antenna, the GNSS timing stated to 2 ms, and the validity a user would set for its precision
COURSE = FilterOptions(measurement="course", delay_uncertainty=0.002)
COURSE_VALIDITY = ValiditySettings(max_rel_std=0.08)


def judge(result: SimResult, vehicle: VehicleParams, settings: ValiditySettings | None = None) -> ValidityFigures:
    """The drive through the estimator configured with its vehicle: validity and coverage from START on."""
    def epochs_for(drive: SimResult):  # noqa: ANN202 - the validity's epochs, with the vehicle's lever arm
        return epochs_of(drive, antenna_x=vehicle.antenna_x, antenna_y=vehicle.antenna_y)

    return pooled_validity_figures([(result, EstimatorConfig(vehicle=vehicle))], epochs_for, START, settings)


def judge_course(result: SimResult, vehicle: VehicleParams) -> ValidityFigures:
    """:func:`judge` with one antenna (its velocity and steering streams, ``ekf.measurement: course``)."""
    config = EstimatorConfig(vehicle=vehicle, options=COURSE)
    run, epochs = run_course(result, config)
    return judged_figures([(run, decide_sequence(config, COURSE_VALIDITY, epochs, run.outputs))], START)


def pooled_line(rows: list[tuple[ValidityFigures, str]]) -> str:
    """Valid share of the epochs, and the share of the valid epochs outside +-2 sigma, over the draws."""
    valid = np.array([f.valid for f, _ in rows])
    kept = np.array([f.kept for f, _ in rows])
    missed = float(np.sum(kept * np.array([f.missed for f, _ in rows])) / max(1, kept.sum()))
    return (f"valid {valid.mean():.2f} of the epochs; valid and outside +-2 sigma {missed:.3f} of the valid epochs; "
            f"draws ever valid {int(np.sum(valid > 0))}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--independent", action="store_true", help="drives of test/independent_sim.py")
    parser.add_argument("--course", action="store_true", help="one antenna: ekf.measurement course, the timing "
                        "stated to 2 ms (ekf.delay_uncertainty), validity.max_rel_std 0.08")
    parser.add_argument("--relaxation", nargs=2, type=float, metavar=("LOW", "HIGH"),
                        help="tires relaxing over a length drawn from [LOW, HIGH] m, not told to the estimator")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    lengths = np.random.default_rng(args.seed + 10_000)  # its own stream: the other conditions stay the seed's
    rows, unchecked = [], []
    for index in range(args.draws):
        length = float(lengths.uniform(*args.relaxation)) if args.relaxation else 0.0
        if args.independent:
            result, vehicle, what = independent_random_drive(rng, args.seed * 1000 + index, length)
        else:
            sim, what = random_drive(rng, args.seed * 1000 + index)
            result, vehicle = simulate(replace(sim, relaxation_length=length)), sim.vehicle
        what += f", relaxation {length:.2f} m" if args.relaxation else ""
        figures = judge_course(result, vehicle) if args.course else judge(result, vehicle)
        rows.append((figures, what))
        if args.relaxation:
            unchecked.append((judge(result, vehicle, UNCHECKED), what))
        shown = f"{figures.missed:.2f}" if figures.valid > 0 else "    -"
        print(f"{index:3d} valid {figures.valid:.2f} missed {shown} final |error| Cf {100 * figures.finals[0]:5.1f} % "
              f"Cr {100 * figures.finals[1]:5.1f} % | {what}", flush=True)
    print(f"{args.draws} draws: {pooled_line(rows)}")
    if unchecked:
        print(f"without the relaxation check: {pooled_line(unchecked)}")
    for figures, what in rows:
        if figures.valid > 0 and figures.missed > 0.05:
            print(f"  missed {figures.missed:.2f} of valid ({figures.valid:.2f} valid), final |error| Cf "
                  f"{100 * figures.finals[0]:.1f} % Cr {100 * figures.finals[1]:.1f} %: {what}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
