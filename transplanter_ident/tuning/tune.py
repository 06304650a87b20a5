"""Tuning Q and R on recorded epochs (paper eqs. 15-22) and comparing the result (Table 2).

:func:`tune` searches the log10 diagonal of Q and R (:mod:`.problem`) with IPSO or PSO
(:mod:`.pso`), starting from the configured Q/R as one of the particles; :func:`compare`
runs the starting and the tuned filter over the same epochs for the paper's Table 2.
:func:`tuned_parameters` and :func:`header_comment` are what the tuner's YAML holds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.metrics import Table2Row, format_table2, table2_row
from transplanter_ident.tuning.problem import NAMES, TuningProblem
from transplanter_ident.tuning.pso import IterationRecord, OptimizeResult, minimize, settings_for

START_LABEL = "EKF (start Q/R)"


@dataclass(frozen=True)
class TuningOutcome:
    """What one tuning run produced."""

    problem: TuningProblem
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
         max_evaluations: int | None = None,
         on_iteration: Callable[[IterationRecord], None] | None = None) -> TuningOutcome:
    """Search Q/R on ``epochs``; ``config``'s own Q/R (clipped to the box) is one of the initial particles.

    So the result is never worse than the starting Q/R when that lies inside the search box.
    ``seed`` None draws one (recorded in the outcome, so the run can be repeated).
    """
    seed = int(np.random.SeedSequence().entropy % 2**32) if seed is None else seed
    problem = TuningProblem.from_epochs(config, epochs, objective)
    settings = settings_for(algorithm, particles=particles, iterations=iterations)
    begin = time.perf_counter()
    result = minimize(problem, problem.box, settings, seed, initial=problem.start[None, :],
                      max_evaluations=max_evaluations, on_iteration=on_iteration)
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
    }
    if options.measurement == "heading":
        flat["ekf.heading_process_noise"] = float(noise.heading_process_noise)
    return flat


def header_comment(outcome: TuningOutcome, bag: str, epochs: int) -> str:
    """The YAML's comment header: provenance of the numbers."""
    result = outcome.result
    names = ", ".join(f"{n}={10.0**v:.3g}" for n, v in zip(NAMES, result.position, strict=True))
    return "\n".join([
        "Q and R tuned by transplanter_ident tuner (paper eqs. 15-22).",
        f"bag: {Path(bag).resolve()} ({epochs} epochs)",
        f"algorithm: {result.algorithm}, objective: {outcome.problem.objective}, seed: {outcome.seed}",
        f"fitness: {result.fitness:.6g} (start {outcome.start_fitness:.6g}), evaluations: {result.evaluations}, "
        f"iterations: {result.iterations}",
        f"tuned: {names}",
        "Layer over the defaults: --params-file config/estimator.yaml --params-file <this file>",
    ])
