"""The tuning problem: the EKF's Q and R (eq. 22) as a log10 search box, and the batched objective.

A candidate is the vector of log10 diagonal entries named by :func:`searched_names`. By
default only the *physical* noises are searched (issue #13, "split Q")::

    [log10 q_vy, log10 q_r, (log10 q_psi,) log10 r_vy, log10 r_2]

the vy, r (and, in ``heading`` mode, psi) process noises and R of eq. 22, with r_2 the heading
variance in ``heading`` mode or the yaw-rate variance in ``yaw_rate`` mode. The stiffness and
steering-offset random walks and the change mechanism are set by design (config/schema.py):
fitted by the NLL on bags whose stiffness is constant, the stiffness random walk goes to zero
and the filter becomes overconfident. ``tune_stiffness_noise`` adds q_Cf and q_Cr (in the
units of the filter state) after the process noises, as the tuner did before the split::

    [log10 q_vy, log10 q_r, (log10 q_psi,) log10 q_Cf, log10 q_Cr, log10 r_vy, log10 r_2]

The process noises are searched within ``q_span`` decades (default :data:`Q_SPAN`, 1) either side
of the configured value, inside the bounds below; R within the bounds alone. The NLL identifies R
well (tuned on each of the project's scenarios alone, r_vy and r_2 land within 0.25 decade of
the simulator's noise, most within 0.1), but it is nearly flat in Q where the linear model holds
and steep where it does not: on a step steer that saturates the tire, motion noise 100x the design absorbs the
model's error (NLL -0.27 per epoch, against -0.01 on the sine drive). Pooled over bags, those
drives set Q, and the stiffness then learns from a model told to trust itself less: in the
leave-one-bag-out check (seed 11, GNSS noise 2x) a held-out stiffness-drop drive ended +12 %
(design Q: -1.6 %) with q_psi tuned 1000x the design. The span keeps the design's balance
between the model and the stiffness; ``q_span`` inf searches the whole box. Every entry not
searched keeps the configured value (:func:`candidate_matrices`). Candidates run
without ``ekf.noise_adaptation`` (:func:`search_arrays`): the search measures R itself, and a filter
that raised a too-small R to what its innovations show would make every R below the truth score alike.

The objective of one candidate is ``ekf.objective_kernel`` over the whole epoch sequence:
eq. (21), the mean absolute one-step innovation (``mae``), or the Gaussian innovation
negative log-likelihood (``nll``); a diverging filter scores ``ekf.DIVERGENCE_PENALTY``.
:func:`batch_objective` runs it for many candidates at once, compiled, one candidate per
thread (``numba.prange``), each with its own copies of the state.

Search bounds (log10), chosen to hold every physically sensible value with margin:

================  ======================  ==================
entry             units                   bounds
================  ======================  ==================
q_vy              (m/s)^2 per step        1e-8 .. 1e-1
q_r               (rad/s)^2 per step      1e-8 .. 1e-1
q_psi             rad^2 per step          1e-12 .. 1e-3
q_Cf, q_Cr log    (ln N/rad)^2 per step   1e-10 .. 1e-2
q_Cf, q_Cr linear (N/rad)^2 per step      1e-2 .. 1e6
r_vy              (m/s)^2                 1e-6 .. 1e-1
r_2 heading       rad^2                   1e-8 .. 1e-2
r_2 yaw_rate      (rad/s)^2               1e-6 .. 1e-1
================  ======================  ==================

("per step" reads "per second" with ``ekf.process_noise_units: per_second``, the default.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numba
import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, NoiseParams
from transplanter_ident.ekf.entries import (
    kernels_for,
    objective_heading,
    objective_heading_lagged,
    objective_kernel,
    objective_yaw_rate,
    objective_yaw_rate_lagged,
)
from transplanter_ident.ekf.joint_ekf import FilterArrays, kernel_input
from transplanter_ident.ekf.layout import (
    HEADING_LAG_STATES,
    HEADING_STATES,
    MAE,
    N_MEMO,
    N_MODEL,
    NLL,
    X_PSI,
    X_R,
    X_THETA_F,
    X_THETA_R,
    X_VY,
    YAW_RATE_LAG_STATES,
    YAW_RATE_STATES,
)
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.jit import parallel_entry_kernel
from transplanter_ident.tuning.box import Box

OBJECTIVES = {"mae": MAE, "nll": NLL}
#: the six entries the tuner searched before Q was split (stiffness noise included, no heading Q)
NAMES = ("q_vy", "q_r", "q_cf", "q_cr", "r_vy", "r_2")
#: the stiffness random walks, searched only with ``tune_stiffness_noise``
STIFFNESS_NAMES = ("q_cf", "q_cr")
MOTION_Q_BOUNDS = (-8.0, -1.0)
HEADING_Q_BOUNDS = (-12.0, -3.0)
STIFFNESS_Q_BOUNDS = {"log": (-10.0, -2.0), "linear": (-2.0, 6.0)}
LATERAL_VELOCITY_R_BOUNDS = (-6.0, -1.0)
SECOND_R_BOUNDS = {"heading": (-8.0, -2.0), "yaw_rate": (-6.0, -1.0), "course": (-8.0, -2.0)}  # course: unused
#: decades either side of the configured value within which a process noise is searched
Q_SPAN = 1.0
#: entry -> the filter state whose diagonal Q it is (the R entries: None)
_STATE_OF = {"q_vy": X_VY, "q_r": X_R, "q_psi": X_PSI, "q_cf": X_THETA_F, "q_cr": X_THETA_R,
             "r_vy": None, "r_2": None}


def searched_names(options: FilterOptions, tune_stiffness_noise: bool = False) -> tuple[str, ...]:
    """The entries searched: the physical noises (q_vy, q_r, q_psi in heading mode, R), plus q_Cf, q_Cr if asked."""
    heading = ("q_psi",) if options.heading_state else ()
    stiffness = STIFFNESS_NAMES if tune_stiffness_noise else ()
    second = () if options.course else ("r_2",)  # a course's R follows from the velocity's (r_vy)
    return ("q_vy", "q_r", *heading, *stiffness, "r_vy", *second)


def _bounds(name: str, options: FilterOptions) -> tuple[float, float]:
    if name in ("q_vy", "q_r"):
        return MOTION_Q_BOUNDS
    if name == "q_psi":
        return HEADING_Q_BOUNDS
    if name in STIFFNESS_NAMES:
        return STIFFNESS_Q_BOUNDS[options.stiffness_state]
    if name == "r_vy":
        return LATERAL_VELOCITY_R_BOUNDS
    return SECOND_R_BOUNDS[options.measurement]


def search_box(options: FilterOptions, names: tuple[str, ...] = NAMES) -> Box:
    """The log10 box of the searched entries ``names`` for this stiffness parameterisation and measurement."""
    rows = [_bounds(name, options) for name in names]
    return Box(tuple(r[0] for r in rows), tuple(r[1] for r in rows), tuple(names))


def check_q_span(q_span: float) -> float:
    """``q_span`` if it is a positive number of decades (inf included), else ValueError."""
    if not q_span > 0.0:
        raise ValueError(f"q_span must be a positive number of decades or inf, got {q_span!r}")
    return q_span


def span_words(q_span: float) -> str:
    """How far from the start Q was searched, in words."""
    if not math.isfinite(q_span):
        return "over the whole box"
    return f"within {q_span:g} decade{'' if q_span == 1.0 else 's'} of the start"


def design_box(config: EstimatorConfig, names: tuple[str, ...], q_span: float = Q_SPAN) -> Box:
    """:func:`search_box` with each process noise narrowed to ``q_span`` decades around the configured value.

    A configured value outside the bounds (or zero) centres its span on the nearest bound.
    """
    check_q_span(q_span)
    box = search_box(config.options, names)
    centre = box.clip(noise_to_vector(config.noise, names))
    low, high = list(box.lower), list(box.upper)
    for i, name in enumerate(names):
        if name.startswith("q_") and math.isfinite(q_span):
            low[i], high[i] = max(low[i], centre[i] - q_span), min(high[i], centre[i] + q_span)
    return Box(tuple(low), tuple(high), tuple(names))


#: a position this share of its span's width from a narrowed edge counts as at that edge
EDGE_SHARE = 0.01


def span_edges(config: EstimatorConfig, names: tuple[str, ...], q_span: float,
               position: np.ndarray) -> tuple[tuple[str, str], ...]:
    """(name, "lower" | "upper") of each entry of ``position`` at an edge the span set (not a physical bound).

    A tuned Q there is where the data wanted more (or less) than the span allows.
    """
    full, box = search_box(config.options, names), design_box(config, names, q_span)
    margin = EDGE_SHARE * box.width
    edges = []
    for i, name in enumerate(names):
        if box.lower[i] > full.lower[i] and position[i] <= box.lower[i] + margin[i]:
            edges.append((name, "lower"))
        elif box.upper[i] < full.upper[i] and position[i] >= box.upper[i] - margin[i]:
            edges.append((name, "upper"))
    return tuple(edges)


def _noise_value(noise: NoiseParams, name: str) -> float:
    values = {"q_vy": noise.process_noise[0], "q_r": noise.process_noise[1], "q_psi": noise.heading_process_noise,
              "q_cf": noise.process_noise[2], "q_cr": noise.process_noise[3], "r_vy": noise.measurement_noise[0],
              "r_2": noise.measurement_noise[1]}
    return float(values[name])


def noise_to_vector(noise: NoiseParams, names: tuple[str, ...] = NAMES) -> np.ndarray:
    """The log10 vector of the entries ``names`` of a NoiseParams (zero entries map to -inf; clip with the box)."""
    values = np.array([_noise_value(noise, name) for name in names], dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.log10(values)


def vector_to_noise(vector: np.ndarray, base: NoiseParams, names: tuple[str, ...] = NAMES) -> NoiseParams:
    """NoiseParams with the entries ``names`` from the log10 vector; everything else (P0, ...) from ``base``."""
    values = dict(zip(names, (float(v) for v in 10.0 ** np.asarray(vector, dtype=np.float64)), strict=True))
    q, r = list(base.process_noise), list(base.measurement_noise)
    for index, name in enumerate(("q_vy", "q_r", "q_cf", "q_cr")):
        q[index] = values.get(name, q[index])
    for index, name in enumerate(("r_vy", "r_2")):
        r[index] = values.get(name, r[index])
    return replace(base, process_noise=tuple(q), measurement_noise=tuple(r),
                   heading_process_noise=values.get("q_psi", base.heading_process_noise))


def search_config(config: EstimatorConfig) -> EstimatorConfig:
    """The filter a candidate is scored with: ``config`` without ``ekf.noise_adaptation``."""
    return replace(config, options=replace(config.options, noise_adaptation=False))


def search_arrays(config: EstimatorConfig) -> FilterArrays:
    """The kernels' arrays of :func:`search_config`."""
    return FilterArrays.from_config(search_config(config))


