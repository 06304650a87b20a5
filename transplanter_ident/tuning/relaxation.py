"""Estimating ``vehicle.relaxation_length`` offline: the filter's own measure of it, pooled over the bags.

A tire builds its lateral force over its relaxation length; left out of the model, 0.3 m at 2 m/s
makes Cf ~12 % high (README, "Tire relaxation"). The tuner's objectives do not pin it: the innovation
NLL over the length, the stiffness re-estimated at each, has its minimum at 0.15-0.2 m on 0.3 m
drives (the length and the stiffness trade off). The filter's measure of a length left out
(:mod:`transplanter_ident.ekf.relaxation_signature`) does: over each bag it fits the vy innovations to
the signature of the length, first order around the configured one.

So, a fixed point: run the filter over every bag at the current length, pool the lengths the bags
measure beyond it (weights 1 / std^2), add them, and again, until the step is below STEP_TOLERANCE
of its std or after MAX_PASSES; never below 0 (a tire only lags) or above MAX_LENGTH. The std is the pooled one of the
last pass. On three 2-minute identification drives of 0.3 m tires it gives 0.30 +- 0.04 m
(``test/test_tuner_relaxation.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.ekf.layout import O_RELAXATION, O_RELAXATION_STD
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.tuning.factor_search import TaskMap
from transplanter_ident.tuning.measures import final_measure, pooled

#: passes of the fixed point at most, and the step (in its std) below which it stops
MAX_PASSES = 4
STEP_TOLERANCE = 0.25
#: m, the longest length it writes (the schema's bound is wider; a tire's length is of the order of its radius)
MAX_LENGTH = 2.0


@dataclass(frozen=True)
class RelaxationEstimate:
    """The length (m), its std (m; inf: no bag measured it), the bags that measured it and the passes run."""

    value: float
    std: float
    bags: int
    passes: int

    def format(self) -> str:
        return (f"vehicle.relaxation_length: {self.value:.3f} +- {self.std:.3f} m (the filter's measure of the "
                f"tire force's lag, pooled over {self.bags} bag{'s' if self.bags != 1 else ''}, {self.passes} "
                f"pass{'es' if self.passes != 1 else ''})")


def with_relaxation_length(config: EstimatorConfig, length: float) -> EstimatorConfig:
    """``config`` with ``vehicle.relaxation_length`` = ``length`` (m)."""
    return replace(config, vehicle=replace(config.vehicle, relaxation_length=float(length)))


def measured_beyond(epochs: EpochArrays, config: EstimatorConfig) -> tuple[float, float]:
    """(m, std m) of the length one bag's innovations show beyond the configured one at its end (std 0: none)."""
    return final_measure(epochs, config, (O_RELAXATION, O_RELAXATION_STD))


def estimate_relaxation_length(bags: Sequence[EpochArrays], config: EstimatorConfig,
                               run: TaskMap | None = None) -> RelaxationEstimate:
    """The fixed point of the module docstring, from ``config``'s length; each bag of a pass a task of ``run``."""
    run = run or (lambda fn, tasks: [fn(*task) for task in tasks])
    length, passes = config.vehicle.relaxation_length, 0
    while True:
        at = with_relaxation_length(config, length)
        step, std, count = pooled(run(measured_beyond, [(epochs, at) for epochs in bags]))
        passes += 1
        moved = min(max(length + step, 0.0), MAX_LENGTH) - length if count else 0.0  # a bound stops it too
        length += moved
        if abs(moved) <= STEP_TOLERANCE * std or passes == MAX_PASSES:
            return RelaxationEstimate(length, std, count, passes)
