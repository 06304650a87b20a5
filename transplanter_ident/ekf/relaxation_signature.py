"""Beyond the paper: a tire relaxation length left out of ``vehicle.relaxation_length``, measured online.

A real tire builds its lateral force over its relaxation length sigma of travel (DESIGN.md section 7):
the force follows the effective slip y, (sigma / vx) y' + y = alpha. To first order in a length
d_sigma left out of the model, each axle's effective slip is short by d_sigma y' / vx, where y' is the
slip's rate (alpha' of eq. 3 when the model has no lag, else vx d / sigma from the slip lag d of
:mod:`.model`). Eq. 4 does not have it, and the stiffness takes it up: 0.3 m at 2 m/s makes Cf
~12 % high while the innovations stay white to the eye.

Over one interval that shortfall is a constant slip deficit per axle, eps = y' / vx per metre; with
the filter's own exact discretisation (the Jacobian F of eq. 13) the motion it misses is

* front: eps_f F[:, b] (a slip deficit at the front wheel is a steering offset, F[:, b] = -E[:, delta]);
* rear: -eps_r (-vx (F[:, vy] - e_vy) + F[:, b]), because the rear axle's force column of eq. 4 is
  -vx A[:, vy] minus the front's, and int e^(A s) ds A = E - I.

:func:`.adaptation.carry_bias` carries it through the filter's F and K (the stiffness takes up what it
can), which gives the innovation per metre that the rest leaves: :func:`.adaptation.score_signature`
fits the innovations to it (O_RELAXATION, its std; memory ``ekf.saturation_memory``, the tire's other
measure's), and the stiffness's share per metre is the sensitivity O_RELAXATION_SENS_F/R. The validity
uses both, as for a GNSS delay. The fit takes the vy innovation alone: the heading's signature
integrates the steering sensor's noise (its rate is in eps) into a slow error that shrank the fit
to ~0.6 of the length at 0.1 deg of steering noise (with GNSS noise 10x below the default; an
instrument, the previous epoch's signature, shrank it alike); with vy alone 0.3 m reads 0.28-0.30 m.
"""

from __future__ import annotations

from transplanter_ident.ekf.adaptation import carry_bias
from transplanter_ident.ekf.layout import (
    B_DIRECT,
    M_RELAXATION_BIAS,
    VEH_LF,
    VEH_LR,
    W_BIAS,
    W_F,
    X_R,
    X_VY,
)
from transplanter_ident.jit import inline_kernel


@inline_kernel
def slip_deficits(before, after, vehicle, dt, speed, steering_rate, first_lag, lagged_active, relaxation):
    """(eps_f, eps_r): each axle's effective slip rate over the interval / vx, the slip deficit per metre of sigma.

    From the open-loop model's motion (layout.N_MODEL) before and after the interval's prediction, and
    the steering ramp (the offset is the same at both ends). The model, driven by the steering alone,
    carries none of the GNSS noise that the filter's own states do (on the identification drive the
    two gave the same fit: what shrank it was the heading channel, see the module). With the slip lags active
    (``lagged_active``, at ``first_lag``) the effective slip is alpha - d, whose rate is vx d /
    ``relaxation``: the mean of the two ends.
    """
    lf, lr = vehicle[VEH_LF], vehicle[VEH_LR]
    if lagged_active:
        rate_f = 0.5 * (before[first_lag] + after[first_lag]) * speed / relaxation
        rate_r = 0.5 * (before[first_lag + 1] + after[first_lag + 1]) * speed / relaxation
    else:
        d_vy, d_r = after[X_VY] - before[X_VY], after[X_R] - before[X_R]
        rate_f = steering_rate - (d_vy + lf * d_r) / (speed * dt)
        rate_r = (lr * d_r - d_vy) / (speed * dt)
    return rate_f / speed, rate_r / speed


@inline_kernel
def propagate_relaxation_bias(memo, n, nd, nb, h1, updated, speed, eps_f, eps_r, ws):
    """The estimate's first-order bias per metre of relaxation length left out (memo M_RELAXATION_BIAS).

    The motion the prediction misses (the module docstring) into ws[W_BIAS, B_DIRECT], then
    :func:`.adaptation.carry_bias`. Returns H b of the prediction: the innovation per metre.
    """
    for i in range(nd):
        kinematic = ws[W_F, i, X_VY] - (1.0 if i == X_VY else 0.0)
        ws[W_BIAS, B_DIRECT, i] = (eps_f - eps_r) * ws[W_F, i, nb] + eps_r * speed * kinematic
    return carry_bias(memo, M_RELAXATION_BIAS, n, nd, h1, updated, B_DIRECT, ws, 0.0)

