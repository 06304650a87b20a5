"""One Q/R for several bags (eqs. 21-22 summed over bags) and the leave-one-bag-out check.

:class:`MultiBagProblem` is the tuning objective over several epoch sequences: the per-bag
objective (eq. 21's mean |innovation| or the innovation NLL, each a mean over its epochs)
averaged with the bags' epoch counts as weights, i.e. the objective of all epochs pooled,
with every bag filtered from its own start. The bags are evaluated on a
:mod:`.parallel` backend and summed here in a fixed order, so the value does not depend on
where they ran.

:func:`leave_one_out` checks that the tuned Q/R hold on drives they were not tuned on: for
each bag, Q/R tuned on the *other* bags are scored on it (held-out objective and, with ground
truth, the final stiffness error), next to the starting Q/R, Q/R tuned on that bag alone, and
Q/R tuned on one other bag alone (the median over the other bags: single-bag tuning on a drive it
has not seen, the overfitting multi-bag tuning is meant to avoid).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig, NoiseParams
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.metrics import stiffness_error
from transplanter_ident.tuning.box import Box
from transplanter_ident.tuning.parallel import Backend, SerialBackend
from transplanter_ident.tuning.problem import Q_SPAN, TuningProblem


class StiffnessTruth(Protocol):
    """True (Cf, Cr) at given times (``bags.Truth``)."""

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Cf, Cr) at times ``t``."""