def candidate_matrices(positions: np.ndarray, config: EstimatorConfig,
                       names: tuple[str, ...] = NAMES) -> tuple[np.ndarray, np.ndarray]:
    """Diag Q (m, n) in the filter's state layout (densities) and diag R (m, 2) for log10 positions (m, len(names)).

    The entries not searched (the offset Q, and any of Q/R not in ``names``) keep the configured values.
    """
    positions = np.atleast_2d(np.asarray(positions, dtype=np.float64))
    if positions.shape[1] != len(names):
        raise ValueError(f"candidates must have {len(names)} columns, got {positions.shape[1]}")
    if "q_psi" in names and not config.options.heading_state:
        raise ValueError("q_psi is an entry of the heading measurement only")
    values = 10.0**positions
    arrays = FilterArrays.from_config(config)
    q = np.tile(arrays.process_noise, (len(values), 1))
    r = np.tile(arrays.measurement_noise, (len(values), 1))
    scale = config.options.noise_rate_scale
    for column, name in enumerate(names):
        state = _STATE_OF[name]
        if state is not None:
            q[:, state] = values[:, column] * scale
        else:
            r[:, 0 if name == "r_vy" else 1] = values[:, column]
    return np.ascontiguousarray(q), np.ascontiguousarray(r)


# One entry per state size: numba caches only module-level functions (see ekf/entries.py).
@parallel_entry_kernel
def _batch_yaw_rate(epochs, x0, p0, vehicle, settings, qs, rs, kind):  # noqa: ANN001, ANN202
    values = np.empty(qs.shape[0])
    for i in numba.prange(qs.shape[0]):
        values[i] = objective_yaw_rate(epochs.copy(), x0.copy(), p0.copy(), np.zeros(N_MODEL), np.zeros(N_MEMO),
                                vehicle.copy(), settings.copy(), qs[i].copy(), rs[i].copy(), kind)
    return values


