"""Steering input over a GNSS interval: least-squares ramp (default) against the held interval mean.

The identification setting of the foundation test (2 m/s, +-15 deg sine with a 6 s period,
120 s at 5 Hz GNSS, 50 Hz steering, default noise and filter), seeds 0-9, plus one noise-free
run. "held" replays the same epochs with the steering slope set to 0, i.e. DESIGN.md's
interval mean held over the interval. Run: ``python bench/steering_input.py``.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "test")]

from helpers import sim_samples  # noqa: E402

from transplanter_ident.config.parameters import EstimatorConfig  # noqa: E402
from transplanter_ident.ekf.joint_ekf import run_sequence  # noqa: E402
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD  # noqa: E402
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler, assemble  # noqa: E402
from transplanter_ident.epochs.epoch import EpochArrays  # noqa: E402
from transplanter_ident.sim.signals import sine_steering  # noqa: E402
from transplanter_ident.sim.simulator import SensorNoise, SimConfig, simulate  # noqa: E402

TRUE_FRONT, TRUE_REAR = 8000.0, 10000.0


def final_rows(seed: int, noise: SensorNoise | None = None) -> dict[str, np.ndarray]:
    """The last output row for the ramp and for the held mean, on one simulated drive."""
    config = SimConfig(seed=seed, steering=sine_steering(math.radians(15.0), 6.0), speed=2.0, duration=120.0)
    if noise is not None:
        config = dataclasses.replace(config, noise=noise)
    epochs = assemble(EpochAssembler(AssemblerSettings()), sim_samples(simulate(config)))
    held = [dataclasses.replace(epoch, steering_rate=0.0) for epoch in epochs]
    return {label: run_sequence(EstimatorConfig(), EpochArrays(eps))[-1]
            for label, eps in (("ramp", epochs), ("held mean", held))}


def main(argv: list[str] | None = None) -> int:
    """Print median/max final error and +-2 sigma coverage for both inputs."""
    rows: dict[str, list[np.ndarray]] = {"ramp": [], "held mean": []}
    for seed in range(10):
        for label, row in final_rows(seed).items():
            rows[label].append(row)
    for label, found in rows.items():
        a = np.array(found)
        err_f, err_r = np.abs(a[:, O_CF] / TRUE_FRONT - 1), np.abs(a[:, O_CR] / TRUE_REAR - 1)
        cover_f = int(np.sum(np.abs(a[:, O_CF] - TRUE_FRONT) <= 2 * a[:, O_CF_STD]))
        cover_r = int(np.sum(np.abs(a[:, O_CR] - TRUE_REAR) <= 2 * a[:, O_CR_STD]))
        print(f"{label:<10} median |err| Cf {100 * np.median(err_f):.2f} % Cr {100 * np.median(err_r):.2f} %; "
              f"max Cf {100 * err_f.max():.2f} % Cr {100 * err_r.max():.2f} %; +-2 sigma covers {cover_f}/10, "
              f"{cover_r}/10")
    for label, row in final_rows(0, SensorNoise(0.0, 0.0, 0.0)).items():
        print(f"{label:<10} noise-free final error Cf {100 * (row[O_CF] / TRUE_FRONT - 1):+.2f} %, "
              f"Cr {100 * (row[O_CR] / TRUE_REAR - 1):+.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
