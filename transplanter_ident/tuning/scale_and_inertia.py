"""``vehicle.steering_scale`` and ``vehicle.iz`` found together: the two are confounded.

A steering sensor reading high (the input of paper eq. 1) and a yaw inertia too small (Iz of its yaw
equation) both make the measured yaw response look larger than the model's, so the tuner's
objectives (eq. 21's mean |innovation| and the innovation NLL) have a tilted ridge in (scale, Iz):
searched one after the other (:mod:`.steering_scale`, then :mod:`.yaw_inertia`), a sensor 2 % high on a
vehicle whose Iz is 1.2 x m lf lr gave the scale 1.002 +- 0.0017 (truth 0.980) and Iz 1.005 x, and
Cf 26 % low, valid. Asked for both, the tuner searches them jointly: a coarse grid of factors
(0.95-1.05 on the scale in 1 % steps x 0.6-1.6 on Iz in 10 % steps), then a fine one (0.2 % x 1 %)
around its minimum (:func:`grid_search_pair`).

The estimate is the minimum of eq. 21 (``mae``; the vertex of a quadratic surface through it around
the grid's best point, :func:`fit_surface`), whatever the tuner's objective: along the ridge the NLL
leans to a larger yaw response (scale high, Iz low), through its heading innovations and its
ln det S term (on noise-free drives too), while eq. 21 is dominated by the vy innovations, which do
not lean. Its std comes from the NLL (objective ``nll``): the surface through it around its own
minimum (:func:`pair_std`), whose inverse Hessian is the covariance of the pair (each std holds what
the other leaves open), times STD_INFLATION (a margin for drives less like the simulated ones).
On 30 sets of three identification drives (``bench/joint_calibration_figures.py``) eq. 21's minimum was
off by a median 0.5 % (scale) and 6.3 % (Iz), the NLL's by 1.4 % and 15 %.
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
PairObjective = Callable[[Sequence[Pair]], Sequence[float]]
#: (low, high, coarse step, fine step) of each factor
SCALE_GRID = (0.95, 1.05, 0.01, 0.002)
INERTIA_GRID = (0.6, 1.6, 0.1, 0.01)
#: fine steps either side of a grid's best point through which a quadratic surface is fitted (fit_surface)
CURVATURE_STEPS = 3
#: the std are the NLL surface's times this. Measured on 30 sets of three identification drives (2 m/s,
#: +-15 deg, 120 s; sensor gain 0.98-1.02, Iz 0.75-1.4 x m lf lr; bench/joint_calibration_figures.py):
#: eq. 21's minimum was off the truth by rms 0.88 / 1.07 (scale / Iz) of the surface's std, worst 2.1 / 2.4,
#: 97 % within 2; x 1.2 for drives less like the simulated ones: rms 0.74 / 0.89, all within 2
STD_INFLATION = 1.2
#: the objective whose minimum is the estimate (eq. 21; see the module's docstring)
LOCATING_OBJECTIVE = "mae"


def pair_objective(epochs: EpochArrays, config: EstimatorConfig, pair: Pair, objective: str,
                   tune_stiffness_noise: bool = False) -> tuple[float, int]:
    """(objective at the starting Q/R, epochs) of one bag with the steering x pair[0] and Iz x pair[1]."""
    inertia = with_yaw_inertia(config, pair[1] * config.vehicle.yaw_inertia)
    return scale_objective(epochs, inertia, pair[0], objective, tune_stiffness_noise)


def pooled_pair_objective(bags: Sequence[EpochArrays], config: EstimatorConfig, objective: str,
                          tune_stiffness_noise: bool = False, run: TaskMap | None = None) -> PairObjective:
    """The objective of a batch of pairs, pooled over ``bags``; every (pair, bag) a task of ``run``."""
    return pooled_factor_objective(pair_objective, bags, config, objective, tune_stiffness_noise, run)


def grid_search_pair(objective: PairObjective, scale: tuple = SCALE_GRID,
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


def fit_surface(points: dict[Pair, float], best: Pair, steps: Pair = (SCALE_GRID[3], INERTIA_GRID[3]),
                reach: int = CURVATURE_STEPS) -> tuple[Pair, np.ndarray | None]:
    """(vertex, Hessian) of a quadratic surface through ``points`` within ``reach`` steps of ``best``.

    The vertex is ``best`` where it lies outside the points fitted or the surface is not a minimum
    (then the Hessian is None too, as with fewer than 6 points).
    """
    near = [(a - best[0], b - best[1], v) for (a, b), v in points.items() if math.isfinite(v)
            and abs(a - best[0]) <= reach * steps[0] + 1e-9 and abs(b - best[1]) <= reach * steps[1] + 1e-9]
    if len(near) < 6:
        return best, None
    da, db, v = (np.array(c) for c in zip(*near, strict=True))
    design = np.column_stack((np.ones_like(da), da, db, da * da, da * db, db * db))
    coef = np.linalg.lstsq(design, v, rcond=None)[0]
    hessian = np.array([[2.0 * coef[3], coef[4]], [coef[4], 2.0 * coef[5]]])
    if not (hessian[0, 0] > 0.0 and np.linalg.det(hessian) > 0.0):
        return best, None
    shift = -np.linalg.solve(hessian, coef[1:3])
    inside = all(abs(shift[i]) <= reach * steps[i] for i in range(2))
    return ((best[0] + float(shift[0]), best[1] + float(shift[1])) if inside else best), hessian


def pair_std(points: dict[Pair, float], best: Pair, epochs: int, steps: Pair = (SCALE_GRID[3], INERTIA_GRID[3])) -> Pair:
    """1-sigma of each factor from the mean NLL over ``epochs`` epochs around its minimum ``best``.

    The inverse Hessian of its surface (:func:`fit_surface`, x ``epochs``) is the covariance of the pair
    (each std holds what the other leaves open), plus each grid's rounding, times STD_INFLATION; +inf
    where the surface is not a minimum.
    """
    _, hessian = fit_surface(points, best, steps)
    if hessian is None or epochs <= 0:
        return math.inf, math.inf
    cov = np.linalg.inv(epochs * hessian)
    return tuple(STD_INFLATION * math.sqrt(cov[i, i] + steps[i] ** 2 / 12.0) for i in range(2))


def search_scale_and_inertia(locate: PairObjective, configured: Pair, likelihood: PairObjective | None = None,
                             epochs: int = 0) -> tuple[FactorEstimate, FactorEstimate]:
    """The steering scale and Iz (estimates with their ``configured`` values), searched jointly.

    ``locate``: eq. 21 of pairs, whose minimum is the estimate (the vertex of its surface around the grid's
    best point, :func:`fit_surface`); ``likelihood``: the mean NLL of
    pairs over ``epochs`` pooled epochs, whose surface gives the std (:func:`pair_std`; +inf at an edge
    of either range; NaN without it).
    """
    best, fitness, seen = grid_search_pair(locate)
    found, _ = fit_surface(seen, best)
    stds, peak = (math.nan, math.nan), best
    if likelihood is not None and epochs > 0:
        peak, _, surface = grid_search_pair(likelihood)
        stds = pair_std(surface, peak, epochs)
    out = []
    for i, (key, grid, advice) in enumerate((("vehicle.steering_scale", SCALE_GRID, SCALE_ADVICE),
                                              ("vehicle.iz", INERTIA_GRID, INERTIA_ADVICE))):
        points = tuple(sorted((p[i], v) for p, v in seen.items() if p[1 - i] == best[1 - i]))
        edge = at_range_edge(best[i], grid[:2]) or at_range_edge(peak[i], grid[:2])
        std = math.inf if math.isfinite(stds[i]) and edge else configured[i] * stds[i]
        value = configured[i] * (best[i] if at_range_edge(best[i], grid[:2]) else found[i])
        out.append(FactorEstimate(key, value, configured[i], fitness, points, grid[:2], std, advice))
    return out[0], out[1]
