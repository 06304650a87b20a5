"""CMA-ES over the same box and budget as the swarms (an alternative to the paper's eqs. 15-20).

The covariance matrix adaptation evolution strategy of the ``cma`` package (N. Hansen) searches
the same log10 box of Q and R (eq. 22) as PSO and IPSO, with the same budget semantics, so the
three compare on equal terms (``bench/optimizers_bench.py``):

* **Coordinates:** CMA-ES runs in the box scaled to the unit cube (every dimension has width 1,
  so one step size fits all); ``cma``'s ``BoundTransform`` keeps every sample inside it.
* **Population and budget:** lambda = F (``particles``) samples per generation; generation 0
  is the "initial swarm" and k_max (``iterations``) generations follow, F (k_max + 1)
  evaluations in all, as standard PSO spends. ``max_evaluations`` caps the total (the batch
  that would exceed it is truncated, as in :mod:`.pso`).
* **Warm start:** the first ``initial`` position is the mean of the first generation and is
  injected into it, so the result is never worse than it (as the swarms' warm start).
* **Step size:** sigma0 = 0.3 of the box width (``sigma0``), the usual choice for a search
  that should cover the box.
* **Randomness:** the normal samples come from a ``numpy.random.Generator`` seeded by the
  caller (``cma``'s ``randn`` option); the few draws ``cma`` takes from numpy's global
  generator (mirrored sampling) are seeded from the same seed and the global state is
  restored afterwards. The same seed gives the same result.

The result is the best *evaluated* position (not the distribution mean), with one
:class:`~.pso.IterationRecord` per generation.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from transplanter_ident.tuning.box import Box
from transplanter_ident.tuning.pso import BatchObjective, IterationRecord, OptimizeResult


@dataclass(frozen=True)
class CmaesSettings:
    """Population F (lambda) and generations k_max after the first, plus the initial step size."""

    particles: int = 20  # lambda, as the swarm size F
    iterations: int = 40  # generations after the first, as k_max
    sigma0: float = 0.3  # initial step size as a fraction of the box width

    def __post_init__(self) -> None:
        for name in ("particles", "iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not (math.isfinite(self.sigma0) and 0.0 < self.sigma0 <= 1.0):
            raise ValueError(f"sigma0 must be in (0, 1], got {self.sigma0!r}")


@contextlib.contextmanager
def _numpy_global_seed(seed: int) -> Iterator[None]:
    """Seed numpy's legacy global generator for the block, then put its state back."""
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(saved)


def minimize_cmaes(
    objective: BatchObjective,
    box: Box,
    settings: CmaesSettings,
    seed: int | np.random.Generator | None = None,
    *,
    initial: np.ndarray | Sequence[Sequence[float]] | None = None,
    max_evaluations: int | None = None,
    on_iteration: Callable[[IterationRecord], None] | None = None,
) -> OptimizeResult:
    """Minimise the batch ``objective`` over ``box`` with CMA-ES (same arguments as :func:`.pso.minimize`)."""
    try:
        import cma  # only this optimiser needs it
    except ImportError:
        raise ValueError("CMA-ES needs the cma package, which is not installed (pip install cma)") from None

    if max_evaluations is not None and max_evaluations < 1:
        raise ValueError(f"max_evaluations must be >= 1, got {max_evaluations!r}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    dimension, low, width = box.dimension, box.low, box.width
    if initial is not None and len(np.atleast_2d(initial)):
        start = box.clip(np.atleast_2d(np.asarray(initial, dtype=np.float64)))
        if start.shape[1] != dimension:
            raise ValueError(f"initial positions must have {dimension} columns, got {start.shape[1]}")
        mean0 = (start[0] - low) / width
    else:
        start, mean0 = None, np.full(dimension, 0.5)
    options = {
        "popsize": settings.particles, "bounds": [0.0, 1.0], "seed": math.nan, "verbose": -9,
        "verb_disp": 0, "verb_log": 0, "verb_filenameprefix": "", "maxiter": math.inf, "maxfevals": math.inf,
        "tolfun": 0.0, "tolx": 0.0, "tolfunhist": 0.0, "tolstagnation": math.inf, "tolflatfitness": math.inf,
        "randn": lambda count, n: rng.standard_normal((count, n)),
    }
    limit = settings.particles * (settings.iterations + 1)
    limit = limit if max_evaluations is None else min(limit, max_evaluations)
    best_x, best_f, used = None, math.inf, 0
    history: list[IterationRecord] = []
    with _numpy_global_seed(int(rng.integers(1, 2**31 - 1))):
        es = cma.CMAEvolutionStrategy(np.clip(mean0, 0.0, 1.0), settings.sigma0, options)
        if start is not None:
            es.inject([np.clip((start[0] - low) / width, 0.0, 1.0)], force=True)
        generation = 0
        while used < limit:
            unit = np.asarray(es.ask(), dtype=np.float64)
            take = min(len(unit), limit - used)
            points = box.clip(low + unit[:take] * width)
            values = np.asarray(objective(np.ascontiguousarray(points)), dtype=np.float64)
            if values.shape != (take,):
                raise ValueError(f"objective returned shape {values.shape}, expected ({take},)")
            values = np.where(np.isnan(values), np.inf, values)
            used += take
            leader = int(np.argmin(values))
            if best_x is None or values[leader] < best_f:
                best_x, best_f = points[leader].copy(), float(values[leader])
            if take == len(unit):
                # cma ranks the samples; infinite (diverged) ones go last, with a finite stand-in
                finite = values[np.isfinite(values)]
                worst = float(finite.max()) if len(finite) else 0.0
                ranked = np.where(np.isfinite(values), values, worst + 1.0 + abs(worst))
                es.tell(list(unit), ranked.tolist())
            history.append(IterationRecord(iteration=generation, best_fitness=best_f,
                                           median_fitness=float(np.median(values)), evaluations=used,
                                           chaotic_particles=0))
            if on_iteration is not None:
                on_iteration(history[-1])
            generation += 1
    assert best_x is not None  # limit >= 1, so at least one evaluation happened
    return OptimizeResult(algorithm="cmaes", position=best_x, fitness=best_f, evaluations=used,
                          history=tuple(history))
