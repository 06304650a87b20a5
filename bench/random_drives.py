"""Random drives the estimator is configured right for: is a valid estimate ever confidently wrong?

Not a test. Each draw (``--draws``, from ``--seed``) is one drive of the project's simulator with
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
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import run_drive, sine_drive  # noqa: E402
from test_validity import epochs_of  # noqa: E402

from transplanter_ident.config.parameters import EstimatorConfig, ValiditySettings, VehicleParams  # noqa: E402
from transplanter_ident.evaluation.validity import decide_sequence  # noqa: E402
from transplanter_ident.sim.signals import StiffnessSchedule, multisine_steering, sine_steering  # noqa: E402
from transplanter_ident.sim.simulator import SensorNoise, SimConfig, simulate  # noqa: E402

START = 30.0  # s


def draw(rng: np.random.Generator, seed: int) -> tuple[SimConfig, str]:
    """One random drive and a line that says what it is."""
    speed = rng.uniform(1.0, 3.0)
    if rng.random() < 0.5:
        amplitude, period = rng.uniform(5.0, 25.0), rng.uniform(3.0, 14.0)
        steering, steer = sine_steering(math.radians(amplitude), period), f"sine +-{amplitude:.0f} deg/{period:.1f} s"
    else:
        amplitude, periods = rng.uniform(5.0, 20.0), tuple(float(p) for p in np.sort(rng.uniform(2.0, 16.0, 4)))
        steering = multisine_steering(math.radians(amplitude), periods, seed=seed)
        steer = f"multisine +-{amplitude:.0f} deg"
    tire, friction = ("linear", 0.8) if rng.random() < 0.4 else ("saturating", rng.uniform(0.3, 0.9))
    cf = rng.uniform(5000.0, 15000.0)
    cr = cf * rng.uniform(1.0, 1.6)
    vehicle = VehicleParams(mass=rng.uniform(600.0, 1200.0), lf=rng.uniform(0.5, 0.9), lr=rng.uniform(0.3, 0.7))
    rate = float(rng.choice([5.0, 10.0]))
    noise_factor = rng.uniform(0.5, 1.5)
    base = SensorNoise()
    noise = replace(base, velocity=noise_factor * base.velocity, heading=noise_factor * base.heading)
    offset = rng.uniform(-2.0, 2.0)
    sim = sine_drive(seed, duration=180.0, speed=speed, steering=steering, tire=tire, friction=friction,
                     stiffness=StiffnessSchedule(front=(cf,), rear=(cr,)), vehicle=vehicle, gnss_rate=rate,
                     noise=noise, steering_offset=math.radians(offset))
    tires = "linear" if tire == "linear" else f"tanh mu {friction:.2f}"
    return sim, (f"{speed:.1f} m/s, {steer}, {tires}, Cf {cf:.0f} Cr {cr:.0f}, m {vehicle.mass:.0f} lf {vehicle.lf:.2f} "
                 f"lr {vehicle.lr:.2f}, {rate:.0f} Hz, noise x{noise_factor:.1f}, offset {offset:+.1f} deg")


def judge(sim: SimConfig) -> tuple[float, float, float, float]:
    """(valid share, share of the valid epochs the band misses (NaN: none), final Cf error, final Cr error)."""
    result = simulate(sim)
    config = EstimatorConfig(vehicle=sim.vehicle)
    run = run_drive(result, config)
    valid = decide_sequence(config, ValiditySettings(), epochs_of(result), run.outputs)
    after = run.t >= START
    kept = valid & after
    front, rear = run.covered()
    missed = float(np.mean(~(front & rear)[kept])) if kept.any() else math.nan
    return (float(np.mean(kept[after])), missed, *run.final_errors())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    for index in range(args.draws):
        sim, what = draw(rng, args.seed * 1000 + index)
        valid, missed, cf, cr = judge(sim)
        rows.append((valid, missed, cf, cr, what))
        shown = "-" if math.isnan(missed) else f"{missed:.2f}"
        print(f"{index:3d} valid {valid:.2f} missed {shown:>5} final Cf {100 * cf:+6.1f} % Cr {100 * cr:+6.1f} % | {what}",
              flush=True)
    valid = np.array([r[0] for r in rows])
    weights = valid / valid.sum() if valid.sum() > 0 else valid
    missed = np.nan_to_num(np.array([r[1] for r in rows]))
    print(f"{args.draws} draws: valid {valid.mean():.2f} of the epochs; valid and outside +-2 sigma "
          f"{float(np.sum(weights * missed)):.3f} of the valid epochs; draws ever valid {int(np.sum(valid > 0))}")
    bad = [r for r in rows if not math.isnan(r[1]) and r[1] > 0.05]
    for v, m, cf, cr, what in bad:
        print(f"  missed {m:.2f} of valid ({v:.2f} valid), final Cf {100 * cf:+.1f} % Cr {100 * cr:+.1f} %: {what}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
