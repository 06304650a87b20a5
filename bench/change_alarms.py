"""False alarms of the surface-change test on drives whose stiffness never changes.

Not a test (test_real_sensors.py and test_noise_adaptation.py assert the budgets on fewer drives).
For each drive kind, ``--seeds`` seeds of the project's simulator, default parameters (or
``--option NAME=VALUE``, e.g. ``change_scale=4 --option change_threshold=12``, the test of before):
the change alarms after 30 s (the start, while R and the stiffness are still learned, is left out).

Run: ``.venv/bin/python bench/change_alarms.py [--seeds 6] [--option NAME=VALUE ...]``
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import NOISY_GNSS, run_drive, sine_drive  # noqa: E402

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions  # noqa: E402
from transplanter_ident.sim.scenarios import build_config  # noqa: E402
from transplanter_ident.sim.signals import multisine_steering  # noqa: E402
from transplanter_ident.sim.simulator import SimConfig, simulate  # noqa: E402

#: drive kind -> (its length in s, the drive of a seed)
DRIVES: dict[str, tuple[float, Callable[[int], SimConfig]]] = {
    "sine, 10 min": (600.0, lambda s: sine_drive(s, duration=600.0)),
    "multisine +-10 deg, 10 min": (600.0, lambda s: sine_drive(
        s, duration=600.0, steering=multisine_steering(math.radians(10.0), (3.0, 5.0, 9.0, 14.0), seed=3))),
    "field work, 5 min": (300.0, lambda s: build_config("field-work", seed=s)),
    "sine at 1.2 m/s, 5 min": (300.0, lambda s: sine_drive(s, duration=300.0, speed=1.2)),
    "sine, GNSS noise 2x (R default, adapted), 5 min": (300.0, lambda s: sine_drive(s, duration=300.0,
                                                                                   noise=NOISY_GNSS)),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=6)
    parser.add_argument("--option", action="append", default=[], metavar="NAME=VALUE",
                        help="a FilterOptions field (number) to set (repeatable)")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.error("--seeds must be >= 1")
    try:
        options = replace(FilterOptions(), **{k: float(v) for k, v in (o.split("=", 1) for o in args.option)})
    except (TypeError, ValueError) as error:
        parser.error(f"--option: {error}")
    print(f"seeds 0-{args.seeds - 1}; defaults{''.join(' ' + o for o in args.option)}")
    for name, (length, make) in DRIVES.items():
        alarms = sum(run_drive(simulate(make(seed)), EstimatorConfig(options=options)).alarms_between(30.0, math.inf)
                     for seed in range(args.seeds))
        minutes = args.seeds * (length - 30.0) / 60.0
        print(f"{name:<50} {alarms:3d} alarms after 30 s in {minutes:.0f} min", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
