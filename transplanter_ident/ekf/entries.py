"""Entry points of the compiled filter, one per state size (paper eqs. 9-14, 21).

numba caches a function on disk only when it is defined at module level with its own source,
so each size has its own small entry here, calling the closures that :mod:`.kernels` makes for
that size. :data:`KERNELS` maps the state size to them; :func:`ekf_step`, :func:`run_kernel`,
:func:`objective_kernel` and :func:`predict` pick the size from the state vector.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from transplanter_ident.ekf.kernels import make_kernels
from transplanter_ident.jit import entry_kernel

_predict_yaw_rate, _step_yaw_rate, _run_yaw_rate, _objective_yaw_rate = make_kernels(4)
_predict_heading, _step_heading, _run_heading, _objective_heading = make_kernels(5)



@entry_kernel
def _predict_4(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN202
    _predict_yaw_rate(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)


@entry_kernel
def _predict_5(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN202
    _predict_heading(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)


@entry_kernel
def _step_4(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN202
            steering_rate, vy, psi, yaw_rate, ws, out):
    return _step_yaw_rate(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate,
                          vy, psi, yaw_rate, ws, out)


@entry_kernel
def _step_5(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN202
            steering_rate, vy, psi, yaw_rate, ws, out):
    return _step_heading(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering, steering_rate,
                         vy, psi, yaw_rate, ws, out)


@entry_kernel
def _run_4(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN202
    _run_yaw_rate(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


@entry_kernel
def _run_5(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN202
    _run_heading(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


@entry_kernel
def objective_4(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """objective_kernel for the 4-state (yaw_rate) filter; callable from compiled code."""
    return _objective_yaw_rate(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


@entry_kernel
def objective_5(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """objective_kernel for the 5-state (heading) filter; callable from compiled code."""
    return _objective_heading(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


class Kernels(NamedTuple):
    """The compiled filter for one state size (numba compiles each lazily, on first call)."""

    predict: Any
    step: Any
    run: Any
    objective: Any


#: by state size: 5 = [vy, r, psi, Cf, Cr] (heading), 4 = [vy, r, Cf, Cr] (yaw_rate)
KERNELS = {4: Kernels(_predict_4, _step_4, _run_4, objective_4), 5: Kernels(_predict_5, _step_5, _run_5, objective_5)}


def predict(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws):  # noqa: ANN001, ANN201
    """Prediction of eq. (12) in place: x <- f(x, u), model <- f(model, u); F = df/dx in ws[W_F].

    ``steering`` is the interval mean and ``steering_rate`` its slope: ``exact`` drives the ramp
    that starts at mean - rate dt / 2, ``euler`` holds the mean. ws: model.work_buffer().
    """
    KERNELS[x.shape[0]].predict(x, model, vehicle, settings, dt, speed, steering, steering_rate, ws)


def ekf_step(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,  # noqa: ANN001, ANN201
             steering_rate, vy, psi, yaw_rate, ws, out):
    """Process one epoch in place; return the StepStatus code. ``out`` receives one output row.

    x (n,), p (n, n): filter state and covariance; model (3,): open-loop model [vy, r, psi];
    memo (3,): [t_prev, initialised, consecutive gated]; q (n,), r_noise (2,): diag Q and R;
    ws: model.work_buffer(). ``speed`` and ``steering`` are means over the interval that ends
    at ``t``, ``steering_rate`` the slope of the steering over it; ``yaw_rate`` is the
    interval-mean yaw rate from heading increments.
    """
    return KERNELS[x.shape[0]].step(x, p, model, memo, vehicle, settings, q, r_noise, t, speed, steering,
                                    steering_rate, vy, psi, yaw_rate, ws, out)


def run_kernel(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs):  # noqa: ANN001, ANN201
    """ekf_step over every row of ``epochs`` (columns E_*); one output row per epoch."""
    KERNELS[x.shape[0]].run(epochs, x, p, model, memo, vehicle, settings, q, r_noise, outputs)


def objective_kernel(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind):  # noqa: ANN001, ANN201
    """Tuning objective over a sequence: eq. 21 mean |innovation| (MAE) or Gaussian NLL.

    Only epochs with a predicted measurement (UPDATED or GATED) count. A diverging filter, or
    one that never predicts, scores DIVERGENCE_PENALTY.
    """
    return KERNELS[x.shape[0]].objective(epochs, x, p, model, memo, vehicle, settings, q, r_noise, kind)


