"""Estimating ``vehicle.steering_scale`` offline: the steering sensor's gain, found on the bags.

At farm speeds the yaw rate is nearly the kinematic vx delta / (lf + lr) (paper eq. 4 at low vx)
and the stiffness is read off the small rest, so a sensor that reads 1 % more than the wheel
angle moves Cf by about -5 % and Cr by +8 % while the estimate stays valid; the offset state takes
up a constant error, not a scale. Like ``gnss.delay`` (:mod:`.delay`), the scale is a calibration
constant best found from recorded drives: a one-dimensional search, ahead of the Q/R search, of
the tuner's objective (eq. 21's mean |innovation| or the innovation NLL, :mod:`.problem`) at the
*starting* Q/R, pooled over the bags with their epoch counts as weights. A candidate factor
multiplies every epoch's steering angle and its rate (:func:`scaled_epochs`; the assembler's
lines are linear in the samples, so this equals assembling with that scale: for a sensor on the
centre line only, as a sensor on one wheel goes through the nonlinear Ackermann map, so the CLI
refuses that case), and the filter
starts from the stiffness and offset a first pass at that factor ends with (:func:`.delay.warm_start`).

Over [0.95, 1.05] x the configured scale, in 0.5 % then 0.05 % steps (:func:`.delay.grid_search`;
ties: the factor nearest 1). A minimum at an edge of that range does not pin the scale: its std is
+inf, and the estimate says so (:class:`.factor_search.FactorEstimate`).
On a 2-minute identification drive the NLL's minimum lies within about +-0.7 % of the truth
(likelihood 1-sigma ~0.35 %), so tune on several bags. With the objective ``nll`` the estimate's
std is the curvature of the pooled NLL there (:func:`with_std`, :func:`.delay.profile_std`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import fields, replace

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.epochs.epoch import Epoch, EpochArrays
from transplanter_ident.tuning.delay import MIN_DELAY_EPOCHS, DelayObjective, warm_start
from transplanter_ident.tuning.factor_search import (
    FactorEstimate,
    TaskMap,
    pooled_factor_objective,
    search_factor,
    with_factor_std,
)
from transplanter_ident.tuning.problem import TuningProblem

#: factors on the configured scale searched (a sensor calibrated within 5 %)
FACTOR_RANGE = (0.95, 1.05)
COARSE_STEP = 0.005
FINE_STEP = 0.0005
#: factors either side of the minimum through which :func:`with_std` fits the NLL's parabola
CURVATURE_WINDOW = 0.0025
_NAMES = [f.name for f in fields(Epoch)]


def scaled_epochs(epochs: EpochArrays, factor: float) -> EpochArrays:
    """``epochs`` with every steering angle and steering rate multiplied by ``factor``."""
    rows = epochs.rows()
    rows[:, [_NAMES.index("steering"), _NAMES.index("steering_rate")]] *= factor
    return EpochArrays.from_rows(rows)


def without_gain_state(config: EstimatorConfig) -> EstimatorConfig:
    """``config`` with the steering gain's error not a filter state (the scale search's objective)."""
    if not config.options.estimate_steering_gain:
        return config
    return replace(config, options=replace(config.options, estimate_steering_gain=False))


def with_steering_scale(params: EstimatorParams, scale: float) -> EstimatorParams:
    """The parameters with ``vehicle.steering_scale`` = ``scale``."""
    config = params.config
    return replace(params, config=replace(config, vehicle=replace(config.vehicle, steering_scale=float(scale))))


def scale_objective(epochs: EpochArrays, config: EstimatorConfig, factor: float, objective: str,
                    tune_stiffness_noise: bool = False) -> tuple[float, int]:
    """(objective at the starting Q/R, epoch count) of one bag's epochs with the steering x ``factor``.

    Without the gain state (``ekf.estimate_steering_gain``): the filter's g would take up the factor searched.
    """
    if len(epochs) < MIN_DELAY_EPOCHS:
        return math.inf, len(epochs)
    config = without_gain_state(config)
    scaled = scaled_epochs(epochs, factor)
    problem = TuningProblem.from_epochs(warm_start(config, scaled), scaled, objective, tune_stiffness_noise)
    return float(problem(problem.start[None, :])[0]), len(epochs)


#: what the tuner advises when the scale's minimum is at an edge of the factors searched
EDGE_ADVICE = "calibrate the sensor against the wheel angle"


def search_steering_scale(objective: DelayObjective, configured: float, low: float = FACTOR_RANGE[0],
                          high: float = FACTOR_RANGE[1], coarse: float = COARSE_STEP,
                          fine: float = FINE_STEP) -> FactorEstimate:
    """Minimise ``objective`` (of factors on ``configured``) over [low, high]: coarse grid, then fine."""
    return search_factor(objective, "vehicle.steering_scale", configured, (low, high), coarse, fine, EDGE_ADVICE)


def with_std(estimate: FactorEstimate, epochs: int) -> FactorEstimate:
    """``estimate`` with its std: the curvature of the pooled NLL (mean over ``epochs`` epochs); +inf at an edge."""
    return with_factor_std(estimate, epochs, CURVATURE_WINDOW, FINE_STEP)


def pooled_scale_objective(bags: Sequence[EpochArrays], config: EstimatorConfig, objective: str,
                           tune_stiffness_noise: bool = False, run: TaskMap | None = None) -> DelayObjective:
    """The objective of a batch of factors, pooled over ``bags``; every (factor, bag) a task of ``run``."""
    return pooled_factor_objective(scale_objective, bags, config, objective, tune_stiffness_noise, run)
