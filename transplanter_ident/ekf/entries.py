"""Entry points of the compiled filter, one per state size (paper eqs. 9-14, 21).

numba caches a function on disk only when it is defined at module level with its own source,
so each size has its own small entry here, calling the closures that :mod:`.kernels` makes for
that size. The run and objective loops (:mod:`.sequence`) call the step's entry, so the step is
compiled once and, from numba's disk cache, shared by every process (the tuner's workers).
:data:`KERNELS` maps the state size to them; :func:`ekf_step`, :func:`run_kernel`,
:func:`objective_kernel` and :func:`predict` pick the size from the state vector.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from transplanter_ident.ekf.kernels import make_kernels
from transplanter_ident.ekf.layout import (
    HEADING_LAG_STATES,
    HEADING_STATES,
    N_EPOCH_COLUMNS,
    N_MEMO,
    N_MODEL,
    N_OUTPUTS,
    N_SETTINGS,
    N_VEHICLE,
    VEH_RELAXATION,
    WORK_SIZE,
    WORK_SLOTS,
    YAW_RATE_LAG_STATES,
    YAW_RATE_STATES,
)
from transplanter_ident.ekf.sequence import make_sequence_kernels
from transplanter_ident.jit import entry_kernel

_predict_yaw_rate, _step_yaw_rate = make_kernels(heading=False)
_predict_heading, _step_heading = make_kernels(heading=True)
_predict_yaw_rate_lagged, _step_yaw_rate_lagged = make_kernels(heading=False, lagged=True)
_predict_heading_lagged, _step_heading_lagged = make_kernels(heading=True, lagged=True)



@entry_kernel
def _predict_yaw_rate_entry(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN202
    _predict_yaw_rate(x, model, vehicle, settings, dt, speed, steering, steering_rate, vehicle[VEH_RELAXATION], ws)


@entry_kernel
def _predict_heading_entry(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN202
    _predict_heading(x, model, vehicle, settings, dt, speed, steering, steering_rate, vehicle[VEH_RELAXATION], ws)


@entry_kernel(runtime=False)
def _step_yaw_rate_entry(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN202
            steering_rate, vy, psi, yaw_rate, ws, out):
    return _step_yaw_rate(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate,
                          vy, psi, yaw_rate, ws, out)


@entry_kernel(runtime=False)
def _step_heading_entry(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN202
            steering_rate, vy, psi, yaw_rate, ws, out):
    return _step_heading(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate,
                         vy, psi, yaw_rate, ws, out)


@entry_kernel
def _predict_yaw_rate_lagged_entry(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN202
    _predict_yaw_rate_lagged(x, model, vehicle, settings, dt, speed, steering, steering_rate, vehicle[VEH_RELAXATION], ws)


@entry_kernel
def _predict_heading_lagged_entry(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN202
    _predict_heading_lagged(x, model, vehicle, settings, dt, speed, steering, steering_rate, vehicle[VEH_RELAXATION], ws)


@entry_kernel(runtime=False)
def _step_yaw_rate_lagged_entry(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN202
            steering_rate, vy, psi, yaw_rate, ws, out):
    return _step_yaw_rate_lagged(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate,
                                 vy, psi, yaw_rate, ws, out)


@entry_kernel(runtime=False)
def _step_heading_lagged_entry(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN202
            steering_rate, vy, psi, yaw_rate, ws, out):
    return _step_heading_lagged(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate,
                                vy, psi, yaw_rate, ws, out)


# The loops call the step's own cached entry: the step is compiled once, and a process that finds
# it in numba's disk cache (one compiled by another process) only links it.
_run_yaw_rate, _objective_yaw_rate = make_sequence_kernels(_step_yaw_rate_entry, heading=False)
_run_heading, _objective_heading = make_sequence_kernels(_step_heading_entry, heading=True)
_run_yaw_rate_lagged, _objective_yaw_rate_lagged = make_sequence_kernels(_step_yaw_rate_lagged_entry, heading=False)
_run_heading_lagged, _objective_heading_lagged = make_sequence_kernels(_step_heading_lagged_entry, heading=True)


@entry_kernel
def _run_yaw_rate_entry(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN202
    _run_yaw_rate(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


@entry_kernel
def _run_heading_entry(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN202
    _run_heading(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


@entry_kernel
def objective_yaw_rate(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """objective_kernel for the yaw_rate filter; callable from compiled code."""
    return _objective_yaw_rate(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


@entry_kernel
def objective_heading(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """objective_kernel for the heading filter; callable from compiled code."""
    return _objective_heading(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


@entry_kernel
def _run_yaw_rate_lagged_entry(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN202
    _run_yaw_rate_lagged(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


@entry_kernel
def _run_heading_lagged_entry(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN202
    _run_heading_lagged(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


@entry_kernel
def objective_yaw_rate_lagged(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """objective_kernel for the yaw_rate filter with relaxing tires; callable from compiled code."""
    return _objective_yaw_rate_lagged(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


@entry_kernel
def objective_heading_lagged(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """objective_kernel for the heading filter with relaxing tires; callable from compiled code."""
    return _objective_heading_lagged(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


class Kernels(NamedTuple):
    """The compiled filter for one state size (numba compiles each lazily, on first call)."""

    predict: Any
    step: Any
    run: Any
    objective: Any


#: by state size: HEADING_STATES = [vy, r, psi, th_f, th_r, b], YAW_RATE_STATES = [vy, r, th_f, th_r, b], and
#: with relaxing tires the slip lags after the motion states (HEADING_LAG_STATES, YAW_RATE_LAG_STATES)
KERNELS = {
    YAW_RATE_STATES: Kernels(_predict_yaw_rate_entry, _step_yaw_rate_entry, _run_yaw_rate_entry, objective_yaw_rate),
    HEADING_STATES: Kernels(_predict_heading_entry, _step_heading_entry, _run_heading_entry, objective_heading),
    YAW_RATE_LAG_STATES: Kernels(_predict_yaw_rate_lagged_entry, _step_yaw_rate_lagged_entry,
                                 _run_yaw_rate_lagged_entry, objective_yaw_rate_lagged),
    HEADING_LAG_STATES: Kernels(_predict_heading_lagged_entry, _step_heading_lagged_entry, _run_heading_lagged_entry,
                                objective_heading_lagged),
}


def kernels_for(x, p=None, model=None, memo=None, vehicle=None, settings=None, q=None,  # noqa: ANN001, ANN201, PLR0913
                r_noise=None, ws=None, out=None, epochs=None, outputs=None):
    """The kernels for x's size, after checking every array's shape.

    The compiled code does not bounds-check: a wrong size would corrupt memory instead of raising.
    """
    n = x.shape[0] if x.ndim == 1 else -1
    if n not in KERNELS:
        raise ValueError(f"state vector of shape {x.shape}: expected one of {sorted((k,) for k in KERNELS)}")
    expected = {"p": (p, (n, n)), "model": (model, (N_MODEL,)), "memo": (memo, (N_MEMO,)),
                "vehicle": (vehicle, (N_VEHICLE,)), "settings": (settings, (N_SETTINGS,)), "q": (q, (n,)),
                "r_noise": (r_noise, (2,)), "ws": (ws, (WORK_SLOTS, WORK_SIZE, WORK_SIZE)),
                "out": (out, (N_OUTPUTS,))}
    for name, (array, shape) in expected.items():
        if array is not None and array.shape != shape:
            raise ValueError(f"{name} has shape {array.shape}, expected {shape}")
    if epochs is not None and (epochs.ndim != 2 or epochs.shape[1] != N_EPOCH_COLUMNS):
        raise ValueError(f"epochs has shape {epochs.shape}, expected (N, {N_EPOCH_COLUMNS})")
    if outputs is not None and outputs.shape != (epochs.shape[0], N_OUTPUTS):
        raise ValueError(f"outputs has shape {outputs.shape}, expected ({epochs.shape[0]}, {N_OUTPUTS})")
    return KERNELS[n]


def predict(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN201
    """Prediction of eq. (12) in place: x <- f(x, u), model <- f(model, u); F = df/dx in ws[W_F].

    ``steering`` is the interval mean and ``steering_rate`` its slope: ``exact`` drives the ramp
    that starts at mean - rate dt / 2, ``euler`` holds the mean. ws: model.work_buffer().
    """
    kernels = kernels_for(x, model=model, vehicle=vehicle, settings=settings, ws=ws)
    kernels.predict(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)


def ekf_step(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN201
             steering_rate, vy, psi, yaw_rate, ws, out):
    """Process one epoch in place; return the StepStatus. ``out`` receives one output row.

    Parameters (n = HEADING_STATES or YAW_RATE_STATES, N_LAG more with relaxing tires; every array
    float64, updated in place where marked *):

    x : (n,)*           state [vy, r, (psi,) (d_f, d_r,) theta_f, theta_r, b], layout.X_*
    p : (n, n)*         state covariance P
    model : (N_MODEL,)*  open-loop model output (paper Figs. 6-7): [vy, r, psi], or x's motion states and lags
    memo : (N_MEMO,)*   [t_prev, initialised, consecutive gated, CUSUM, adapting until, consecutive diverged,
                        saturation bias of each state (n), R's measure, the delay's and gain's biases,
                        the speed sample's covariance with each state, the directional test], layout.M_*
    vehicle : (N_VEHICLE,)  [mass, lf, lr, iz, relaxation length], model.vehicle_array
    settings : (N_SETTINGS,)  options as numbers, layout.S_*
    q : (n,)            diag Q as a spectral density (per second; each interval adds q dt)
    r_noise : (2,)      diag R: vy (m/s)^2, then psi rad^2 (or r (rad/s)^2)
    t : float           epoch time, s (interval end)
    speed : float       interval-mean vx at the CG, m/s
    steering : float    interval-mean steering sensor angle, rad (the wheel angle is this - b)
    steering_rate : float  least-squares slope of the steering over the interval, rad/s
    vy : float          lateral velocity at the antenna, body axes, m/s (h: vy + antenna_x r)
    psi : float         unwrapped ENU heading at t, rad
    yaw_rate : float    interval-mean r from heading increments, rad/s
    ws : (WORK_SLOTS, WORK_SIZE, WORK_SIZE)*  scratch, model.work_buffer()
    out : (N_OUTPUTS,)* one output row, layout.O_*
    """
    kernels = kernels_for(x, p, model, memo, vehicle, settings, q, r_noise, ws, out)
    return kernels.step(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate, vy,
                        psi, yaw_rate, ws, out)


def run_kernel(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN201
    """ekf_step over every row of ``epochs`` (columns E_*); one output row per epoch."""
    kernels = kernels_for(x, p, model, memo, vehicle, settings, q, r_noise, epochs=epochs, outputs=outputs)
    kernels.run(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


def objective_kernel(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """Tuning objective over a sequence: eq. 21 mean |innovation| (MAE) or Gaussian NLL.

    Only epochs with a predicted measurement (UPDATED, GATED, NONLINEAR) count. A diverging
    filter, or one that never predicts, scores DIVERGENCE_PENALTY.
    """
    kernels = kernels_for(x, p, model, memo, vehicle, settings, q, r_noise, epochs=epochs)
    return kernels.objective(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


