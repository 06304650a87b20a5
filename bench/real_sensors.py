"""Figures of the real-sensor issue (#10): offset, delay, arrival order, drop, saturation, held step, GNSS rates.

Not a test (test/test_real_sensors.py asserts the thresholds): it prints the figures over seeds 0-9
of the project's simulator with the default parameters. Run: ``.venv/bin/python bench/real_sensors.py``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import Run, median_and_worst, pooled_coverage, run_drive, sine_drive  # noqa: E402

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions  # noqa: E402
from transplanter_ident.sim.signals import StiffnessSchedule, sine_steering, step_steering  # noqa: E402
from transplanter_ident.sim.simulator import simulate  # noqa: E402

SEEDS = range(10)
DROP = StiffnessSchedule(times=(0.0, 60.0), front=(8000.0, 4800.0), rear=(10000.0, 6000.0), transition=0.0)
STEP = {"speed": 1.0, "steering": step_steering(math.radians(20.0), start=2.0, ramp=0.5), "duration": 90.0}


def errors(runs: list[Run]) -> str:
    median, worst = median_and_worst([e for r in runs for e in r.final_errors()])
    return f"median {100 * median:.2f} %, worst {100 * worst:.2f} %"


def coverage(runs: list[Run]) -> str:
    return "coverage after 30 s Cf {:.3f}, Cr {:.3f}".format(*pooled_coverage(runs, 30.0))


def drives(config: EstimatorConfig | None = None, **overrides: object) -> list[Run]:
    return [run_drive(sine_drive(seed, **overrides), config) for seed in SEEDS]


def main() -> int:
    clean = drives()
    print("clean:", errors(clean), coverage(clean))
    print("clean, no offset state:", errors(drives(EstimatorConfig(options=FilterOptions(estimate_steering_offset=False)))))
    for degrees in (0.25, 0.5, 1.0):
        offset = math.radians(degrees)
        runs = drives(steering_offset=offset)
        worst = max(abs(math.degrees(r.offset - offset)) for r in runs)
        print(f"offset {degrees} deg:", errors(runs), f"offset error at most {worst:.3f} deg")
    delayed = [run_drive(sine_drive(seed, gnss_delay=0.08), gnss_delay=0.08) for seed in SEEDS]
    print("80 ms GNSS delay, gnss.delay 0.08:", errors(delayed), "| unset:", errors(drives(gnss_delay=0.08)))
    results = [simulate(sine_drive(seed)) for seed in SEEDS]
    pairs = [(run_drive(r, gnss_first=True), run_drive(r)) for r in results]
    diff = max(max(abs(a.cf[-1] / b.cf[-1] - 1.0), abs(a.cr[-1] / b.cr[-1] - 1.0)) for a, b in pairs)
    print(f"arrival order: largest final difference {100 * diff:.2e} %")
    drop = drives(duration=150.0, stiffness=DROP)
    before = [float(r.cf[r.t < 60.0][-1] / 8000.0 - 1.0) for r in drop]
    before += [float(r.cr[r.t < 60.0][-1] / 10000.0 - 1.0) for r in drop]
    print(f"40 % drop: back within 10 % in a median {np.median([r.recovery_time(60.0, 0.10) for r in drop]):.1f} s, "
          f"within 5 % in {np.median([r.recovery_time(60.0, 0.05) for r in drop]):.1f} s; before the change median "
          f"{100 * median_and_worst(before)[0]:.2f} %; {coverage(drop)}; alarms before the change "
          f"{sum(r.alarms_between(0.0, 60.0) for r in drop)}, in 20 min of constant stiffness "
          f"{sum(r.alarms_between(0.0, math.inf) for r in clean)}")
    wet = drives(tire="saturating", friction=0.3)
    print("wet field (mu 0.3, tanh tire):", errors(wet), coverage(wet))
    beyond = drives(tire="saturating", friction=0.3, speed=3.0)
    print("wet field at 3 m/s (slip beyond the linear range):", errors(beyond), coverage(beyond))
    sharp = drives(tire="saturating", friction=0.3, steering=sine_steering(math.radians(25.0), 6.0))
    print("wet field, +-25 deg:", errors(sharp), coverage(sharp))
    step = drives(**STEP)
    print("paper step, 1 m/s, 20 deg held:", errors(step), coverage(step))
    for rate in (5.0, 10.0, 20.0, 100.0):
        runs = drives(gnss_rate=rate, steering_rate=max(50.0, rate), duration=120.0 if rate <= 20.0 else 60.0)
        print(f"GNSS at {rate:g} Hz:", errors(runs), coverage(runs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
