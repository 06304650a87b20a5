"""``vehicle.steering_scale`` and ``vehicle.iz`` found together: the two are confounded.

A steering sensor reading high (the input of paper eq. 1) and a yaw inertia too small (Iz of its yaw
equation) both make the measured yaw response look larger than the model's, so the tuner's
objective (eq. 21's mean |innovation| or the innovation NLL) has a tilted ridge in (scale, Iz): searched
one after the other (:mod:`.steering_scale`, then :mod:`.yaw_inertia`), a sensor 2 % high on a
vehicle whose Iz is 1.2 x m lf lr gave the scale 1.002 +- 0.0017 (truth 0.980) and Iz 1.005 x, and
Cf 26 % low, valid. Asked for both, the tuner searches them jointly: a coarse grid of factors
(0.95-1.05 on the scale in 1 % steps x 0.6-1.6 on Iz in 10 % steps), then a fine one (0.2 % x 1 %)
around its minimum (:func:`grid_search_pair`). With ``nll`` a quadratic surface through the pooled NLL
there gives both and their std, both directions at once (:func:`fit_pair`): each std holds what the other
leaves open. Along that ridge the NLL's curvature overstates what the drives pin (errors of up to 6.5 of
its std on three 2-minute drives at one speed), so the std are widened fourfold (RIDGE_INFLATION): the
estimate is then rarely valid on such drives, which is what they can tell.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Sequence

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.tuning.delay import at_range_edge, grid_points
from transplanter_ident.tuning.factor_search import FactorEstimate, TaskMap, pooled_factor_objective
from transplanter_ident.tuning.steering_scale import EDGE_ADVICE as SCALE_ADVICE
from transplanter_ident.tuning.steering_scale import scale_objective
from transplanter_ident.tuning.yaw_inertia import EDGE_ADVICE as INERTIA_ADVICE
from transplanter_ident.tuning.yaw_inertia import with_yaw_inertia

Pair = tuple[float, float]  # (factor on the steering scale, factor on Iz)
#: (low, high, coarse step, fine step) of each factor
SCALE_GRID = (0.95, 1.05, 0.01, 0.002)
INERTIA_GRID = (0.6, 1.6, 0.1, 0.01)
#: fine steps either side of the minimum through which the NLL's quadratic surface is fitted
CURVATURE_STEPS = 3
#: the std are the surface's times this: along the ridge the NLL's curvature overstates what the drives
#: pin. Measured on 6 sets of three identification drives (2 m/s, +-15 deg, 120 s; sensor 1 or 1.02,
#: Iz 1 or 1.2 x m lf lr): errors of 1-6.5 of the surface's std, rms 4 (the one-dimensional searches: rms 1.3)
RIDGE_INFLATION = 4.0


def pair_objective(epochs: EpochArrays, config: EstimatorConfig, pair: Pair, objective: str,
                   tune_stiffness_noise: bool = False) -> tuple[float, int]:
    """(objective at the starting Q/R, epochs) of one bag with the steering x pair[0] and Iz x pair[1]."""
    inertia = with_yaw_inertia(config, pair[1] * config.vehicle.yaw_inertia)
    return scale_objective(epochs, inertia, pair[0], objective, tune_stiffness_noise)


def pooled_pair_objective(bags: Sequence[EpochArrays], config: EstimatorConfig, objective: str,
                          tune_stiffness_noise: bool = False,
                          run: TaskMap | None = None) -> Callable[[Sequence[Pair]], list[float]]:
    """The objective of a batch of pairs, pooled over ``bags``; every (pair, bag) a task of ``run``."""
    return pooled_factor_objective(pair_objective, bags, config, objective, tune_stiffness_noise, run)


def grid_search_pair(objective: Callable[[Sequence[Pair]], Sequence[float]], scale: tuple = SCALE_GRID,
                     inertia: tuple = INERTIA_GRID) -> tuple[Pair, float, dict[Pair, float]]:
    """(best pair, its value, every pair evaluated): a coarse product grid, then a fine one around its minimum.

    Ties go to the pair nearest (1, 1); a non-finite value counts as +inf.
    """
    seen: dict[Pair, float] = {}

    def evaluate(pairs: list[Pair]) -> Pair:
        todo = [p for p in pairs if p not in seen]
        if todo:
            seen.update((p, float(v) if math.isfinite(v) else math.inf) for p, v in zip(todo, objective(todo), strict=True))
        return min(seen, key=lambda p: (seen[p], abs(p[0] - 1.0) + abs(p[1] - 1.0), p))

    best = evaluate(list(itertools.product(grid_points(*scale[:3]), grid_points(*inertia[:3]))))
    window = [(max(lo, b - c), min(hi, b + c), f) for (lo, hi, c, f), b in ((scale, best[0]), (inertia, best[1]))]
    best = evaluate(list(itertools.product(*(grid_points(*w) for w in window))))
    return best, seen[best], seen


def fit_pair(points: dict[Pair, float], best: Pair, epochs: int, steps: Pair = (SCALE_GRID[3], INERTIA_GRID[3]),
             reach: int = CURVATURE_STEPS) -> tuple[Pair, Pair]:
    """(minimum, 1-sigma) of each factor: a quadratic surface through the NLL (x ``epochs``) within ``reach`` steps.

    The grid's best point is on a tilted ridge only within a few steps of the minimum: the surface's
    vertex is the estimate (``best`` if the vertex lies outside the points fitted). The inverse of
    its Hessian is the covariance of the pair (each std holds what the other leaves open), plus each
    grid's rounding, times RIDGE_INFLATION; +inf where the surface is not a minimum, NaN with too few points.
    """
    near = [(a - best[0], b - best[1], v) for (a, b), v in points.items() if math.isfinite(v)
            and abs(a - best[0]) <= reach * steps[0] + 1e-9 and abs(b - best[1]) <= reach * steps[1] + 1e-9]
    if len(near) < 6 or epochs <= 0:
        return best, (math.nan, math.nan)
    da, db, v = (np.array(c) for c in zip(*near, strict=True))
    design = np.column_stack((np.ones_like(da), da, db, da * da, da * db, db * db))
    coef = np.linalg.lstsq(design, epochs * v, rcond=None)[0]
    hessian = np.array([[2.0 * coef[3], coef[4]], [coef[4], 2.0 * coef[5]]])
    if not (hessian[0, 0] > 0.0 and np.linalg.det(hessian) > 0.0):
        return best, (math.inf, math.inf)
    cov = np.linalg.inv(hessian)
    shift = -cov @ coef[1:3]
    inside = all(abs(shift[i]) <= reach * steps[i] for i in range(2))
    vertex = (best[0] + float(shift[0]), best[1] + float(shift[1])) if inside else best
    return vertex, tuple(RIDGE_INFLATION * math.sqrt(cov[i, i] + steps[i] ** 2 / 12.0) for i in range(2))


def search_scale_and_inertia(objective: Callable[[Sequence[Pair]], Sequence[float]], configured: Pair,
                             epochs: int | None = None) -> tuple[FactorEstimate, FactorEstimate]:
    """The steering scale and Iz (estimates with their ``configured`` values), searched jointly.

    ``epochs``: the pooled epochs (objective ``nll``): then each is the fitted surface's vertex, with its
    std (+inf at an edge of its range); without, the grid's best point.
    """
    best, fitness, seen = grid_search_pair(objective)
    found, stds = fit_pair(seen, best, epochs) if epochs else (best, (math.nan, math.nan))
    out = []
    for i, (key, grid, advice) in enumerate((("vehicle.steering_scale", SCALE_GRID, SCALE_ADVICE),
                                              ("vehicle.iz", INERTIA_GRID, INERTIA_ADVICE))):
        points = tuple(sorted((p[i], v) for p, v in seen.items() if p[1 - i] == best[1 - i]))
        edge = at_range_edge(best[i], grid[:2])
        std = math.inf if epochs and edge else configured[i] * stds[i]
        value = configured[i] * (best[i] if edge else found[i])
        out.append(FactorEstimate(key, value, configured[i], fitness, points, grid[:2], std, advice))
    return out[0], out[1]
