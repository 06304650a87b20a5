"""The tuning problem: the EKF's Q and R (eq. 22) as a 6-D search box, and the batched objective.

A candidate is the 6-vector of log10 diagonal entries::

    [log10 q_vy, log10 q_r, log10 q_Cf, log10 q_Cr, log10 r_vy, log10 r_2]

(Q of eq. 22 in the units of the filter state, R of eq. 22 with r_2 the heading variance in
``heading`` mode or the yaw-rate variance in ``yaw_rate`` mode). In ``heading`` mode the
filter state has a fifth entry, psi, whose Q entry (``ekf.heading_process_noise``) is not
searched: it is kept from the configuration and inserted at index 2, as
``ekf.FilterArrays.from_config`` does.

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
q_Cf, q_Cr log    (ln N/rad)^2 per step   1e-10 .. 1e-2
q_Cf, q_Cr linear (N/rad)^2 per step      1e-2 .. 1e6
r_vy              (m/s)^2                 1e-6 .. 1e-1
r_2 heading       rad^2                   1e-8 .. 1e-2
r_2 yaw_rate      (rad/s)^2               1e-6 .. 1e-1
================  ======================  ==================
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numba
import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, NoiseParams
from transplanter_ident.ekf.entries import (
    kernels_for,
    objective_heading,
    objective_kernel,
    objective_yaw_rate,
)
from transplanter_ident.ekf.joint_ekf import FilterArrays, kernel_input
from transplanter_ident.ekf.layout import (
    HEADING_STATES,
    MAE,
    N_MEMO,
    N_MODEL,
    NLL,
    X_R,
    X_THETA_F,
    X_THETA_R,
    X_VY,
    YAW_RATE_STATES,
)
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.jit import parallel_entry_kernel
from transplanter_ident.tuning.box import Box

OBJECTIVES = {"mae": MAE, "nll": NLL}
NAMES = ("q_vy", "q_r", "q_cf", "q_cr", "r_vy", "r_2")
MOTION_Q_BOUNDS = (-8.0, -1.0)
STIFFNESS_Q_BOUNDS = {"log": (-10.0, -2.0), "linear": (-2.0, 6.0)}
LATERAL_VELOCITY_R_BOUNDS = (-6.0, -1.0)
SECOND_R_BOUNDS = {"heading": (-8.0, -2.0), "yaw_rate": (-6.0, -1.0)}


def search_box(options: FilterOptions) -> Box:
    """The log10 box of the six searched entries for this stiffness parameterisation and measurement."""
    rows = (
        MOTION_Q_BOUNDS,
        MOTION_Q_BOUNDS,
        STIFFNESS_Q_BOUNDS[options.stiffness_state],
        STIFFNESS_Q_BOUNDS[options.stiffness_state],
        LATERAL_VELOCITY_R_BOUNDS,
        SECOND_R_BOUNDS[options.measurement],
    )
    return Box(tuple(r[0] for r in rows), tuple(r[1] for r in rows), NAMES)


def noise_to_vector(noise: NoiseParams) -> np.ndarray:
    """The log10 6-vector of a NoiseParams (zero entries map to -inf; clip with the box)."""
    values = np.array([*noise.process_noise, *noise.measurement_noise], dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.log10(values)


def vector_to_noise(vector: np.ndarray, base: NoiseParams) -> NoiseParams:
    """NoiseParams with Q and R from the log10 6-vector; everything else (heading Q, P0) from ``base``."""
    values = [float(v) for v in 10.0 ** np.asarray(vector, dtype=np.float64)]
    return replace(base, process_noise=tuple(values[:4]), measurement_noise=tuple(values[4:6]))


def candidate_matrices(positions: np.ndarray, config: EstimatorConfig) -> tuple[np.ndarray, np.ndarray]:
    """Diag Q (m, n) in the filter's state layout (densities) and diag R (m, 2) for log10 positions (m, 6).

    The unsearched entries (heading and offset Q) keep the configured values.
    """
    positions = np.atleast_2d(np.asarray(positions, dtype=np.float64))
    if positions.shape[1] != len(NAMES):
        raise ValueError(f"candidates must have {len(NAMES)} columns, got {positions.shape[1]}")
    values = 10.0**positions
    q = np.tile(FilterArrays.from_config(config).process_noise, (len(values), 1))
    scale = config.options.noise_rate_scale
    motion = [X_VY, X_R]
    q[:, motion] = values[:, :2] * scale
    q[:, [X_THETA_F, X_THETA_R]] = values[:, 2:4] * scale
    return np.ascontiguousarray(q), np.ascontiguousarray(values[:, 4:6])


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


_BATCH = {YAW_RATE_STATES: _batch_yaw_rate, HEADING_STATES: _batch_heading}


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
    """The objective of eq. (21) (or the NLL) over one epoch sequence, as a batch function of log10 Q/R."""

    config: EstimatorConfig
    kernel_input: np.ndarray
    objective: str = "mae"

    def __post_init__(self) -> None:
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {', '.join(OBJECTIVES)}, got {self.objective!r}")

    @classmethod
    def from_epochs(cls, config: EstimatorConfig, epochs: EpochArrays, objective: str = "mae") -> TuningProblem:
        """Build from an epoch sequence (bag_io.read_epochs or the simulator)."""
        return cls(config, kernel_input(epochs), objective)

    @property
    def box(self) -> Box:
        """The search box for this configuration."""
        return search_box(self.config.options)

    @property
    def start(self) -> np.ndarray:
        """The configuration's own Q/R as a log10 vector, clipped to the box."""
        return self.box.clip(noise_to_vector(self.config.noise))

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        """Objective of each row of ``positions`` (m, 6)."""
        arrays = FilterArrays.from_config(self.config)
        qs, rs = candidate_matrices(positions, self.config)
        return batch_objective(self.kernel_input, arrays.initial_state, arrays.initial_covariance, arrays.vehicle,
                               arrays.settings, qs, rs, OBJECTIVES[self.objective])

    def evaluate_noise(self, noise: NoiseParams) -> float:
        """Objective of one NoiseParams (any values, not clipped to the box), single-threaded."""
        arrays = FilterArrays.from_config(replace(self.config, noise=noise))
        return float(objective_kernel(self.kernel_input, arrays.initial_state.copy(),
                                      arrays.initial_covariance.copy(), np.zeros(N_MODEL), np.zeros(N_MEMO), arrays.vehicle,
                                      arrays.settings, arrays.process_noise, arrays.measurement_noise,
                                      OBJECTIVES[self.objective]))

    def tuned_config(self, position: np.ndarray) -> EstimatorConfig:
        """The configuration with Q/R from a log10 position."""
        return replace(self.config, noise=vector_to_noise(position, self.config.noise))

