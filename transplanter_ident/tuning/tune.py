"""Tuning Q and R on recorded epochs (paper eqs. 15-22) and comparing the result (Table 2).

:func:`tune` searches the log10 diagonal of Q and R (:mod:`.problem`) of one bag, and
:func:`tune_problem` that of any batch problem (several bags: :class:`.multi.MultiBagProblem`),
with IPSO or PSO (:mod:`.pso`) or CMA-ES (:mod:`.cmaes`), starting from the configured Q/R
as one of the candidates (:func:`optimize` picks the algorithm); :func:`compare` runs the
starting and the tuned filter over the same epochs for the paper's Table 2.
:func:`tuned_parameters` and :func:`header_comment` are what the tuner's YAML holds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig, NoiseParams
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.metrics import Table2Row, format_table2, table2_row
from transplanter_ident.tuning.box import Box
from transplanter_ident.tuning.cmaes import CmaesSettings, minimize_cmaes
from transplanter_ident.tuning.problem import Q_SPAN, TuningProblem, span_edges, span_words
from transplanter_ident.tuning.pso import (
    BatchObjective,
    IterationRecord,
    OptimizeResult,
    minimize,
    settings_for,
)

START_LABEL = "EKF (start Q/R)"
#: the optimisers: the paper's IPSO (eqs. 17-20), standard PSO (eqs. 15-16), CMA-ES (``cma``)
ALGORITHMS = ("ipso", "pso", "cmaes")


class Problem(Protocol):
    """What tuning needs of a problem (:class:`.problem.TuningProblem`, :class:`.multi.MultiBagProblem`)."""

    config: EstimatorConfig
    objective: str

    @property
    def names(self) -> tuple[str, ...]:
        """The searched entries (a position's columns)."""

    @property
    def box(self) -> Box:
        """The search box."""

    @property
    def q_span(self) -> float:
        """Decades either side of the configured Q searched."""

    @property
    def start(self) -> np.ndarray:
        """The configuration's Q/R as a position in the box."""

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        """Objective of each row of ``positions``."""

    def evaluate_noise(self, noise: NoiseParams) -> float:
        """Objective of one NoiseParams."""

    def tuned_config(self, position: np.ndarray) -> EstimatorConfig:
        """The configuration with the Q/R of ``position``."""


def optimize(algorithm: str, objective: BatchObjective, box: Box, *, particles: int = 20, iterations: int = 40,
             seed: int | np.random.Generator | None = None, initial: np.ndarray | None = None,
             max_evaluations: int | None = None,
             on_iteration: Callable[[IterationRecord], None] | None = None) -> OptimizeResult:
    """Minimise with ``ipso``, ``pso`` or ``cmaes``: F = ``particles`` per iteration, k_max = ``iterations``."""
    if algorithm == "cmaes":
        return minimize_cmaes(objective, box, CmaesSettings(particles=particles, iterations=iterations), seed,
                              initial=initial, max_evaluations=max_evaluations, on_iteration=on_iteration)
    if algorithm not in ALGORITHMS:
        raise ValueError(f"algorithm must be one of {', '.join(ALGORITHMS)}, got {algorithm!r}")
    settings = settings_for(algorithm, particles=particles, iterations=iterations)
    return minimize(objective, box, settings, seed, initial=initial, max_evaluations=max_evaluations,
                    on_iteration=on_iteration)


@dataclass(frozen=True)
class TuningOutcome:
    """What one tuning run produced."""

    problem: Problem
    result: OptimizeResult
    start_fitness: float
    seed: int
    seconds: float

    @property
    def start_config(self) -> EstimatorConfig:
        """The configuration tuning started from (hand-tuned Q/R)."""
        return self.problem.config

    @property
    def tuned_config(self) -> EstimatorConfig:
        """The configuration with the tuned Q/R."""
        return self.problem.tuned_config(self.result.position)


@dataclass(frozen=True)
class Comparison:
    """Table 2 for the starting and the tuned Q/R over the same epochs."""

    start: Table2Row
    tuned: Table2Row
    start_outputs: np.ndarray
    tuned_outputs: np.ndarray

    def ratio(self, name: str) -> float:
        """Ratio tuned / start of a Table2Row field (NaN if the start is 0 or not finite)."""
        before, after = getattr(self.start, name), getattr(self.tuned, name)
        return after / before if math.isfinite(before) and before > 0.0 else math.nan

    def format(self, title: str = "") -> str:
        """Table 2's layout, plus the tuned/start ratios of the mean errors."""
        table = format_table2([self.start, self.tuned], title)
        return (f"{table}\nratio tuned/start: mean err vy {self.ratio('mean_error_vy'):.3g}, "
                f"mean err r {self.ratio('mean_error_r'):.3g} (max err vy {self.ratio('max_error_vy'):.3g}, "
                f"max err r {self.ratio('max_error_r'):.3g})")


def tune(config: EstimatorConfig, epochs: EpochArrays, *, algorithm: str = "ipso", objective: str = "nll",
         particles: int = 20, iterations: int = 40, seed: int | None = None,
         max_evaluations: int | None = None, tune_stiffness_noise: bool = False, q_span: float = Q_SPAN,
         on_iteration: Callable[[IterationRecord], None] | None = None) -> TuningOutcome:
    """Search Q/R on ``epochs``; ``config``'s own Q/R (clipped to the box) is one of the initial particles.

    So the result is never worse than the starting Q/R when that lies inside the search box.
    ``seed`` None draws one (recorded in the outcome, so the run can be repeated). The physical
    noises are searched, and the stiffness random walks too with ``tune_stiffness_noise``; each
    process noise within ``q_span`` decades of the configured value.
    """
    problem = TuningProblem.from_epochs(config, epochs, objective, tune_stiffness_noise, q_span)
    return tune_problem(problem, algorithm=algorithm, particles=particles, iterations=iterations, seed=seed,
                        max_evaluations=max_evaluations, on_iteration=on_iteration)


def draw_seed() -> int:
    """A fresh random seed (recorded with the result, so the run can be repeated)."""
    return int(np.random.SeedSequence().entropy % 2**32)


def tune_problem(problem: Problem, *, algorithm: str = "ipso", particles: int = 20, iterations: int = 40,
                 seed: int | None = None, max_evaluations: int | None = None,
                 on_iteration: Callable[[IterationRecord], None] | None = None) -> TuningOutcome:
    """Search Q/R on any problem (one bag or several); its starting Q/R is one of the initial candidates."""
    seed = draw_seed() if seed is None else seed
    begin = time.perf_counter()
    result = optimize(algorithm, problem, problem.box, particles=particles, iterations=iterations, seed=seed,
                      initial=problem.start[None, :], max_evaluations=max_evaluations, on_iteration=on_iteration)
    seconds = time.perf_counter() - begin
    start_fitness = float(problem(problem.start[None, :])[0])  # as the swarm saw its starting particle
    return TuningOutcome(problem, result, start_fitness, seed, seconds)


def compare(outcome: TuningOutcome, epochs: EpochArrays, tuned_label: str | None = None) -> Comparison:
    """Table 2 rows of the starting and the tuned Q/R over ``epochs``."""
    label = tuned_label or f"{outcome.result.algorithm.upper()}-EKF (tuned)"
    return compare_configs(outcome.start_config, outcome.tuned_config, epochs, label)


def compare_configs(start: EstimatorConfig, tuned: EstimatorConfig, epochs: EpochArrays,
                    tuned_label: str = "IPSO-EKF (tuned)") -> Comparison:
    """Table 2 rows of two configurations over the same epochs."""
    start_out, tuned_out = run_sequence(start, epochs), run_sequence(tuned, epochs)
    return Comparison(table2_row(START_LABEL, epochs, start_out), table2_row(tuned_label, epochs, tuned_out),
                      start_out, tuned_out)


def tuned_parameters(config: EstimatorConfig) -> dict[str, Any]:
    """The flat keys the tuner writes: Q, R and the ekf options they are valid for."""
    options, noise = config.options, config.noise
    flat: dict[str, Any] = {
        "ekf.discretization": options.discretization,
        "ekf.stiffness_state": options.stiffness_state,
        "ekf.measurement": options.measurement,
        "ekf.process_noise": [float(v) for v in noise.process_noise],
        "ekf.measurement_noise": [float(v) for v in noise.measurement_noise],
        "ekf.process_noise_units": options.process_noise_units,  # Q per second (or per step of the file)
    }
    if options.process_noise_units == "per_step":
        flat["ekf.process_noise_step"] = float(options.process_noise_step)
    if options.heading_state:
        flat["ekf.heading_process_noise"] = float(noise.heading_process_noise)
    return flat


def edge_note(outcome: TuningOutcome) -> str:
    """A sentence naming the tuned Q entries at an edge of their span, or ''."""
    problem = outcome.problem
    edges = span_edges(problem.config, problem.names, problem.q_span, outcome.result.position)
    if not edges:
        return ""
    listed = ", ".join(f"{name} at its {side} edge" for name, side in edges)
    return (f"{listed} (searched {span_words(problem.q_span)}): the bags wanted more room there; before "
            "widening --q-span, check the leave-one-bag-out table (README)")


def _kept_line(outcome: TuningOutcome) -> list[str]:
    """The header lines on the span searched and on the stiffness random walk kept at its designed value (split Q)."""
    lines = [f"Q searched {span_words(outcome.problem.q_span)} (tuner --q-span)"]
    note = edge_note(outcome)
    if note:
        lines.append(note)
    if "q_cf" in outcome.problem.names:
        return lines
    q = outcome.problem.config.noise.process_noise
    return [*lines, f"kept by design (not tuned): q_cf={q[2]:.3g}, q_cr={q[3]:.3g} (stiffness random walk), the "
            "offset Q and the change mechanism; tuner --tune-stiffness-noise searches q_cf, q_cr too"]


def header_comment(outcome: TuningOutcome, bag: str | Sequence[str], epochs: int | Sequence[int]) -> str:
    """The YAML's comment header: provenance of the numbers (one ``bag:`` line per bag)."""
    result = outcome.result
    names = ", ".join(f"{n}={10.0**v:.3g}" for n, v in zip(outcome.problem.names, result.position, strict=True))
    bags = [bag] if isinstance(bag, (str, Path)) else list(bag)
    counts = [epochs] if isinstance(epochs, int) else list(epochs)
    lines = [f"bag: {Path(b).resolve()} ({n} epochs)" for b, n in zip(bags, counts, strict=True)]
    if len(bags) > 1:
        lines.insert(0, f"{len(bags)} bags, {sum(counts)} epochs; objective: epoch-weighted mean over the bags")
    return "\n".join([
        "Q and R tuned by transplanter_ident tuner (paper eqs. 15-22).",
        *lines,
        f"algorithm: {result.algorithm}, objective: {outcome.problem.objective}, seed: {outcome.seed}",
        f"fitness: {result.fitness:.6g} (start {outcome.start_fitness:.6g}), evaluations: {result.evaluations}, "
        f"iterations: {result.iterations}",
        f"tuned: {names}",
        *_kept_line(outcome),
        "Layer over the defaults: --params-file config/estimator.yaml --params-file <this file>",
    ])
