"""Estimating the GNSS delay ``gnss.delay`` offline (issue #13 item 4; DESIGN.md section 7).

A GNSS sample stamped t describes the motion at t - delay. At farm speeds the stiffness is read
off a lateral lag of 40-65 ms, so an unconfigured delay of 80 ms costs about half the stiffness;
the delay is a calibration constant, best found from the recorded drives.

The search is one-dimensional, ahead of the Q/R search, on the tuner's own objective (eq. 21's
mean |innovation| or the innovation NLL, :mod:`.problem`) at the *starting* Q/R, averaged over
the bags with their epoch counts as weights (as :class:`.multi.MultiBagProblem`). Each delay
gives its own epochs: the bag's input samples, decoded once (``bags.inputs``), are assembled
again by the node's :class:`~transplanter_ident.epochs.assembler.EpochAssembler` with that
delay (:func:`assemble_epochs`). A wrong delay shifts the measured response against the
steering input, which the filter cannot explain, so the objective has its minimum near the
true delay. :func:`search_delay`: a coarse grid over [low, high] (default -0.2-0.3 s in 20 ms
steps: a GNSS driver that stamps on arrival is late, a steering driver that does is early, which
is a negative delay), then a fine grid (2 ms) within one coarse step either side of the coarse
minimum; the best point wins (ties: the delay nearest 0). Every grid's points are independent, so
the caller evaluates them in parallel. A minimum at an edge of the range does not pin the delay
(it may lie beyond): its std is +inf and the estimate says so (:attr:`DelayEstimate.at_edge`).

The estimate's std (:func:`profile_std`, objective ``nll`` only) comes from the curvature of the
total NLL around the minimum: the objective is a profile likelihood (the filter re-estimates the
stiffness at every delay), so the delay's confounding with the stiffness is in it. It is what
``tuner`` writes as ``ekf.delay_uncertainty``: at 2 m/s every millisecond left moves Cf, Cr ~2 %.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.ekf.layout import O_CF, O_CR, O_OFFSET
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler, assemble
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.tuning.problem import TuningProblem

#: s: the delays searched (GNSS receivers stamped on arrival are 0-0.3 s late; a steering sensor
#: stamped on arrival, behind a GNSS stamped by its receiver, makes the delay negative)
DELAY_RANGE = (-0.2, 0.3)
COARSE_STEP = 0.02  # s
FINE_STEP = 0.002  # s
#: s: the fine points either side of the minimum through which :func:`profile_std` fits its parabola
CURVATURE_WINDOW = 0.010
#: fewer epochs than this at a delay: that delay scores +inf
MIN_DELAY_EPOCHS = 10
#: rad: the range of ``vehicle.steering_offset`` (config/schema.py)
MAX_OFFSET = 0.3

Sample = tuple[str, float, tuple[float, ...]]
#: objective of each delay of a batch (s) -> values (lower is better; non-finite = unusable)
DelayObjective = Callable[[Sequence[float]], Sequence[float]]
#: delays of a batch (s) -> for each delay, every bag's (objective, epochs) (:func:`delay_objective`)
BagScores = Callable[[Sequence[float]], Sequence[Sequence[tuple[float, int]]]]


def with_delay(params: EstimatorParams, delay: float) -> EstimatorParams:
    """The parameters with ``gnss.delay`` = ``delay`` (s)."""
    return replace(params, gnss=replace(params.gnss, delay=float(delay)))


def assemble_epochs(samples: Sequence[Sample], params: EstimatorParams, delay: float) -> EpochArrays:
    """The epochs of ``samples`` (in arrival order) under the parameters with ``gnss.delay`` = ``delay``."""
    settings = AssemblerSettings.from_params(with_delay(params, delay))
    return EpochArrays(assemble(EpochAssembler(settings), samples))


#: relative 1-sigma of the warm start's stiffness (the first pass's end); wide enough for any factor searched,
#: whose first pass ends at that factor's own stiffness
WARM_START_STD = 0.1


def warm_start(config: EstimatorConfig, epochs: EpochArrays) -> EstimatorConfig:
    """``config`` started from the stiffness and steering offset a first pass over ``epochs`` ends with.

    The stiffness's initial std is then WARM_START_STD (relative) where P0's was wider: from P0's
    (a factor of e^2 in ln C) the first seconds of a drive could throw the stiffness a factor of 16
    and diverge the single pass a candidate is scored with, at some candidates and not at others
    (a 1-D Iz search put Iz 17 % off with a std of 1 %, the NLL's jump there read as curvature).
    """
    final = run_sequence(config, epochs)[-1]
    low, high = config.options.stiffness_bounds
    stiffness = tuple(float(np.clip(final[i], low, high)) for i in (O_CF, O_CR))
    if not all(math.isfinite(v) for v in (*stiffness, final[O_OFFSET])):
        return config
    offset = float(np.clip(final[O_OFFSET], -MAX_OFFSET, MAX_OFFSET))
    log_state = config.options.stiffness_state == "log"
    p0 = config.noise.initial_covariance
    narrowed = tuple(min(p0[2 + i], WARM_START_STD ** 2 * (1.0 if log_state else c * c)) for i, c in enumerate(stiffness))
    return replace(config, noise=replace(config.noise, initial_stiffness=stiffness, initial_covariance=(*p0[:2], *narrowed)),
                   vehicle=replace(config.vehicle, steering_offset=offset))


def delay_objective(samples: Sequence[Sample], params: EstimatorParams, delay: float, objective: str,
                    tune_stiffness_noise: bool = False, warm: bool = True) -> tuple[float, int]:
    """(objective at the starting Q/R, epoch count) of one bag's samples assembled with ``delay``.

    ``warm``: the filter starts from the stiffness and offset a first pass at this delay ended with
    (:func:`warm_start`), so the start-up transient from ``ekf.initial_stiffness`` does not bias the delay.
    """
    epochs = assemble_epochs(samples, params, delay)
    if len(epochs) < MIN_DELAY_EPOCHS:
        return math.inf, len(epochs)
    config = warm_start(params.config, epochs) if warm else params.config
    problem = TuningProblem.from_epochs(config, epochs, objective, tune_stiffness_noise)
    return float(problem(problem.start[None, :])[0]), len(epochs)


def pooled(per_bag: Sequence[tuple[float, int]]) -> float:
    """Epoch-weighted mean of per-bag (value, epochs), summed in bag order; +inf if any bag is unusable."""
    total, count = 0.0, 0
    for value, epochs in per_bag:
        if not math.isfinite(value):
            return math.inf
        total += epochs * value
        count += epochs
    return total / count if count else math.inf


def profile_std(points: Sequence[tuple[float, float]], best: float, epochs: int,
                window: float = CURVATURE_WINDOW, step: float = FINE_STEP) -> float:
    """1-sigma (s) of the delay ``best`` found on a grid of ``step``, from the curvature of the NLL there.

    ``points``: (delay, mean NLL per epoch) as the search evaluated them; ``epochs``: how many epochs
    that mean is over. ``epochs x value`` is -ln L up to a constant, so a least-squares parabola
    a (d - best)^2 + b (d - best) + c through the finite points within ``window`` of ``best`` gives
    the observed information 2a: std^2 = 1 / 2a, plus step^2 / 12 for the grid's rounding. +inf for a
    curvature that is not positive (the data do not pin the delay); NaN with fewer than three points.
    """
    near = np.array([(d - best, v) for d, v in points if abs(d - best) <= window + 1e-9 and math.isfinite(v)])
    if len(near) < 3 or epochs <= 0:
        return math.nan
    curvature = float(np.polyfit(near[:, 0], epochs * near[:, 1], 2)[0])
    return math.sqrt(0.5 / curvature + step**2 / 12.0) if curvature > 0.0 else math.inf


@dataclass(frozen=True)
class DelayEstimate:
    """The delay with the lowest objective, every (delay, objective) evaluated (by delay), and its std.

    ``std`` (s): :func:`profile_std`; NaN where it is not known (objective ``mae``), +inf where nothing pins it.
    """

    delay: float
    fitness: float
    points: tuple[tuple[float, float], ...]
    std: float = math.nan
    bounds: tuple[float, float] = DELAY_RANGE  # s, the range searched

    @property
    def at_edge(self) -> bool:
        """Whether the minimum lies at an edge of the range searched (the delay may lie beyond it)."""
        return at_range_edge(self.delay, self.bounds)

    def value_at(self, delay: float) -> float:
        """The objective evaluated at ``delay`` (NaN if it was not evaluated)."""
        return next((v for d, v in self.points if abs(d - delay) < 1e-9), math.nan)

    def format(self, objective: str = "objective") -> str:
        """One line: the estimate, its objective, and the objective at 0 s for comparison."""
        at_zero = self.value_at(0.0)
        zero = f"; at 0 ms {at_zero:.6g}" if math.isfinite(at_zero) else ""
        spread = f" +- {1e3 * self.std:.1f}" if math.isfinite(self.std) else ""
        low, high = (round(1e3 * b) for b in self.bounds)
        edge = (f"; at the edge of the range searched, [{low}, {high}] ms: the delay may lie beyond it, widen "
                "--delay-range" if self.at_edge else "")
        return (f"gnss.delay: {1e3 * self.delay:.0f}{spread} ms ({objective} {self.fitness:.6g} at the starting "
                f"Q/R{zero}; {len(self.points)} delays evaluated{edge})")


def serial_scores(bags: Sequence[Sequence[Sample]], params: EstimatorParams, objective: str,
                  warm: bool = True) -> BagScores:
    """:data:`BagScores` of the bags' samples, evaluated one after the other in this process."""
    return lambda delays: [[delay_objective(samples, params, d, objective, warm=warm) for samples in bags]
                           for d in delays]


class PooledScores:
    """The bags' :func:`pooled` objective of a batch of candidates: delays, plays or (delay, play) pairs.

    ``scores``: per candidate, every bag's (value, epochs). Each candidate's epoch count (``epochs``) and
    value (``values``) are kept, for the NLL's curvature.
    """

    def __init__(self, scores: Callable[[Sequence[Any]], Sequence[Sequence[tuple[float, int]]]]) -> None:
        self.scores = scores
        self.epochs: dict[Any, int] = {}
        self.values: dict[Any, float] = {}

    def __call__(self, candidates: Sequence[Any]) -> list[float]:
        per_candidate = self.scores(candidates)
        values = [pooled(bags) for bags in per_candidate]
        for candidate, bags, value in zip(candidates, per_candidate, values, strict=True):
            self.epochs[candidate] = sum(n for _, n in bags)
            self.values[candidate] = value
        return values


def grid_estimate(scores: BagScores, objective: str, bounds: tuple[float, float], coarse: float, fine: float,
                  window: float, what: str) -> tuple[float, float, tuple[tuple[float, float], ...], float]:
    """(best, its value, every (point, value), std): :func:`grid_search` of the bags' pooled objective (ties: 0).

    The std (:func:`profile_std` within ``window``) only with ``nll``, a likelihood (else NaN); +inf at an edge of
    ``bounds``: the minimum may lie beyond them, and nothing within them pins it.
    """
    pooled_objective = PooledScores(scores)
    best, fitness, points = grid_search(pooled_objective, *bounds, coarse, fine, what, prefer=0.0)
    if objective != "nll":
        return best, fitness, points, math.nan
    if at_range_edge(best, bounds):
        return best, fitness, points, math.inf
    return best, fitness, points, profile_std(points, best, pooled_objective.epochs[best], window, fine)


def estimate_delay(scores: BagScores, objective: str, low: float = DELAY_RANGE[0],
                   high: float = DELAY_RANGE[1]) -> DelayEstimate:
    """:func:`search_delay`'s grids on the bags' :func:`pooled` objective; with ``nll`` also its :func:`profile_std`."""
    best, fitness, points, std = grid_estimate(scores, objective, (low, high), COARSE_STEP, FINE_STEP,
                                               CURVATURE_WINDOW, "delay")
    return DelayEstimate(best, fitness, points, std, (low, high))


def grid_points(low: float, high: float, step: float) -> list[float]:
    """low, low + step, ..., high (the step rounded to fit), to 9 decimals."""
    count = max(1, round((high - low) / step))
    return [float(v) for v in np.round(np.linspace(low, high, count + 1), 9)]


def search_delay(objective: DelayObjective, low: float = DELAY_RANGE[0], high: float = DELAY_RANGE[1],
                 coarse: float = COARSE_STEP, fine: float = FINE_STEP) -> DelayEstimate:
    """Minimise ``objective`` over [low, high]: a coarse grid, then a fine grid around its minimum (ties: nearest 0)."""
    return DelayEstimate(*grid_search(objective, low, high, coarse, fine, "delay", prefer=0.0), bounds=(low, high))


def at_range_edge(point: float, bounds: tuple[float, float]) -> bool:
    """Whether a grid search's ``point`` is an end of its ``bounds`` (its minimum may lie beyond them)."""
    return min(abs(point - bounds[0]), abs(point - bounds[1])) < 1e-9


def grid_search(objective: DelayObjective, low: float, high: float, coarse: float, fine: float,
                what: str = "grid", prefer: float | None = None) -> tuple[float, float, tuple[tuple[float, float], ...]]:
    """(best point, its value, every (point, value) by point): a coarse grid, then a fine one around its minimum.

    Ties go to the point nearest ``prefer`` (default ``low``), then to the smaller; a non-finite value
    counts as +inf. Shared by the calibration searches.
    """
    if not (math.isfinite(low) and math.isfinite(high) and low < high and 0.0 < fine <= coarse):
        raise ValueError(f"{what} search: need low < high and 0 < fine <= coarse, got [{low}, {high}], {coarse}, "
                         f"{fine}")
    seen: dict[float, float] = {}

    def evaluate(delays: list[float]) -> None:
        todo = [d for d in delays if d not in seen]
        if todo:
            values = objective(todo)
            seen.update((d, float(v) if math.isfinite(v) else math.inf) for d, v in zip(todo, values, strict=True))

    centre = low if prefer is None else prefer

    def order(d: float) -> tuple[float, float, float]:
        return seen[d], abs(d - centre), d

    evaluate(grid_points(low, high, coarse))
    best = min(seen, key=order)
    evaluate(grid_points(max(low, best - coarse), min(high, best + coarse), fine))
    best = min(seen, key=order)
    return best, seen[best], tuple(sorted(seen.items()))
