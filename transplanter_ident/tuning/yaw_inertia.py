"""Estimating ``vehicle.iz`` offline: the yaw inertia Iz of paper eq. 1, found on the bags.

Paper eq. 5 takes Iz = m lf lr, a rule of thumb a real vehicle misses by tens of percent, and the
estimate takes Iz on trust: configured 20 % high, Cf and Cr end 15-22 % off (README, "The defaults
on drives unlike their own"). The data pin it, given m, lf and lr: the lateral equation of eq. 1
fixes C / m, the yaw equation C l / Iz. So, like ``vehicle.steering_scale`` (:mod:`.steering_scale`),
a one-dimensional search of the tuner's objective at the starting Q/R over factors on the
configured Iz (0.6-1.6, in 5 % then 0.5 % steps; :mod:`.factor_search`), the filter warm-started at
each. On a 2-minute identification drive (2 m/s, +-15 deg) the NLL pins Iz to about +-5 % (1-sigma),
and Cf, Cr move by about 0.6-0.9 % per 1 % of Iz: tune on several bags. With ``nll`` the tuner
writes the std as ``ekf.yaw_inertia_uncertainty``, and the estimator's band holds the bias it may
leave (:func:`transplanter_ident.ekf.adaptation.propagate_inertia_bias`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.tuning.delay import MIN_DELAY_EPOCHS, DelayObjective, warm_start
from transplanter_ident.tuning.factor_search import (
    FactorEstimate,
    TaskMap,
    pooled_factor_objective,
    search_factor,
    with_factor_std,
)
from transplanter_ident.tuning.problem import TuningProblem

#: factors on the configured yaw inertia searched
FACTOR_RANGE = (0.6, 1.6)
COARSE_STEP = 0.05
FINE_STEP = 0.005
#: factors either side of the minimum through which the NLL's parabola goes (:func:`with_std`)
CURVATURE_WINDOW = 0.05
EDGE_ADVICE = "check vehicle.mass, lf, lr and the steering scale"


def with_yaw_inertia(config: EstimatorConfig, iz: float) -> EstimatorConfig:
    """``config`` with ``vehicle.iz`` = ``iz`` (kg m^2)."""
    return replace(config, vehicle=replace(config.vehicle, iz=float(iz)))


def inertia_objective(epochs: EpochArrays, config: EstimatorConfig, factor: float, objective: str,
                      tune_stiffness_noise: bool = False) -> tuple[float, int]:
    """(objective at the starting Q/R, epoch count) of one bag with the yaw inertia x ``factor``."""
    if len(epochs) < MIN_DELAY_EPOCHS:
        return math.inf, len(epochs)
    scaled = with_yaw_inertia(config, factor * config.vehicle.yaw_inertia)
    problem = TuningProblem.from_epochs(warm_start(scaled, epochs), epochs, objective, tune_stiffness_noise)
    return float(problem(problem.start[None, :])[0]), len(epochs)


def pooled_inertia_objective(bags: Sequence[EpochArrays], config: EstimatorConfig, objective: str,
                             tune_stiffness_noise: bool = False, run: TaskMap | None = None) -> DelayObjective:
    """The objective of a batch of factors, pooled over ``bags``; every (factor, bag) a task of ``run``."""
    return pooled_factor_objective(inertia_objective, bags, config, objective, tune_stiffness_noise, run)


def search_yaw_inertia(objective: DelayObjective, configured: float, low: float = FACTOR_RANGE[0],
                       high: float = FACTOR_RANGE[1], coarse: float = COARSE_STEP,
                       fine: float = FINE_STEP) -> FactorEstimate:
    """Minimise ``objective`` (of factors on the ``configured`` Iz) over [low, high]: coarse grid, then fine."""
    return search_factor(objective, "vehicle.iz", configured, (low, high), coarse, fine, EDGE_ADVICE)


def with_std(estimate: FactorEstimate, epochs: int) -> FactorEstimate:
    """``estimate`` with its std (kg m^2): the curvature of the pooled NLL; +inf at an edge."""
    return with_factor_std(estimate, epochs, CURVATURE_WINDOW, FINE_STEP)
