"""CPU cost of the identifiability guard (ekf/identifiability.py) in replay: filter alone vs filter + guard.

Not a test. A 600 s sine drive at 5 and 20 Hz GNSS through ``run_sequence`` with
``ekf.identifiability_check`` off and on; prints CPU seconds per hour of data (one warm run each).
Run: ``.venv/bin/python bench/identifiability_cost.py``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from drives import sine_drive  # noqa: E402
from helpers import epochs_from_result  # noqa: E402

from transplanter_ident.config.parameters import EstimatorConfig  # noqa: E402
from transplanter_ident.ekf.joint_ekf import run_sequence  # noqa: E402
from transplanter_ident.epochs.epoch import EpochArrays  # noqa: E402
from transplanter_ident.sim.simulator import simulate  # noqa: E402

DURATION = 600.0


def main() -> int:
    on = EstimatorConfig()
    off = EstimatorConfig(options=replace(on.options, identifiability_check=False))
    for rate in (5.0, 20.0):
        epochs = EpochArrays(epochs_from_result(simulate(sine_drive(0, duration=DURATION, gnss_rate=rate)), on.vehicle))
        per_hour = []
        for config in (off, on):
            run_sequence(config, epochs)  # load the kernels
            start = time.process_time()
            run_sequence(config, epochs)
            per_hour.append((time.process_time() - start) * 3600.0 / DURATION)
        print(f"{rate:g} Hz: filter {per_hour[0]:.2f} s, filter + guard {per_hour[1]:.2f} s of CPU per hour of data")
    return 0


if __name__ == "__main__":
    sys.exit(main())
