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

*With the delay* (:func:`estimate_delay_and_play`): at one steering amplitude and period a play looks
like a timing error (a sensor half the play ahead of the wheels on a +-15 deg sine of 6 s is ~12 ms
early), so searched one after the other the first takes up the second, and the likelihood's narrow
valley between them stops the second. Both are then searched jointly by CMA-ES (:mod:`.cmaes`, the
``cma`` package) in the (delay, play) box, seeded, and their stds come from the Hessian of the pooled
NLL at the minimum (a quadratic through a 5 x 5 stencil, inverted: each std holds the other's
confounding). On the identification drive the true pair's -ln L is 7-37 below the valley's other end
(two drives; a sine of 15 or 5 deg, a multisine).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.tuning.box import Box
from transplanter_ident.tuning.cmaes import CmaesSettings, minimize_cmaes
from transplanter_ident.tuning.delay import (
    DELAY_RANGE,
    BagScores,
    DelayEstimate,
    PooledScores,
    Sample,
    at_range_edge,
    delay_objective,
    grid_estimate,
    with_delay,
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


def pair_objective(samples: Sequence[Sample], params: EstimatorParams, pair: tuple[float, float], objective: str,
                   tune_stiffness_noise: bool = False) -> tuple[float, int]:
    """:func:`play_objective` at ``pair`` = (gnss.delay s, steering play rad)."""
    return play_objective(samples, with_delay(params, pair[0]), pair[1], objective, tune_stiffness_noise)


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
        none = f"; {at_zero:.6g} with none" if math.isfinite(at_zero) else ""
        spread = f" +- {self.std:.2g}" if math.isfinite(self.std) else ""
        edge = (f"; at the edge of the plays searched, [{self.bounds[0]:g}, {self.bounds[1]:g}] rad: it may lie "
                "beyond them, take up the linkage's play" if self.at_edge else "")
        return (f"vehicle.steering_play: {self.play:.4g}{spread} rad ({math.degrees(self.play):.3f} deg; {objective} "
                f"{self.fitness:.6g} at the starting Q/R{none}; {len(self.points)} plays evaluated{edge})")


def estimate_steering_play(scores: BagScores, objective: str, low: float = PLAY_RANGE[0],
                           high: float = PLAY_RANGE[1]) -> PlayEstimate:
    """The play minimising the bags' pooled objective (``scores``: per play, every bag's (value, epochs)); its std."""
    return PlayEstimate(*grid_estimate(scores, objective, (low, high), COARSE_STEP, FINE_STEP, CURVATURE_WINDOW,
                                       "steering play"), (low, high))


#: the joint search: CMA-ES population and generations after the first (6 x 50 = 300 evaluations), step size
JOINT_SEARCH = CmaesSettings(particles=6, iterations=49, sigma0=0.1)
#: (s, rad): the 5 x 5 stencil's steps about the joint minimum, for the NLL's Hessian (a 3 x 3 one is too
#: short for the valley: its fit came out indefinite on a drive without play)
STENCIL = (0.002, 0.0005)
STENCIL_REACH = 2


#: (gnss.delay s, steering play rad) pairs -> for each, every bag's (objective, epochs)
PairScores = Callable[[Sequence[tuple[float, float]]], Sequence[Sequence[tuple[float, int]]]]


def estimate_delay_and_play(scores: PairScores, objective: str, start: tuple[float, float] = (0.0, 0.0),
                            delay_range: tuple[float, float] = DELAY_RANGE,
                            play_range: tuple[float, float] = PLAY_RANGE,
                            seed: int = 1) -> tuple[DelayEstimate, PlayEstimate]:
    """The (gnss.delay, steering play) minimising the bags' pooled objective, jointly.

    CMA-ES from ``start`` (seeded: the same result for any parallelism), then with ``nll`` the stds from the
    Hessian of the NLL summed over the bags' epochs (+inf where it is not positive definite or the minimum
    is at an edge of the box).
    """
    pooled_objective = PooledScores(scores)
    box = Box((delay_range[0], play_range[0]), (delay_range[1], play_range[1]), ("gnss.delay", "steering_play"))
    found = minimize_cmaes(lambda points: pooled_objective([(float(d), float(p)) for d, p in points]), box,
                           JOINT_SEARCH, seed, initial=[start])
    best = (float(found.position[0]), float(found.position[1]))
    std = (math.nan, math.nan)
    if objective == "nll":  # a likelihood: its curvature is the estimates' information
        edge = at_range_edge(best[0], delay_range) or at_range_edge(best[1], play_range)
        std = (math.inf, math.inf) if edge else _hessian_std(pooled_objective, best, found.fitness,
                                                             pooled_objective.epochs[best])
    points = sorted(pooled_objective.values.items())  # every pair evaluated: the estimates' points, by coordinate
    return (DelayEstimate(best[0], found.fitness, tuple((d, v) for (d, _), v in points), std[0], delay_range),
            PlayEstimate(best[1], found.fitness, tuple((p, v) for (_, p), v in points), std[1], play_range))


def _hessian_std(pairs: Callable[[Sequence[tuple[float, float]]], list[float]], best: tuple[float, float],
                 value: float, epochs: int) -> tuple[float, float]:
    """Marginal stds of the pair: a least-squares quadratic of epochs x NLL through the 5 x 5 stencil, inverted."""
    reach = range(-STENCIL_REACH, STENCIL_REACH + 1)
    offsets = [(i, j) for i in reach for j in reach]
    points = [(best[0] + i * STENCIL[0], best[1] + j * STENCIL[1]) for i, j in offsets]
    values = np.array([value if (i, j) == (0, 0) else v for (i, j), v in zip(offsets, pairs(points), strict=True)])
    if not np.all(np.isfinite(values)):
        return math.inf, math.inf
    u = np.array([i * STENCIL[0] for i, _ in offsets])
    w = np.array([j * STENCIL[1] for _, j in offsets])
    design = np.column_stack((u * u, w * w, u * w, u, w, np.ones_like(u)))
    a, b, c = np.linalg.lstsq(design, epochs * (values - value), rcond=None)[0][:3]
    hessian = np.array([[2.0 * a, c], [c, 2.0 * b]])
    if not (hessian[0, 0] > 0.0 and np.linalg.det(hessian) > 0.0):
        return math.inf, math.inf
    covariance = np.linalg.inv(hessian)
    return math.sqrt(covariance[0, 0]), math.sqrt(covariance[1, 1])
