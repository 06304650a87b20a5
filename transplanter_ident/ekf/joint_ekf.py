"""The joint-state EKF as Python types: the node's epoch-by-epoch view and the offline runs.

:class:`JointEKF` (the node) and :func:`run_sequence` / :func:`sequence_objective` (replay,
tuner) call the same compiled step of :mod:`.kernels` (paper eqs. 9-14, 21), so online and
offline numbers are identical; both take the same re-linearised passes over the start
(:mod:`.relinearization`). :class:`FilterArrays` translates an
:class:`~transplanter_ident.config.parameters.EstimatorConfig` into the kernels' arrays and
:class:`~transplanter_ident.ekf.estimate.Estimate` reads one output row back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, NoiseParams
from transplanter_ident.ekf.entries import ekf_step, objective_kernel, run_kernel
from transplanter_ident.ekf.estimate import Estimate
from transplanter_ident.ekf.identifiability import IdentifiabilityGuard
from transplanter_ident.ekf.layout import (
    EPOCH_COLUMNS,
    EULER,
    EXACT,
    M_NOISE_SPAN_SECOND,
    M_NOISE_VY,
    MAE,
    N_LAG,
    N_MEMO,
    N_MODEL,
    N_MOTION_HEADING,
    N_MOTION_YAW_RATE,
    N_OUTPUTS,
    N_SETTINGS,
    NLL,
    PARAMETER_STATES,
    S_ANTENNA_X,
    S_CHANGE_DETECTION,
    S_CHANGE_HOLD,
    S_CHANGE_OFFSET_Q,
    S_CHANGE_Q,
    S_CUSUM_CAP,
    S_CUSUM_SCALE,
    S_CUSUM_THRESHOLD,
    S_DELAY_MEMORY,
    S_DELAY_UNCERTAINTY,
    S_GATE,
    S_HEADING,
    S_HIGH,
    S_INERTIA_UNCERTAINTY,
    S_LINEAR_RANGE,
    S_LOG,
    S_LOW,
    S_MAX_GATED,
    S_MAX_INTERVAL,
    S_MAX_LAT_ACC,
    S_MAX_NOISE_SCALE,
    S_MAX_SLIP,
    S_MAX_UTILISATION,
    S_MEASURE_ERRORS,
    S_METHOD,
    S_MIN_FRICTION,
    S_MIN_SPEED,
    S_NOISE_ADAPTATION,
    S_NOISE_CORRELATION,
    S_NOISE_MEMORY,
    S_P0_HEADING_OFFSET,
    S_P0_OFFSET,
    S_P0_PSI,
    S_P0_R,
    S_P0_STEERING_GAIN,
    S_P0_THETA_F,
    S_P0_THETA_R,
    S_P0_VY,
    S_PLAY_UNCERTAINTY,
    S_R_FROM_COVARIANCE,
    S_RAMP_SHIFT,
    S_RAMP_THRESHOLD,
    S_RELAXATION_UNCERTAINTY,
    S_ROLL_LEVER,
    S_SATURATION_CORRECTION,
    S_SATURATION_MEMORY,
    S_SATURATION_PRIOR,
    S_SCALE_UNCERTAINTY,
    S_SHIFT,
    S_SHIFT_THRESHOLD,
    S_SPEED_NOISE,
    X_HEADING_OFFSET,
    X_OFFSET,
    X_PSI,
    X_STEERING_GAIN,
    X_THETA_F,
    X_THETA_R,
)
from transplanter_ident.ekf.model import vehicle_array, work_buffer
from transplanter_ident.ekf.persistence import LearnedState
from transplanter_ident.ekf.relinearization import (
    FilterState,
    RelinearizationSchedule,
    run_relinearized,
    schedule_for,
)
from transplanter_ident.ekf.sequence import epoch_measurement_noise
from transplanter_ident.epochs.epoch import Epoch, EpochArrays


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
        heading = options.heading_state
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
        settings[S_ANTENNA_X] = config.vehicle.antenna_x
        settings[S_ROLL_LEVER] = config.vehicle.roll_lever
        settings[S_MAX_SLIP] = options.max_slip_angle
        settings[S_MAX_LAT_ACC] = options.max_lateral_acceleration
        settings[S_MAX_UTILISATION] = options.max_tire_utilisation
        settings[S_SATURATION_PRIOR] = options.saturation_prior
        settings[S_SATURATION_MEMORY] = options.saturation_memory
        settings[S_MIN_FRICTION] = options.min_friction
        settings[S_SATURATION_CORRECTION] = 1.0 if options.saturation_correction else 0.0
        settings[S_CUSUM_SCALE] = options.change_scale
        settings[S_CUSUM_THRESHOLD] = options.change_threshold
        settings[S_CUSUM_CAP] = 0.5 * options.change_threshold  # one outlier alone never raises an alarm
        settings[S_CHANGE_Q] = options.change_process_noise
        settings[S_SHIFT] = options.change_shift
        settings[S_SHIFT_THRESHOLD] = options.change_shift_threshold
        settings[S_RAMP_SHIFT] = options.change_ramp_shift
        settings[S_RAMP_THRESHOLD] = options.change_ramp_threshold
        settings[S_CHANGE_HOLD] = options.change_hold
        settings[S_CHANGE_OFFSET_Q] = options.change_offset_variance / options.change_hold
        settings[S_LINEAR_RANGE] = 1.0 if options.linear_range_check else 0.0
        settings[S_CHANGE_DETECTION] = 1.0 if options.change_detection else 0.0
        settings[S_R_FROM_COVARIANCE] = 1.0 if options.measurement_noise_from_covariance else 0.0
        settings[S_NOISE_ADAPTATION] = 1.0 if options.noise_adaptation else 0.0
        settings[S_NOISE_MEMORY] = options.noise_memory
        settings[S_MAX_NOISE_SCALE] = options.max_noise_scale
        settings[S_NOISE_CORRELATION] = 1.0 if options.noise_correlation else 0.0
        settings[S_DELAY_UNCERTAINTY] = options.timing_uncertainty
        settings[S_SCALE_UNCERTAINTY] = options.steering_scale_uncertainty
        settings[S_PLAY_UNCERTAINTY] = options.steering_play_uncertainty
        settings[S_INERTIA_UNCERTAINTY] = options.yaw_inertia_uncertainty
        settings[S_RELAXATION_UNCERTAINTY] = options.relaxation_uncertainty
        settings[S_MEASURE_ERRORS] = 1.0
        settings[S_SPEED_NOISE] = 1.0 if options.speed_noise else 0.0
        settings[S_DELAY_MEMORY] = options.identifiability_memory
        q, p0 = _state_diagonals(noise, options, config.vehicle.relaxation_length > 0.0)
        settings[S_P0_THETA_F], settings[S_P0_THETA_R] = p0[X_THETA_F], p0[X_THETA_R]  # recovery.py
        settings[S_P0_OFFSET], settings[S_P0_HEADING_OFFSET] = p0[X_OFFSET], p0[X_HEADING_OFFSET]
        settings[S_P0_STEERING_GAIN] = p0[X_STEERING_GAIN]
        x0 = np.zeros(len(q))
        x0[X_THETA_F] = to_state(noise.initial_stiffness[0])
        x0[X_THETA_R] = to_state(noise.initial_stiffness[1])
        x0[X_OFFSET] = config.vehicle.steering_offset
        return cls(
            vehicle=vehicle_array(config.vehicle, options.course),
            settings=settings,
            process_noise=q,
            measurement_noise=np.array(noise.measurement_noise, dtype=np.float64),
            initial_state=x0,
            initial_covariance=np.diag(p0),
        )


def _state_diagonals(noise: NoiseParams, options: FilterOptions, lagged: bool) -> tuple[np.ndarray, np.ndarray]:
    """Diag Q (a density, per second) and diag P0 in the state's order; a fixed offset or gain (b, g or h) has Q = P0 = 0.

    ``lagged`` (relaxing tires): the slip lags follow the motion states with Q = P0 = 0 (they start at
    0, a steady turn, and follow vy, r and the steering deterministically).
    """
    q, p0 = list(noise.process_noise), list(noise.initial_covariance)
    if options.heading_state:
        q.insert(X_PSI, noise.heading_process_noise)
        p0.insert(X_PSI, noise.initial_heading_covariance)
    motion = N_MOTION_HEADING if options.heading_state else N_MOTION_YAW_RATE
    q[motion:motion] = [0.0] * (N_LAG if lagged else 0)
    p0[motion:motion] = [0.0] * (N_LAG if lagged else 0)
    estimated = options.estimate_steering_offset
    q.append(noise.steering_offset_process_noise if estimated else 0.0)
    p0.append(noise.steering_offset_initial_variance if estimated else 0.0)
    estimated = options.estimate_steering_gain
    q.append(noise.steering_gain_process_noise if estimated else 0.0)
    p0.append(noise.steering_gain_initial_variance if estimated else 0.0)
    estimated = options.heading_offset_estimated
    q.append(noise.heading_offset_process_noise if estimated else 0.0)
    p0.append(noise.heading_offset_initial_variance if estimated else 0.0)
    scale = options.noise_rate_scale
    return np.array(q, dtype=np.float64) * scale, np.array(p0, dtype=np.float64)


class JointEKF:
    """The joint-state EKF, stepped one epoch at a time (the node's view)."""

    def __init__(self, config: EstimatorConfig) -> None:
        self._config = config
        self._arrays = FilterArrays.from_config(config)
        self._guard = identifiability_guard(config, self._arrays)
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
        self._guard.reset()
        self._schedule = relinearization_schedule(self._config, self._arrays)
        self._taken: list[np.ndarray] = []  # the epochs since the start, while a new pass may begin

    @property
    def recent_information(self) -> np.ndarray:
        """(3, 3) Fisher information of (ln Cf, ln Cr, b) of the recent epochs (ekf/identifiability.py)."""
        return self._guard.information

    def set_noise(self, noise: NoiseParams) -> None:
        """Swap Q and R at run time; the state and covariance carry on.

        A new R restarts the innovations' measure of it (adaptation.learn_noise_scales): its factors
        were relative to the old R.
        """
        config = EstimatorConfig(vehicle=self._config.vehicle, options=self._config.options, noise=noise)
        arrays = FilterArrays.from_config(config)
        if noise.measurement_noise != self._config.noise.measurement_noise:
            self._memo[M_NOISE_VY:M_NOISE_SPAN_SECOND + 1] = 0.0
        self._guard.set_config(config)
        self._config, self._arrays = config, arrays

    def learned_state(self, stamp: float) -> LearnedState:
        """The parameter states [theta_f, theta_r, b, g] and their covariance (what persistence saves)."""
        block = self.covariance[np.ix_(PARAMETER_STATES, PARAMETER_STATES)]
        return LearnedState((float(self.state[X_THETA_F]), float(self.state[X_THETA_R])),
                            float(self.state[X_OFFSET]), tuple(tuple(float(v) for v in row) for row in block), stamp,
                            float(self.state[X_STEERING_GAIN]))

    def restore(self, learned: LearnedState) -> None:
        """Start from saved parameter states (after :meth:`reset`); a fixed offset or gain stays as configured."""
        options = self._config.options
        estimated = (True, True, options.estimate_steering_offset, options.estimate_steering_gain)
        values = (*learned.theta, learned.offset, learned.gain)  # in PARAMETER_STATES' order
        block = np.array(learned.covariance, dtype=np.float64)
        for k, index in enumerate(PARAMETER_STATES):
            if estimated[k]:
                self.state[index] = values[k]
            else:
                block[k, :] = block[:, k] = 0.0
        index = np.ix_(PARAMETER_STATES, PARAMETER_STATES)
        self.covariance[index] = block
        self._guard.trust_restored()
        self._schedule.close()  # a learned state is linearised where it was learned
        self._taken = []

    def step(self, epoch: Epoch) -> Estimate:
        """Filter one epoch (eq. 12) and return the estimate."""
        a = self._arrays
        r_noise = a.measurement_noise
        if self._config.options.measurement_noise_from_covariance:  # as run/objective do (sequence.py)
            r_noise = np.zeros(2)
            epoch_measurement_noise(a.measurement_noise, True, a.settings[S_HEADING] > 0.5,
                                    epoch.velocity_variance, epoch.heading_variance, epoch.yaw_rate_variance, r_noise)
        ekf_step(self.state, self.covariance, self._model, self._memo, a.vehicle, a.settings,
                 a.process_noise, r_noise, epoch.t, epoch.speed, epoch.steering,
                 epoch.steering_rate, epoch.antenna_lateral_velocity, epoch.heading, epoch.yaw_rate, self._ws, self._out)
        row = epoch_row(epoch)
        self._guard.step(row, self._out)
        self._relinearize(row)
        return Estimate.from_row(epoch.t, self._out)

    @property
    def relinearized_passes(self) -> tuple[int, int]:
        """(tried, kept): the new passes over the start so far (ekf/relinearization.py)."""
        return self._schedule.passes - 1, self._schedule.kept

    def _relinearize(self, row: np.ndarray) -> None:
        """After an epoch: the pass to go on from (ekf/relinearization.py, as run_sequence)."""
        if not self._schedule.open:
            self._taken = []
            return
        self._taken.append(row)
        a = self._arrays
        state = FilterState(self.state, self.covariance, self._model, self._memo)
        state = self._schedule.step(self._taken, self._out, state, a.initial_state, a.initial_covariance,
                                    partial(_run_pass, a))
        self.state, self.covariance, self._model, self._memo = state.x, state.p, state.model, state.memo


def kernel_input(epochs: EpochArrays) -> np.ndarray:
    """The (N, N_EPOCH_COLUMNS) kernel input, columns in layout.EPOCH_COLUMNS order (E_*)."""
    return np.ascontiguousarray(np.column_stack([epochs.column(name) for name in EPOCH_COLUMNS]))


def run_sequence(config: EstimatorConfig, epochs: EpochArrays) -> np.ndarray:
    """Filter a whole epoch sequence; returns the (N, N_OUTPUTS) output rows."""
    a = FilterArrays.from_config(config)
    outputs = np.zeros((len(epochs), N_OUTPUTS))
    rows = kernel_input(epochs)

    run_relinearized(rows, a.initial_state, a.initial_covariance, relinearization_schedule(config, a),
                     partial(_run_pass, a), outputs)
    identifiability_guard(config, a).run(rows, outputs)
    return outputs


def _run_pass(a: FilterArrays, rows: np.ndarray, x: np.ndarray, p: np.ndarray, model: np.ndarray, memo: np.ndarray,
              outputs: np.ndarray) -> None:
    """The compiled filter over ``rows`` from (x, p, model, memo), in place (relinearization.Run)."""
    run_kernel(rows, x, p, model, memo, a.vehicle, a.settings, a.process_noise, a.measurement_noise, outputs)


def relinearization_schedule(config: EstimatorConfig, arrays: FilterArrays) -> RelinearizationSchedule:
    """The start-up's re-linearised passes (ekf/relinearization.py) for this configuration."""
    options = config.options
    return schedule_for(options.relinearization_window, options.relinearization_threshold,
                        options.stiffness_state == "log", arrays.initial_state)


def identifiability_guard(config: EstimatorConfig, arrays: FilterArrays) -> IdentifiabilityGuard:
    """The published band's guard (ekf/identifiability.py) for this configuration."""
    return IdentifiabilityGuard(config, arrays.initial_state, arrays.initial_covariance,
                                config.options.stiffness_state == "log")


def epoch_row(epoch: Epoch) -> np.ndarray:
    """The kernel input of one epoch (a row of kernel_input)."""
    return np.array([getattr(epoch, name) for name in EPOCH_COLUMNS], dtype=np.float64)


def sequence_objective(config: EstimatorConfig, epochs: EpochArrays, kind: str = "mae") -> float:
    """Tuning objective (``mae``: eq. 21, ``nll``: innovation negative log-likelihood)."""
    a = FilterArrays.from_config(config)
    code = MAE if kind == "mae" else NLL
    return float(objective_kernel(kernel_input(epochs), a.initial_state.copy(), a.initial_covariance.copy(),
                                  np.zeros(N_MODEL), np.zeros(N_MEMO), a.vehicle, a.settings, a.process_noise,
                                  a.measurement_noise, code))


def warm_up(config: EstimatorConfig) -> None:
    """Run the compiled step, the information sum and the run over epochs once (load or compile them).

    The node calls it before it subscribes, so no epoch waits for a kernel: a stall while one
    loads lets the executor take one topic's backlog first. The run over epochs is what a
    re-linearised pass takes (ekf/relinearization.py).
    """
    ekf = JointEKF(config)
    epochs = [Epoch(t=t, longitudinal_velocity=1.0, lateral_velocity=0.0, heading=0.0, yaw_rate=0.0, steering=0.1,
                    steering_rate=0.0, speed=1.0) for t in (0.0, 0.1, 1.2)]  # turned wheels: the bound is evaluated
    for epoch in epochs:
        ekf.step(epoch)
    run_sequence(config, EpochArrays(epochs))