@dataclass(frozen=True)
class MultiBagProblem:
    """The epoch-weighted mean of the per-bag objectives, as a batch function of the log10 Q/R vector."""

    problems: tuple[TuningProblem, ...]
    backend: Backend = field(default_factory=SerialBackend, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not self.problems:
            raise ValueError("a multi-bag problem needs at least one bag")
        first = self.problems[0]
        for other in self.problems[1:]:
            if (other.config, other.objective, other.names, other.q_span) != (first.config, first.objective,
                                                                              first.names, first.q_span):
                raise ValueError("every bag of a multi-bag problem must share the configuration, objective and "
                                 "searched entries and span")

    @classmethod
    def from_epochs(cls, config: EstimatorConfig, epochs: Sequence[EpochArrays], objective: str = "nll",
                    backend: Backend | None = None, tune_stiffness_noise: bool = False,
                    q_span: float = Q_SPAN) -> MultiBagProblem:
        """One TuningProblem per epoch sequence, evaluated on ``backend`` (default: here)."""
        problems = tuple(TuningProblem.from_epochs(config, e, objective, tune_stiffness_noise, q_span)
                         for e in epochs)
        return cls(problems, backend if backend is not None else SerialBackend())

    # the search space and the configuration are those of every bag (delegated, so new dimensions follow)
    @property
    def config(self) -> EstimatorConfig:
        """The starting configuration."""
        return self.problems[0].config

    @property
    def objective(self) -> str:
        """``mae`` or ``nll``."""
        return self.problems[0].objective

    @property
    def names(self) -> tuple[str, ...]:
        """The searched entries."""
        return self.problems[0].names

    @property
    def q_span(self) -> float:
        """Decades either side of the configured Q searched."""
        return self.problems[0].q_span

    @property
    def box(self) -> Box:
        """The search box."""
        return self.problems[0].box

    @property
    def start(self) -> np.ndarray:
        """The starting Q/R as a position in the box."""
        return self.problems[0].start

    def tuned_config(self, position: np.ndarray) -> EstimatorConfig:
        """The configuration with the Q/R of ``position``."""
        return self.problems[0].tuned_config(position)

    @property
    def epochs(self) -> tuple[int, ...]:
        """Epochs per bag (the weights)."""
        return tuple(len(p.kernel_input) for p in self.problems)

    def subset(self, indices: Sequence[int]) -> MultiBagProblem:
        """The problem over the bags ``indices`` only (same backend)."""
        return replace(self, problems=tuple(self.problems[i] for i in indices))

    def combine(self, per_bag: np.ndarray) -> np.ndarray:
        """Epoch-weighted mean over the bags (rows) of per-bag values, summed in bag order."""
        if len(per_bag) == 1:
            return np.array(per_bag[0], dtype=np.float64)  # one bag: its own objective, untouched
        weights = self.epochs
        total = np.zeros(per_bag.shape[1:])
        for weight, row in zip(weights, per_bag, strict=True):
            total = total + weight * row
        return total / float(sum(weights))

    def per_bag(self, positions: np.ndarray) -> np.ndarray:
        """(bags, m) objective of each candidate on each bag."""
        return self.backend.evaluate(self.problems, np.atleast_2d(np.asarray(positions, dtype=np.float64)))

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        """The multi-bag objective of each row of ``positions``."""
        return self.combine(self.per_bag(positions))

    def evaluate_noise(self, noise: NoiseParams) -> float:
        """The multi-bag objective of one NoiseParams (not clipped to the box), here."""
        values = np.array([[p.evaluate_noise(noise)] for p in self.problems])
        return float(self.combine(values)[0])


# --------------------------------------------------------------------------- leave one bag out


@dataclass(frozen=True)
class HoldOut:
    """One bag of the leave-one-bag-out check: its objective and final stiffness errors under three Q/R.

    ``elsewhere``: (|Cf|, |Cr|) final error with Q/R tuned on one *other* bag alone, the median over
    the other bags (the single-bag tuning used on a drive it has not seen).
    """

    name: str
    epochs: int
    objective: tuple[float, float, float]  # starting Q/R, tuned on this bag alone, tuned on the others
    final_cf: tuple[float, float, float] | None  # relative final error of Cf (ground truth only)
    final_cr: tuple[float, float, float] | None
    elsewhere: tuple[float, float] | None = None


COLUMNS = ("default", "single", "others")


@dataclass(frozen=True)
class LeaveOneOut:
    """The leave-one-bag-out table."""

    objective: str
    rows: tuple[HoldOut, ...]

    def wins(self) -> tuple[int, int, int, int]:
        """(bags with truth, |Cf| and |Cr| of 'others' <= 'default' on both, <= 'single', <= 'one other')."""
        truth = [r for r in self.rows if r.final_cf is not None and r.final_cr is not None]
        not_worse = lambda r, i: all(abs(e[2]) <= abs(e[i]) for e in (r.final_cf, r.final_cr))  # noqa: E731
        elsewhere = [r for r in truth if r.elsewhere is not None
                     and abs(r.final_cf[2]) <= r.elsewhere[0] and abs(r.final_cr[2]) <= r.elsewhere[1]]
        return len(truth), sum(not_worse(r, 0) for r in truth), sum(not_worse(r, 1) for r in truth), len(elsewhere)

    def format(self) -> str:
        """The table: objective and final stiffness errors with default / single-bag / multi-bag Q/R."""
        width = max([12, *(len(r.name) for r in self.rows)])
        lines = [
            f"Leave-one-bag-out ({self.objective}): 'others' = Q/R tuned on the other bags, scored on this bag "
            "(held out); 'single' = tuned on this bag alone (in-sample); 'default' = the starting Q/R; "
            "'1 other' = median |error| with Q/R tuned on one other bag alone",
            f"{'bag':<{width}}{'epochs':>8}  {'objective: default':>18}{'single':>11}{'others':>11}"
            f"  {'final Cf err: default':>21}{'single':>9}{'others':>9}{'1 other':>9}  {'final Cr err: default':>21}"
            f"{'single':>9}{'others':>9}{'1 other':>9}",
        ]
        pct = lambda v: f"{100.0 * v:+.1f}%" if math.isfinite(v) else "nan"  # noqa: E731
        for r in self.rows:
            cf = [pct(v) for v in r.final_cf] if r.final_cf is not None else ["-"] * 3
            cr = [pct(v) for v in r.final_cr] if r.final_cr is not None else ["-"] * 3
            far = [f"{100.0 * v:.1f}%" for v in r.elsewhere] if r.elsewhere is not None else ["-"] * 2
            obj = r.objective
            lines.append(f"{r.name:<{width}}{r.epochs:>8}  {obj[0]:>18.6g}{obj[1]:>11.6g}{obj[2]:>11.6g}"
                         f"  {cf[0]:>21}{cf[1]:>9}{cf[2]:>9}{far[0]:>9}  {cr[0]:>21}{cr[1]:>9}{cr[2]:>9}{far[1]:>9}")
        count, vs_default, vs_single, vs_elsewhere = self.wins()
        if count:
            lines.append(f"held-out |error| of Cf and Cr with multi-bag Q/R <= default on {vs_default}/{count} "
                         f"bags, <= single-bag (in-sample) on {vs_single}/{count}, <= single-bag tuned on one "
                         f"other bag (median) on {vs_elsewhere}/{count}")
        return "\n".join(lines)


def fold_seed(seed: int, kind: int, index: int) -> int:
    """The seed of one leave-one-out tuning run, derived from the main seed."""
    return int(np.random.SeedSequence([seed, kind, index]).generate_state(1)[0])


def final_errors(configs: Sequence[EstimatorConfig], epochs: EpochArrays,
                 truth: StiffnessTruth) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Final relative Cf and Cr errors of each configuration on ``epochs`` against ``truth``."""
    true_f, true_r = truth.at(epochs.t)
    errors = [stiffness_error(run_sequence(c, epochs), true_f, true_r) for c in configs]
    return tuple(e.final_front for e in errors), tuple(e.final_rear for e in errors)


TuneFn = Callable[[MultiBagProblem, int], EstimatorConfig]


def leave_one_out(problem: MultiBagProblem, epochs: Sequence[EpochArrays], truths: Sequence[StiffnessTruth | None],
                  names: Sequence[str], tune: TuneFn, seed: int,
                  on_fold: Callable[[str], None] | None = None) -> LeaveOneOut:
    """For each bag: ``tune`` (problem, seed) -> config on the others and on it alone; score all on it.

    Each bag's single-bag Q/R is also scored on every other bag (the 'one other' column).
    """
    count = len(problem.problems)
    if count < 2:
        raise ValueError("leave-one-bag-out needs at least two bags")
    singles = [tune(problem.subset([i]), fold_seed(seed, 2, i)) for i in range(count)]
    rows = []
    for i in range(count):
        others = [j for j in range(count) if j != i]
        multi = tune(problem.subset(others), fold_seed(seed, 1, i))
        configs = (problem.config, singles[i], multi)
        bag = problem.problems[i]
        objective = tuple(bag.evaluate_noise(c.noise) for c in configs)
        cf = cr = elsewhere = None
        if truths[i] is not None:
            cf, cr = final_errors(configs, epochs[i], truths[i])
            far_cf, far_cr = final_errors([singles[j] for j in others], epochs[i], truths[i])
            elsewhere = (float(np.median(np.abs(far_cf))), float(np.median(np.abs(far_cr))))
        rows.append(HoldOut(names[i], len(epochs[i]), objective, cf, cr, elsewhere))
        if on_fold is not None:
            on_fold(f"leave-one-out {i + 1}/{count}: {names[i]}: held-out {problem.objective} "
                    f"{objective[2]:.6g} (default {objective[0]:.6g}, single-bag {objective[1]:.6g})")
    return LeaveOneOut(problem.objective, tuple(rows))