@parallel_entry_kernel
def _batch_heading(epochs, x0, p0, vehicle, settings, qs, rs, kind):  # noqa: ANN001, ANN202
    values = np.empty(qs.shape[0])
    for i in numba.prange(qs.shape[0]):
        values[i] = objective_heading(epochs.copy(), x0.copy(), p0.copy(), np.zeros(N_MODEL), np.zeros(N_MEMO),
                                vehicle.copy(), settings.copy(), qs[i].copy(), rs[i].copy(), kind)
    return values


@parallel_entry_kernel
def _batch_yaw_rate_lagged(epochs, x0, p0, vehicle, settings, qs, rs, kind):  # noqa: ANN001, ANN202
    values = np.empty(qs.shape[0])
    for i in numba.prange(qs.shape[0]):
        values[i] = objective_yaw_rate_lagged(epochs.copy(), x0.copy(), p0.copy(), np.zeros(N_MODEL),
                                              np.zeros(N_MEMO), vehicle.copy(), settings.copy(), qs[i].copy(),
                                              rs[i].copy(), kind)
    return values


@parallel_entry_kernel
def _batch_heading_lagged(epochs, x0, p0, vehicle, settings, qs, rs, kind):  # noqa: ANN001, ANN202
    values = np.empty(qs.shape[0])
    for i in numba.prange(qs.shape[0]):
        values[i] = objective_heading_lagged(epochs.copy(), x0.copy(), p0.copy(), np.zeros(N_MODEL), np.zeros(N_MEMO),
                                             vehicle.copy(), settings.copy(), qs[i].copy(), rs[i].copy(), kind)
    return values


