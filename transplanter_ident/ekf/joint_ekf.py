"""The joint-state EKF as Python types: the node's epoch-by-epoch view and the offline runs.

:class:`JointEKF` (the node) and :func:`run_sequence` / :func:`sequence_objective` (replay,
tuner) call the same compiled step of :mod:`.kernels` (paper eqs. 9-14, 21), so online and
offline numbers are identical. :class:`FilterArrays` translates an
:class:`~transplanter_ident.config.parameters.EstimatorConfig` into the kernels' arrays and
:class:`Estimate` reads one output row back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig, NoiseParams
from transplanter_ident.ekf.entries import ekf_step, objective_kernel, run_kernel
from transplanter_ident.ekf.layout import (
    EULER,
    EXACT,
    MAE,
    N_MEMO,
    N_MODEL,
    N_OUTPUTS,
    N_SETTINGS,
    NLL,
    O_CF,
    O_CF_STD,
    O_CR,
    O_CR_STD,
    O_E0,
    O_E1,
    O_NIS,
    O_R,
    O_R_MODEL,
    O_S00,
    O_S01,
    O_S11,
    O_STATUS,
    O_VY,
    O_VY_MODEL,
    S_GATE,
    S_HEADING,
    S_HIGH,
    S_LOG,
    S_LOW,
    S_MAX_GATED,
    S_MAX_INTERVAL,
    S_METHOD,
    S_MIN_SPEED,
    S_P0_PSI,
    S_P0_R,
    S_P0_VY,
    StepStatus,
)
from transplanter_ident.ekf.model import vehicle_array, work_buffer
from transplanter_ident.epochs.epoch import Epoch, EpochArrays


@dataclass(frozen=True)
class Estimate:
    """What one epoch produced (Cf, Cr in N/rad per tire)."""

    t: float
    status: StepStatus
    lateral_velocity: float
    yaw_rate: float
    cornering_stiffness_front: float
    cornering_stiffness_rear: float
    cornering_stiffness_front_std: float
    cornering_stiffness_rear_std: float
    lateral_velocity_model: float
    yaw_rate_model: float
    innovation: tuple[float, float]
    innovation_covariance: tuple[float, float, float]  # S00, S01, S11
    normalized_innovation_squared: float

    @classmethod
    def from_row(cls, t: float, row: np.ndarray) -> Estimate:
        """Build from one kernel output row."""
        return cls(
            t=t,
            status=StepStatus(int(row[O_STATUS])),
            lateral_velocity=float(row[O_VY]),
            yaw_rate=float(row[O_R]),
            cornering_stiffness_front=float(row[O_CF]),
            cornering_stiffness_rear=float(row[O_CR]),
            cornering_stiffness_front_std=float(row[O_CF_STD]),
            cornering_stiffness_rear_std=float(row[O_CR_STD]),
            lateral_velocity_model=float(row[O_VY_MODEL]),
            yaw_rate_model=float(row[O_R_MODEL]),
            innovation=(float(row[O_E0]), float(row[O_E1])),
            innovation_covariance=(float(row[O_S00]), float(row[O_S01]), float(row[O_S11])),
            normalized_innovation_squared=float(row[O_NIS]),
        )


@dataclass(frozen=True)
class FilterArrays:
    """The numeric form of an EstimatorConfig for the compiled kernels."""

    vehicle: np.ndarray
    settings: np.ndarray
    process_noise: np.ndarray
    measurement_noise: np.ndarray
    initial_state: np.ndarray
    initial_covariance: np.ndarray

    @classmethod
    def from_config(cls, config: EstimatorConfig) -> FilterArrays:
        """Translate the parameters to the state's units and the kernels' layout."""
        options, noise = config.options, config.noise
        log_state = options.stiffness_state == "log"
        heading = options.measurement == "heading"
        to_state = math.log if log_state else float
        settings = np.zeros(N_SETTINGS)
        settings[S_METHOD] = EXACT if options.discretization == "exact" else EULER
        settings[S_LOG] = 1.0 if log_state else 0.0
        settings[S_HEADING] = 1.0 if heading else 0.0
        settings[S_MIN_SPEED] = options.min_speed
        settings[S_LOW] = to_state(options.stiffness_bounds[0])
        settings[S_HIGH] = to_state(options.stiffness_bounds[1])
        settings[S_GATE] = options.gate_threshold
        settings[S_MAX_GATED] = options.max_gated
        settings[S_MAX_INTERVAL] = options.max_interval
        settings[S_P0_VY] = noise.initial_covariance[0]
        settings[S_P0_R] = noise.initial_covariance[1]
        settings[S_P0_PSI] = noise.initial_heading_covariance
        q, p0 = _state_diagonals(noise, heading)
        x0 = np.zeros(len(q))
        x0[-2] = to_state(noise.initial_stiffness[0])
        x0[-1] = to_state(noise.initial_stiffness[1])
        return cls(
            vehicle=vehicle_array(config.vehicle),
            settings=settings,
            process_noise=q,
            measurement_noise=np.array(noise.measurement_noise, dtype=np.float64),
            initial_state=x0,
            initial_covariance=np.diag(p0),
        )


def _state_diagonals(noise: NoiseParams, heading: bool) -> tuple[np.ndarray, np.ndarray]:
    q, p0 = list(noise.process_noise), list(noise.initial_covariance)
    if heading:
        q.insert(2, noise.heading_process_noise)
        p0.insert(2, noise.initial_heading_covariance)
    return np.array(q, dtype=np.float64), np.array(p0, dtype=np.float64)


class JointEKF:
    """The joint-state EKF, stepped one epoch at a time (the node's view)."""

    def __init__(self, config: EstimatorConfig) -> None:
        self._config = config
        self._arrays = FilterArrays.from_config(config)
        self._ws = work_buffer()
        self._out = np.zeros(N_OUTPUTS)
        self.reset()

    @property
    def config(self) -> EstimatorConfig:
        """The parameters in force."""
        return self._config

    def reset(self) -> None:
        """Restart from the initial state (paper: x(0), P(0))."""
        self.state = self._arrays.initial_state.copy()
        self.covariance = self._arrays.initial_covariance.copy()
        self._model = np.zeros(N_MODEL)
        self._memo = np.zeros(N_MEMO)

    def set_noise(self, noise: NoiseParams) -> None:
        """Swap Q and R at run time; the state and covariance carry on."""
        config = EstimatorConfig(vehicle=self._config.vehicle, options=self._config.options, noise=noise)
        arrays = FilterArrays.from_config(config)
        self._config, self._arrays = config, arrays

    def step(self, epoch: Epoch) -> Estimate:
        """Filter one epoch (eq. 12) and return the estimate."""
        a = self._arrays
        ekf_step(self.state, self.covariance, self._model, self._memo, a.vehicle, a.settings,
                 a.process_noise, a.measurement_noise, epoch.t, epoch.speed, epoch.steering,
                 epoch.steering_rate, epoch.lateral_velocity, epoch.heading, epoch.yaw_rate, self._ws, self._out)
        return Estimate.from_row(epoch.t, self._out)


def run_sequence(config: EstimatorConfig, epochs: EpochArrays) -> np.ndarray:
    """Filter a whole epoch sequence; returns the (N, N_OUTPUTS) output rows."""
    a = FilterArrays.from_config(config)
    outputs = np.zeros((len(epochs), N_OUTPUTS))
    run_kernel(epochs.kernel_input(), a.initial_state.copy(), a.initial_covariance.copy(), np.zeros(N_MODEL),
               np.zeros(N_MEMO), a.vehicle, a.settings, a.process_noise, a.measurement_noise, outputs)
    return outputs


def sequence_objective(config: EstimatorConfig, epochs: EpochArrays, kind: str = "mae") -> float:
    """Tuning objective (``mae``: eq. 21, ``nll``: innovation negative log-likelihood)."""
    a = FilterArrays.from_config(config)
    code = MAE if kind == "mae" else NLL
    return float(objective_kernel(epochs.kernel_input(), a.initial_state.copy(), a.initial_covariance.copy(),
                                  np.zeros(N_MODEL), np.zeros(N_MEMO), a.vehicle, a.settings, a.process_noise,
                                  a.measurement_noise, code))
