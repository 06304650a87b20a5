"""The filter's own measures of what the configuration left out, read off each bag and pooled over the bags.

Shared by the calibrations that take a measure rather than a search: the tire relaxation length
(:mod:`.relaxation`) and the heading offset (:mod:`.heading_offset`). Each bag's measure is its last
epoch's value and std (the fit over ``ekf.saturation_memory`` of the innovations to the error's
signature, DESIGN.md section 7); the bags are pooled with weights 1 / std^2.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.epochs.epoch import EpochArrays


def final_measure(epochs: EpochArrays, config: EstimatorConfig, columns: tuple[int, int]) -> tuple[float, float]:
    """(value, std) of the output ``columns`` (layout.O_*) at one bag's last epoch; (0, 0) when not measured."""
    if len(epochs) == 0:
        return 0.0, 0.0
    last = run_sequence(config, epochs)[-1]
    value, std = float(last[columns[0]]), float(last[columns[1]])
    return (value, std) if math.isfinite(value) and math.isfinite(std) and std > 0.0 else (0.0, 0.0)


def pooled(measures: Sequence[tuple[float, float]]) -> tuple[float, float, int]:
    """(mean, std, bags) of the bags' measures weighted by 1 / std^2; (0, inf, 0) when none measured."""
    kept = np.array([(v, s) for v, s in measures if s > 0.0])
    if not len(kept):
        return 0.0, math.inf, 0
    weights = 1.0 / kept[:, 1] ** 2
    return float(np.sum(weights * kept[:, 0]) / np.sum(weights)), float(1.0 / math.sqrt(np.sum(weights))), len(kept)
