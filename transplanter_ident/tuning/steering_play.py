"""Estimating ``vehicle.steering_play`` offline: the steering linkage's free travel, found on the bags.

A play (:mod:`transplanter_ident.epochs.steering_play`) puts the sensor half of it ahead of or behind
the wheels, towards the last motion: 0.1 deg left out moves Cf by about 10 % while the estimate stays
valid. Like ``gnss.delay`` (:mod:`.delay`) it shapes the epochs, so each candidate play re-assembles
every bag's decoded input samples with it (:func:`play_objective`) and is scored by the tuner's
objective (eq. 21's mean |innovation| or the innovation NLL, :mod:`.problem`) at the *starting* Q/R,
the filter warm-started, pooled over the bags by their epochs (:func:`.delay.pooled`).

Signed, over [-1.15, 1.15] deg (+-0.02 rad) in 0.057 deg (1 mrad) then 0.0057 deg steps
(:func:`.delay.grid_search`; ties: the play nearest 0). With ``nll`` the estimate's std is the
curvature of the pooled NLL there (:func:`.delay.profile_std`); a minimum at an edge pins nothing
(std +inf). On the identification drive with 0.3 deg of play (two 2-minute drives) the pooled NLL's
minimum is at 0.3 deg, and 0.1 deg either side costs 3-12 in -ln L.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.tuning.delay import (
    BagScores,
    Sample,
    at_range_edge,
    delay_objective,
    grid_search,
    pooled,
    profile_std,
)

#: rad: the plays searched (signed: > 0 the wheels follow the sensor, < 0 the sensor follows the wheels)
PLAY_RANGE = (-0.02, 0.02)
COARSE_STEP = 0.001  # rad
FINE_STEP = 0.0001  # rad
#: rad: the fine points either side of the minimum through which the NLL's parabola is fitted
CURVATURE_WINDOW = 0.0005


def with_steering_play(params: EstimatorParams, play: float) -> EstimatorParams:
    """The parameters with ``vehicle.steering_play`` = ``play`` (rad)."""
    config = params.config
    return replace(params, config=replace(config, vehicle=replace(config.vehicle, steering_play=float(play))))


def play_objective(samples: Sequence[Sample], params: EstimatorParams, play: float, objective: str,
                   tune_stiffness_noise: bool = False) -> tuple[float, int]:
    """(objective at the starting Q/R, epoch count) of one bag's samples assembled with ``play`` (warm-started)."""
    with_play = with_steering_play(params, play)
    return delay_objective(samples, with_play, with_play.gnss.delay, objective, tune_stiffness_noise)


@dataclass(frozen=True)
class PlayEstimate:
    """The play with the lowest objective (rad), every (play, objective) evaluated, its std and the range searched."""

    play: float
    fitness: float
    points: tuple[tuple[float, float], ...]
    std: float = math.nan  # rad; NaN with objective mae, +inf at an edge of ``bounds``
    bounds: tuple[float, float] = PLAY_RANGE

    @property
    def at_edge(self) -> bool:
        return at_range_edge(self.play, self.bounds)

    def format(self, objective: str = "objective") -> str:
        """One line: the estimate (rad and deg), its objective, and the objective with no play."""
        at_zero = next((v for p, v in self.points if abs(p) < 1e-12), math.nan)
        spread = f" +- {self.std:.2g}" if math.isfinite(self.std) else ""
        edge = (f"; at the edge of the plays searched, [{self.bounds[0]:g}, {self.bounds[1]:g}] rad: it may lie "
                "beyond them, take up the linkage's play" if self.at_edge else "")
        return (f"vehicle.steering_play: {self.play:.4g}{spread} rad ({math.degrees(self.play):.3f} deg; {objective} "
                f"{self.fitness:.6g} at the starting Q/R; {at_zero:.6g} with none; {len(self.points)} plays "
                f"evaluated{edge})")


def estimate_steering_play(scores: BagScores, objective: str, low: float = PLAY_RANGE[0],
                           high: float = PLAY_RANGE[1]) -> PlayEstimate:
    """The play minimising the bags' pooled objective (``scores``: per play, every bag's (value, epochs)); its std."""
    epochs: dict[float, int] = {}

    def pooled_objective(plays: Sequence[float]) -> list[float]:
        per_play = scores(plays)
        epochs.update((p, sum(n for _, n in bags)) for p, bags in zip(plays, per_play, strict=True))
        return [pooled(bags) for bags in per_play]

    best, fitness, points = grid_search(pooled_objective, low, high, COARSE_STEP, FINE_STEP, "steering play",
                                        prefer=0.0)
    estimate = PlayEstimate(best, fitness, points, bounds=(low, high))
    if objective != "nll":
        return estimate
    if estimate.at_edge:
        return replace(estimate, std=math.inf)
    return replace(estimate, std=profile_std(points, best, epochs[best], CURVATURE_WINDOW, FINE_STEP))
