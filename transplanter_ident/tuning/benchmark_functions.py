"""Reference problems for the optimisers: random search, Rastrigin and Ackley (shifted).

Used by the optimiser tests and benchmarks to check PSO and IPSO (paper eqs. 15-20) on
functions with known minima.
"""

from __future__ import annotations

import math

import numpy as np

from transplanter_ident.tuning.box import Box
from transplanter_ident.tuning.pso import BatchObjective, IterationRecord, OptimizeResult


def random_search(objective: BatchObjective, box: Box, evaluations: int,
                  seed: int | np.random.Generator | None = None) -> OptimizeResult:
    """Baseline: the best of ``evaluations`` uniform samples of the box."""
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    x = box.uniform(rng, evaluations)
    f = np.asarray(objective(x), dtype=np.float64)
    best = int(np.argmin(f))
    record = IterationRecord(0, float(f[best]), float(np.median(f)), evaluations, 0)
    return OptimizeResult("random", x[best].copy(), float(f[best]), evaluations, (record,))


def rastrigin(x: np.ndarray) -> np.ndarray:
    """Rastrigin, batch form: 10 D + sum(x^2 - 10 cos(2 pi x)); minimum 0 at x = 0."""
    x = np.atleast_2d(x)
    return 10.0 * x.shape[1] + np.sum(x * x - 10.0 * np.cos(2.0 * math.pi * x), axis=1)


def ackley(x: np.ndarray) -> np.ndarray:
    """Ackley, batch form; minimum 0 at x = 0."""
    x = np.atleast_2d(x)
    d = x.shape[1]
    term1 = -20.0 * np.exp(-0.2 * np.sqrt(np.sum(x * x, axis=1) / d))
    term2 = -np.exp(np.sum(np.cos(2.0 * math.pi * x), axis=1) / d)
    return term1 + term2 + 20.0 + math.e


def shifted(function: BatchObjective, shift: np.ndarray) -> BatchObjective:
    """function(x - shift): moves the optimum away from the box centre (eq. 17 pulls towards it)."""
    offset = np.asarray(shift, dtype=np.float64)

    def moved(x: np.ndarray) -> np.ndarray:
        return function(np.atleast_2d(x) - offset)

    return moved
