"""Particle swarm optimisers over a box: standard PSO (paper eqs. 15-16) and IPSO (eqs. 17-20).

Both minimise a *batch* objective ``f(positions (m, D)) -> fitness (m,)`` so that a whole swarm
is evaluated in one call (the tuner evaluates candidates in parallel, compiled).

Standard PSO, eqs. (15) and (16) with the erratum of eq. (16) fixed (DESIGN.md section 1)::

    v(k+1) = w v(k) + c1 r1 (p - x(k)) + c2 r2 (g - x(k))                         (15)
    x(k+1) = x(k) + v(k+1)                                                         (16, fixed)

The inertia w falls linearly from 0.9 to 0.4 with t = k / k_max (k = 1 .. k_max).

IPSO adds the adaptive detection radius of eq. (17), with t read as k / k_max (DESIGN.md)::

    R(k) = (x_max + x_min) / 2 + (x_max - x_min) / 2 * exp(-lambda t) cos(2 pi u)   (17)
    v(k+1) = ... as (15) ... + c3 r3 (R(k) - x(k))                                 (18)

and a chaotic local search for stagnating particles. A particle whose personal best improved
by less than delta for N consecutive iterations stagnates; it then takes up to N_max logistic-map
steps (eqs. 19-20) around its position::

    y(j+1) = 4 y(j) (1 - y(j)),  y(0) ~ U(0, 1) per dimension                       (19)
    x_cand = x + R_d (2 y(j) - 1)                                                   (20)

moving to the first candidate that is better and ending its search there ("up to N_max
steps"); the stagnation counter restarts afterwards.

Choices the paper leaves open (documented, so that results are reproducible):

* **Units of R_d.** The paper's R_d = 10 refers to its unscaled parameter space, which it
  does not state. Here the box may have any scale (the tuner searches log10 values), so
  R_d is read as a *fraction of each dimension's width*: the paper's 10 becomes 10 %
  (``chaos_radius = 0.1``). Chaotic candidates are clipped to the box.
* **Velocity clamping:** |v_d| <= ``velocity_clamp`` (default 0.2) x width_d. Initial
  velocities are uniform in that range.
* **Walls:** a position leaving the box is clipped to it and that velocity component is
  zeroed (absorbing wall), so every evaluated point lies in the box.
* **Stagnation** is |f(p_i) - f(p_i, one iteration earlier)| < delta: the personal best
  stopped improving. The paper's wording, |f(x_i) - f(p_i)| < delta, read literally also
  flags a particle that improves at every iteration (then x_i = p_i). delta is absolute.
* **Warm start:** ``initial`` positions (e.g. the hand-tuned Q/R) replace the first random
  particles, so the result is never worse than them.
* **Budget:** ``max_evaluations`` caps the evaluations (initial swarm, swarm updates and
  chaotic steps all count); the batch that would exceed it is truncated. This gives PSO and
  IPSO equal budgets in comparisons.

Randomness comes only from a ``numpy.random.Generator`` seeded by the caller: the same seed
gives the same result.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from transplanter_ident.tuning.box import Box

BatchObjective = Callable[[np.ndarray], np.ndarray]
ALGORITHMS = ("ipso", "pso")


@dataclass(frozen=True)
class PsoSettings:
    """Standard PSO (eqs. 15-16); defaults are the paper's F, k_max, c1, c2 and w schedule."""

    particles: int = 20  # F
    iterations: int = 40  # k_max
    c1: float = 1.0
    c2: float = 1.5
    inertia_start: float = 0.9
    inertia_end: float = 0.4
    velocity_clamp: float = 0.2  # |v_d| <= velocity_clamp * width_d

    def __post_init__(self) -> None:
        if isinstance(self.particles, bool) or not isinstance(self.particles, int) or self.particles < 1:
            raise ValueError(f"particles must be an integer >= 1, got {self.particles!r}")
        if isinstance(self.iterations, bool) or not isinstance(self.iterations, int) or self.iterations < 1:
            raise ValueError(f"iterations must be an integer >= 1, got {self.iterations!r}")
        for name in ("c1", "c2", "inertia_start", "inertia_end"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be >= 0, got {value!r}")
        if not (math.isfinite(self.velocity_clamp) and self.velocity_clamp > 0.0):
            raise ValueError(f"velocity_clamp must be > 0, got {self.velocity_clamp!r}")


@dataclass(frozen=True)
class IpsoSettings(PsoSettings):
    """IPSO (eqs. 17-20): the paper's c3, lambda, N, N_max, R_d and delta."""

    c3: float = 2.0
    radius_decay: float = 4.0  # lambda of eq. (17)
    stagnation_iterations: int = 5  # N
    chaos_steps: int = 10  # N_max
    chaos_radius: float = 0.1  # R_d as a fraction of the box width (the paper's R_d = 10, read as 10 %)
    stagnation_tolerance: float = 1.0e-6  # delta

    def __post_init__(self) -> None:
        super().__post_init__()
        if not (math.isfinite(self.c3) and self.c3 >= 0.0):
            raise ValueError(f"c3 must be >= 0, got {self.c3!r}")
        if not (math.isfinite(self.radius_decay) and self.radius_decay >= 0.0):
            raise ValueError(f"radius_decay must be >= 0, got {self.radius_decay!r}")
        for name in ("stagnation_iterations", "chaos_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
        if not (math.isfinite(self.chaos_radius) and self.chaos_radius > 0.0):
            raise ValueError(f"chaos_radius must be > 0, got {self.chaos_radius!r}")
        if not (math.isfinite(self.stagnation_tolerance) and self.stagnation_tolerance >= 0.0):
            raise ValueError(f"stagnation_tolerance must be >= 0, got {self.stagnation_tolerance!r}")


@dataclass(frozen=True)
class IterationRecord:
    """The swarm after iteration ``iteration`` (0 = the initial swarm)."""

    iteration: int
    best_fitness: float
    median_fitness: float  # of the swarm's current positions (robust to divergence penalties)
    evaluations: int  # cumulative
    chaotic_particles: int  # particles that ran a chaotic search this iteration


@dataclass(frozen=True)
class OptimizeResult:
    """Best position and fitness, the evaluation count and the per-iteration history."""

    algorithm: str
    position: np.ndarray
    fitness: float
    evaluations: int
    history: tuple[IterationRecord, ...] = field(default_factory=tuple)

    @property
    def iterations(self) -> int:
        """Iterations completed (not counting the initial swarm)."""
        return self.history[-1].iteration if self.history else 0

    @property
    def best_curve(self) -> np.ndarray:
        """The gbest fitness per iteration, initial swarm first (Fig. 4)."""
        return np.array([h.best_fitness for h in self.history])


class _Budget:
    """Counts evaluations and truncates batches at ``limit``."""

    def __init__(self, objective: BatchObjective, limit: int | None) -> None:
        self._objective = objective
        self.limit = limit
        self.used = 0

    @property
    def remaining(self) -> int:
        return self.limit - self.used if self.limit is not None else 2**62

    def evaluate(self, positions: np.ndarray) -> np.ndarray:
        """Fitness of the first ``min(len, remaining)`` rows (the others are not evaluated)."""
        take = min(len(positions), self.remaining)
        if take <= 0:
            return np.empty(0)
        values = np.asarray(self._objective(np.ascontiguousarray(positions[:take])), dtype=np.float64)
        if values.shape != (take,):
            raise ValueError(f"objective returned shape {values.shape}, expected ({take},)")
        self.used += take
        return np.where(np.isnan(values), np.inf, values)


@dataclass
class _Swarm:
    x: np.ndarray
    v: np.ndarray
    f: np.ndarray
    best_x: np.ndarray
    best_f: np.ndarray
    stagnant_for: np.ndarray

    @property
    def leader(self) -> int:
        return int(np.argmin(self.best_f))

    def remember(self, index: np.ndarray) -> None:
        """Update the personal bests of the particles ``index``."""
        better = index[self.f[index] < self.best_f[index]]
        self.best_x[better] = self.x[better]
        self.best_f[better] = self.f[better]


def inertia(settings: PsoSettings, t: float) -> float:
    """Inertia weight w, falling linearly from inertia_start (t = 0) to inertia_end (t = 1)."""
    return settings.inertia_start - (settings.inertia_start - settings.inertia_end) * t


def detection_radius(box: Box, t: float, radius_decay: float, u: np.ndarray) -> np.ndarray:
    """Eq. (17): the adaptive detection point R(k), one per entry of ``u`` (shape (m, D))."""
    centre = 0.5 * (box.high + box.low)
    half = 0.5 * box.width
    return centre + half * math.exp(-radius_decay * t) * np.cos(2.0 * math.pi * u)


def logistic_map(y: np.ndarray) -> np.ndarray:
    """Eq. (19): y <- 4 y (1 - y) (the caller re-seeds values that collapse onto 0 or 1)."""
    return 4.0 * y * (1.0 - y)


def _initial_swarm(box: Box, settings: PsoSettings, rng: np.random.Generator,
                   initial: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    x = box.uniform(rng, settings.particles)
    if initial is not None:
        seeds = box.clip(np.atleast_2d(np.asarray(initial, dtype=np.float64)))
        if seeds.shape[1] != box.dimension:
            raise ValueError(f"initial positions must have {box.dimension} columns, got {seeds.shape[1]}")
        count = min(len(seeds), settings.particles)
        x[:count] = seeds[:count]
    vmax = settings.velocity_clamp * box.width
    v = (2.0 * rng.random(x.shape) - 1.0) * vmax
    return x, v


def _move(swarm: _Swarm, box: Box, settings: PsoSettings, rng: np.random.Generator, t: float) -> None:
    """Eqs. (15)/(18) and the fixed eq. (16), with velocity clamping and absorbing walls."""
    shape = swarm.x.shape
    g = swarm.best_x[swarm.leader]
    r1, r2 = rng.random(shape), rng.random(shape)
    v = (inertia(settings, t) * swarm.v + settings.c1 * r1 * (swarm.best_x - swarm.x)
         + settings.c2 * r2 * (g - swarm.x))
    if isinstance(settings, IpsoSettings):
        r3, u = rng.random(shape), rng.random(shape)
        radius = detection_radius(box, t, settings.radius_decay, u)
        v = v + settings.c3 * r3 * (radius - swarm.x)
    vmax = settings.velocity_clamp * box.width
    v = np.clip(v, -vmax, vmax)
    x = swarm.x + v
    clipped = box.clip(x)
    v[clipped != x] = 0.0
    swarm.x, swarm.v = clipped, v


def _chaotic_search(swarm: _Swarm, stagnant: np.ndarray, box: Box, settings: IpsoSettings,
                    rng: np.random.Generator, budget: _Budget) -> None:
    """Eqs. (19)-(20) for the ``stagnant`` particles, in lock-step batches (one per chaotic step)."""
    active = stagnant.copy()
    y = rng.random((len(active), box.dimension))
    radius = settings.chaos_radius * box.width
    for _ in range(settings.chaos_steps):
        if len(active) == 0 or budget.remaining <= 0:
            break
        y = logistic_map(y)
        stuck = (y <= 1e-12) | (y >= 1.0 - 1e-12)
        y[stuck] = rng.random(int(stuck.sum()))
        candidates = box.clip(swarm.x[active] + radius * (2.0 * y - 1.0))
        values = budget.evaluate(candidates)
        done = len(values)  # < len(active) only when the budget ran out
        tried = active[:done]
        better = values < swarm.f[tried]
        moved = tried[better]
        swarm.x[moved] = candidates[:done][better]
        swarm.f[moved] = values[better]
        swarm.remember(moved)
        active, y = tried[~better], y[:done][~better]  # an improved particle ends its search
    swarm.stagnant_for[stagnant] = 0


def minimize(
    objective: BatchObjective,
    box: Box,
    settings: PsoSettings,
    seed: int | np.random.Generator | None = None,
    *,
    initial: np.ndarray | Sequence[Sequence[float]] | None = None,
    max_evaluations: int | None = None,
    on_iteration: Callable[[IterationRecord], None] | None = None,
) -> OptimizeResult:
    """Minimise ``objective`` over ``box``: IPSO for :class:`IpsoSettings`, standard PSO otherwise.

    Args:
        objective: batch objective, (m, D) positions -> (m,) fitness (NaN counts as +inf).
        box: the search box.
        settings: PsoSettings (standard PSO) or IpsoSettings (IPSO).
        seed: seed or Generator; the same seed gives the same result.
        initial: positions that replace the first random particles (warm start).
        max_evaluations: evaluation budget (None: unlimited, k_max iterations).
        on_iteration: called with each iteration's record (progress output).
    """
    if max_evaluations is not None and max_evaluations < 1:
        raise ValueError(f"max_evaluations must be >= 1, got {max_evaluations!r}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    algorithm = "ipso" if isinstance(settings, IpsoSettings) else "pso"
    budget = _Budget(objective, max_evaluations)
    x, v = _initial_swarm(box, settings, rng, None if initial is None else np.asarray(initial, dtype=float))
    f = budget.evaluate(x)
    if len(f) < len(x):  # budget smaller than the swarm: only the evaluated particles take part
        x, v = x[: len(f)], v[: len(f)]
    swarm = _Swarm(x=x, v=v, f=f, best_x=x.copy(), best_f=f.copy(), stagnant_for=np.zeros(len(x), dtype=int))
    history = [_record(0, swarm, budget, 0)]
    _report(on_iteration, history[-1])
    for k in range(1, settings.iterations + 1):
        if budget.remaining <= 0:
            break
        t = k / settings.iterations
        previous_x, previous_v, previous_best = swarm.x.copy(), swarm.v.copy(), swarm.best_f.copy()
        _move(swarm, box, settings, rng, t)
        values = budget.evaluate(swarm.x)
        done = len(values)
        swarm.x[done:], swarm.v[done:] = previous_x[done:], previous_v[done:]  # not evaluated: stay
        swarm.f[:done] = values
        evaluated = np.arange(done)
        swarm.remember(evaluated)
        chaotic = 0
        if isinstance(settings, IpsoSettings) and settings.chaos_steps > 0:
            with np.errstate(invalid="ignore"):  # inf - inf (two failed evaluations) is not stagnation
                unchanged = np.abs(previous_best[:done] - swarm.best_f[:done]) < settings.stagnation_tolerance
            swarm.stagnant_for[:done] = np.where(unchanged, swarm.stagnant_for[:done] + 1, 0)
            stagnant = np.flatnonzero(swarm.stagnant_for >= max(settings.stagnation_iterations, 1))
            chaotic = len(stagnant)
            if chaotic:
                _chaotic_search(swarm, stagnant, box, settings, rng, budget)
        history.append(_record(k, swarm, budget, chaotic))
        _report(on_iteration, history[-1])
    leader = swarm.leader
    return OptimizeResult(algorithm=algorithm, position=swarm.best_x[leader].copy(),
                          fitness=float(swarm.best_f[leader]), evaluations=budget.used, history=tuple(history))


def _record(k: int, swarm: _Swarm, budget: _Budget, chaotic: int) -> IterationRecord:
    return IterationRecord(iteration=k, best_fitness=float(swarm.best_f.min()),
                           median_fitness=float(np.median(swarm.f)),
                           evaluations=budget.used, chaotic_particles=chaotic)


def _report(callback: Callable[[IterationRecord], None] | None, record: IterationRecord) -> None:
    if callback is not None:
        callback(record)


def settings_for(algorithm: str, **overrides: int | float) -> PsoSettings:
    """Paper defaults for ``ipso`` or ``pso``, with ``overrides`` (e.g. particles, iterations)."""
    if algorithm not in ALGORITHMS:
        raise ValueError(f"algorithm must be one of {', '.join(ALGORITHMS)}, got {algorithm!r}")
    cls = IpsoSettings if algorithm == "ipso" else PsoSettings
    return cls(**overrides)


def pso_for_budget(evaluations: int, base: PsoSettings | None = None) -> PsoSettings:
    """Standard PSO settings whose k_max spends ``evaluations`` (pair with ``max_evaluations``).

    The last iteration may be partial; the inertia schedule still ends at inertia_end.
    """
    base = base or PsoSettings()
    iterations = max(1, math.ceil((evaluations - base.particles) / base.particles))
    fields = {f: getattr(base, f) for f in PsoSettings.__dataclass_fields__}
    fields["iterations"] = iterations
    return PsoSettings(**fields)


# ----------------------------------------------------------------- test functions (benchmarks)


