"""A calibration constant found on the bags as a factor on its configured value (steering scale, yaw inertia).

The shared part of ``tuner --estimate-steering-scale`` (:mod:`.steering_scale`) and
``--estimate-yaw-inertia`` (:mod:`.yaw_inertia`): a one-dimensional search of the tuner's objective
(eq. 21's mean |innovation| or the innovation NLL, :mod:`.problem`) at the *starting* Q/R over
factors on the configured value, pooled over the bags with their epoch counts as weights
(:func:`.delay.pooled`), the filter warm-started at each factor (:func:`.delay.warm_start`); a
coarse grid, then a fine one around its minimum (:func:`.delay.grid_search`; ties: the factor nearest
1). With ``nll`` the estimate's std is the curvature of the pooled NLL there (:func:`with_factor_std`,
:func:`.delay.profile_std`); a minimum at an edge of the factors searched pins nothing (std +inf).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.tuning.delay import DelayObjective, at_range_edge, grid_search, pooled, profile_std

#: (function, argument tuples) -> results in order: a backend's ``map`` (tuning.parallel), or here
TaskMap = Callable[[Callable[..., tuple[float, int]], list[tuple]], list[tuple[float, int]]]
#: (one bag's epochs, config, factor (or a pair of them), objective, tune_stiffness_noise) -> (objective at the
#: starting Q/R, epochs)
FactorScore = Callable[[EpochArrays, EstimatorConfig, Any, str, bool], tuple[float, int]]


@dataclass(frozen=True)
class FactorEstimate:
    """The value of ``key`` with the lowest objective, the configured one it was searched from, every point, its std.

    ``points``: (factor on the configured value, objective); ``std``: 1-sigma of ``value`` (NaN where
    unknown: objective ``mae``; +inf at an edge of ``bounds``, the factors searched).
    """

    key: str
    value: float
    configured: float
    fitness: float
    points: tuple[tuple[float, float], ...]
    bounds: tuple[float, float]
    std: float = math.nan
    advice: str = ""  # what to do when the minimum is at an edge

    @property
    def factor(self) -> float:
        return self.value / self.configured

    @property
    def at_edge(self) -> bool:
        """Whether the minimum lies at an edge of the factors searched (the value may lie beyond them)."""
        return at_range_edge(self.factor, self.bounds)

    def format(self, objective: str = "objective") -> str:
        """One line: the estimate, its objective, and the objective at the configured value."""
        at_configured = next((v for f, v in self.points if abs(f - 1.0) < 1e-9), math.nan)
        spread = f" +- {self.std:.4g}" if math.isfinite(self.std) else ""
        if self.std == math.inf and not self.at_edge:
            spread = " +- inf (the drives do not pin it)"
        low, high = (self.configured * b for b in self.bounds)
        edge = (f"; at the edge of the values searched, [{low:.4g}, {high:.4g}]: it may lie beyond them, "
                f"{self.advice}" if self.at_edge else "")
        return (f"{self.key}: {self.value:.5g}{spread} ({objective} {self.fitness:.6g} at the starting Q/R; "
                f"{at_configured:.6g} at the configured {self.configured:.5g}; {len(self.points)} values evaluated{edge})")


def search_factor(objective: DelayObjective, key: str, configured: float, bounds: tuple[float, float],
                  coarse: float, fine: float, advice: str = "") -> FactorEstimate:
    """Minimise ``objective`` (of factors on ``configured``) over ``bounds``: coarse grid, then fine."""
    factor, fitness, points = grid_search(objective, *bounds, coarse, fine, key, prefer=1.0)
    return FactorEstimate(key, configured * factor, configured, fitness, points, bounds, advice=advice)


def with_factor_std(estimate: FactorEstimate, epochs: int, window: float, step: float) -> FactorEstimate:
    """``estimate`` with its std: the curvature of the pooled NLL (mean over ``epochs`` epochs) at its minimum.

    ``window``: the factors either side of the minimum the parabola goes through; ``step``: the fine grid's.
    +inf at an edge of the factors searched (the minimum may lie beyond them).
    """
    if estimate.at_edge:
        return replace(estimate, std=math.inf)
    return replace(estimate, std=estimate.configured * profile_std(estimate.points, estimate.factor, epochs, window,
                                                                    step))


def pooled_factor_objective(score: FactorScore, bags: Sequence[EpochArrays], config: EstimatorConfig,
                            objective: str, tune_stiffness_noise: bool = False,
                            run: TaskMap | None = None) -> Callable[[Sequence[Any]], list[float]]:
    """The objective of a batch of factors (or pairs), pooled over ``bags``; every (factor, bag) a task of ``run``."""
    run = run or (lambda fn, tasks: [fn(*task) for task in tasks])

    def of(factors: Sequence[float]) -> list[float]:
        tasks = [(e, config, f, objective, tune_stiffness_noise) for f in factors for e in bags]
        values = run(score, tasks)
        return [pooled(values[i * len(bags):(i + 1) * len(bags)]) for i in range(len(factors))]

    return of