_BATCH = {YAW_RATE_STATES: _batch_yaw_rate, HEADING_STATES: _batch_heading,
          YAW_RATE_LAG_STATES: _batch_yaw_rate_lagged, HEADING_LAG_STATES: _batch_heading_lagged}


def batch_objective(epochs, x0, p0, vehicle, settings, qs, rs, kind):  # noqa: ANN001, ANN201
    """objective_kernel for every candidate (row of qs, rs), one candidate per thread.

    Every candidate gets private copies of *all* its arrays, the read-only ones included: the
    kernel's array views touch the owning array's reference count (an atomic add) every step,
    and two threads sharing one array contend for that cache line so hard that a second
    thread gained nothing (measured: 2 threads, shared inputs 1.0x, private copies 2.0x).
    """
    kernels_for(x0, p0, vehicle=vehicle, settings=settings, epochs=epochs)  # shape checks
    n = x0.shape[0]
    if qs.ndim != 2 or qs.shape[1] != n or rs.shape != (qs.shape[0], 2):
        raise ValueError(f"qs {qs.shape} and rs {rs.shape}: expected (m, {n}) and (m, 2)")
    return _BATCH[n](epochs, x0, p0, vehicle, settings, qs, rs, kind)


@dataclass(frozen=True)
class TuningProblem:
    """The objective of eq. (21) (or the NLL) over one epoch sequence, as a batch function of log10 Q/R.

    ``tune_stiffness_noise`` False (the default) searches the physical noises only, True adds the
    stiffness random walks (:func:`searched_names`). ``q_span``: decades either side of the
    configured Q searched (:func:`design_box`; inf: the whole box).
    """

    config: EstimatorConfig
    kernel_input: np.ndarray
    objective: str = "mae"
    tune_stiffness_noise: bool = False
    q_span: float = Q_SPAN

    def __post_init__(self) -> None:
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {', '.join(OBJECTIVES)}, got {self.objective!r}")
        check_q_span(self.q_span)

    @classmethod
    def from_epochs(cls, config: EstimatorConfig, epochs: EpochArrays, objective: str = "mae",
                    tune_stiffness_noise: bool = False, q_span: float = Q_SPAN) -> TuningProblem:
        """Build from an epoch sequence (bag_io.read_epochs or the simulator)."""
        return cls(config, kernel_input(epochs), objective, tune_stiffness_noise, q_span)

    @property
    def names(self) -> tuple[str, ...]:
        """The searched entries, in the order of a position's columns."""
        return searched_names(self.config.options, self.tune_stiffness_noise)

    @property
    def box(self) -> Box:
        """The search box for this configuration: the process noises within ``q_span`` decades of the start."""
        return design_box(self.config, self.names, self.q_span)

    @property
    def start(self) -> np.ndarray:
        """The configuration's own Q/R as a log10 vector, clipped to the box."""
        return self.box.clip(noise_to_vector(self.config.noise, self.names))

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        """Objective of each row of ``positions`` (m, len(names))."""
        arrays = search_arrays(self.config)
        qs, rs = candidate_matrices(positions, self.config, self.names)
        return batch_objective(self.kernel_input, arrays.initial_state, arrays.initial_covariance, arrays.vehicle,
                               arrays.settings, qs, rs, OBJECTIVES[self.objective])

    def evaluate_serially(self, positions: np.ndarray) -> np.ndarray:
        """The values of ``__call__``, one candidate after another in this thread.

        Through the sequence objective's own entry, so no parallel kernel is loaded or compiled:
        what a pool worker or a Dask task runs (each is one slot), and what a cold start compiles.
        """
        arrays = search_arrays(self.config)
        qs, rs = candidate_matrices(positions, self.config, self.names)
        kind = OBJECTIVES[self.objective]
        return np.array([objective_kernel(self.kernel_input, arrays.initial_state.copy(),
                                          arrays.initial_covariance.copy(), np.zeros(N_MODEL), np.zeros(N_MEMO),
                                          arrays.vehicle, arrays.settings, q, r, kind)
                         for q, r in zip(qs, rs, strict=True)], dtype=np.float64).reshape(len(qs))

    def evaluate_noise(self, noise: NoiseParams) -> float:
        """Objective of one NoiseParams (any values, not clipped to the box), single-threaded."""
        arrays = search_arrays(replace(self.config, noise=noise))
        return float(objective_kernel(self.kernel_input, arrays.initial_state.copy(),
                                      arrays.initial_covariance.copy(), np.zeros(N_MODEL), np.zeros(N_MEMO), arrays.vehicle,
                                      arrays.settings, arrays.process_noise, arrays.measurement_noise,
                                      OBJECTIVES[self.objective]))

    def tuned_config(self, position: np.ndarray) -> EstimatorConfig:
        """The configuration with Q/R from a log10 position."""
        return replace(self.config, noise=vector_to_noise(position, self.config.noise, self.names))
