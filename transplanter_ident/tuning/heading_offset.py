"""Estimating ``vehicle.heading_offset`` offline: the filter's measure of a misaligned heading, pooled over the bags.

A dual-antenna baseline mounted delta off ``vehicle.heading_offset`` leaves a lateral velocity of
-vx delta that no motion gives (:mod:`transplanter_ident.ekf.heading_signature`); the filter measures
delta from its innovations, first order and nearly exact (1 deg reads 1.00 +- 0.12 deg on one
2-minute drive at 2 m/s). The offset shapes the epochs (the assembler turns the heading and the
body-frame velocity by it), so, as for the relaxation length (:mod:`.relaxation`), a fixed point over
the bags decoded at the current offset: pool what each bag measures beyond it (weights 1 / std^2),
add it, decode again, until the step is within STEP_TOLERANCE of its std or after MAX_PASSES.
The value is the last pass's offset plus its pooled measure; the std is that measure's.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.ekf.layout import (
    O_HEADING_ESTIMATE,
    O_HEADING_ESTIMATE_STD,
    O_HEADING_OFFSET,
    O_HEADING_OFFSET_STD,
)
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.tuning.factor_search import TaskMap
from transplanter_ident.tuning.measures import final_measure, pooled

#: passes of the fixed point at most (the first-order measure needs one; the next confirms it), and the step
#: (in its std) below which it stops
MAX_PASSES = 3
STEP_TOLERANCE = 0.25


@dataclass(frozen=True)
class HeadingEstimate:
    """The offset (rad), its std (rad; inf: no bag measured it), the bags that measured it and the passes run."""

    value: float
    std: float
    bags: int
    passes: int

    def format(self) -> str:
        spread = f"{math.degrees(self.std):.2f}" if math.isfinite(self.std) else "inf"
        return (f"vehicle.heading_offset: {self.value:.5f} rad ({math.degrees(self.value):+.2f} +- {spread} deg; "
                f"the filter's estimate of a misaligned heading, pooled over {self.bags} "
                f"bag{'s' if self.bags != 1 else ''}, {self.passes} pass{'es' if self.passes != 1 else ''})")


def with_heading_offset(params: EstimatorParams, offset: float) -> EstimatorParams:
    """``params`` with ``vehicle.heading_offset`` = ``offset`` (rad)."""
    config = params.config
    return replace(params, config=replace(config, vehicle=replace(config.vehicle, heading_offset=float(offset))))


def measured_misalignment(epochs: EpochArrays, config: EstimatorConfig) -> tuple[float, float]:
    """(rad, std rad) of the misalignment one bag shows beyond its offset, at its end (std 0: none).

    The filter's state h (``ekf.estimate_heading_offset``), else the innovations' measure of it.
    """
    columns = ((O_HEADING_OFFSET, O_HEADING_OFFSET_STD) if config.options.estimate_heading_offset
               else (O_HEADING_ESTIMATE, O_HEADING_ESTIMATE_STD))
    return final_measure(epochs, config, columns)


def estimate_heading_offset(epochs_at: Callable[[EstimatorParams], Sequence[EpochArrays]], params: EstimatorParams,
                            run: TaskMap | None = None) -> HeadingEstimate:
    """The fixed point of the module docstring from ``params``' offset; ``epochs_at`` decodes the bags at given params."""
    run = run or (lambda fn, tasks: [fn(*task) for task in tasks])
    offset, passes = params.config.vehicle.heading_offset, 0
    while True:
        at = with_heading_offset(params, offset)
        step, std, count = pooled(run(measured_misalignment, [(epochs, at.config) for epochs in epochs_at(at)]))
        passes += 1
        offset = math.remainder(offset + step, 2.0 * math.pi)  # the last pass's measure beyond it added
        if not count or abs(step) <= STEP_TOLERANCE * std or passes == MAX_PASSES:
            return HeadingEstimate(offset, std, count, passes)
