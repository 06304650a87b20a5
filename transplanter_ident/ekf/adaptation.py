"""Beyond the paper: the tire's linear range and stiffness changes (DESIGN.md section 7).

* :func:`beyond_linear_range`: whether the slip angles (eq. 3) or the lateral acceleration have
  left the range where the linear tire of eq. 2 holds; the step then updates only the motion;
* :func:`detect_change`: a CUSUM test on the normalised innovation squared for a change of the
  innovation variance (a new surface); an alarm raises the stiffness random walk for a while.
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.layout import (
    M_ADAPT_UNTIL,
    M_CUSUM,
    O_CHANGE,
    O_CUSUM,
    O_LAT_ACC,
    O_SLIP_F,
    O_SLIP_R,
    S_CHANGE_HOLD,
    S_CUSUM_CAP,
    S_CUSUM_SCALE,
    S_CUSUM_THRESHOLD,
    S_LINEAR_RANGE,
    S_MAX_LAT_ACC,
    S_MAX_SLIP,
    VEH_LF,
    VEH_LR,
)
from transplanter_ident.jit import inline_kernel


@inline_kernel
def beyond_linear_range(vehicle, settings, speed, steering, offset, vy, yaw_rate, out):
    """Whether the slip angles or the lateral acceleration leave the linear tire's range.

    From the last estimate of vy and r (which the measurements keep close to the truth), not
    from the prediction (a wrong stiffness must not make the tires look saturated) nor from
    the differenced yaw rate (its noise would select the epochs).
    """
    lf, lr = vehicle[VEH_LF], vehicle[VEH_LR]
    slip_f = steering - offset - (vy + lf * yaw_rate) / speed
    slip_r = (lr * yaw_rate - vy) / speed
    lateral_acceleration = speed * yaw_rate
    out[O_SLIP_F] = slip_f
    out[O_SLIP_R] = slip_r
    out[O_LAT_ACC] = lateral_acceleration
    if settings[S_LINEAR_RANGE] < 0.5:
        return False
    limit = settings[S_MAX_SLIP]
    return abs(slip_f) > limit or abs(slip_r) > limit or abs(lateral_acceleration) > settings[S_MAX_LAT_ACC]


@inline_kernel
def detect_change(memo, settings, t, nis, out):
    """CUSUM of the log-likelihood ratio of a variance scale s of the innovations (chi^2_2 NIS).

    l = -ln s + NIS (1 - 1/s) / 2, capped; an alarm at g > threshold (a surface change) opens a
    window of ``change_hold`` s in which the stiffness random walk runs at the raised density
    ``change_process_noise``, so the estimate moves to the new surface over several epochs
    instead of one large, badly linearised step; the sum restarts.
    """
    scale = settings[S_CUSUM_SCALE]
    llr = min(-math.log(scale) + 0.5 * nis * (1.0 - 1.0 / scale), settings[S_CUSUM_CAP])
    g = max(0.0, memo[M_CUSUM] + llr)
    if g > settings[S_CUSUM_THRESHOLD]:
        memo[M_ADAPT_UNTIL] = t + settings[S_CHANGE_HOLD]
        out[O_CHANGE] = 1.0
        g = 0.0
    memo[M_CUSUM] = g
    out[O_CUSUM] = g


#: relative 1-sigma of a stiffness below which it counts as known (the linear-range check applies)
KNOWN_REL_STD = 0.1


@inline_kernel
def known_to(theta, variance, log_state):
    """Whether a stiffness state (ln C, or C) is known to KNOWN_REL_STD relative 1-sigma.

    The linear-range hold applies only then: before, a still wrong offset or stiffness makes every
    slip look large, and holding the stiffness would trap the filter where it is.
    """
    std = math.sqrt(max(variance, 0.0))
    return std <= KNOWN_REL_STD if log_state else std <= KNOWN_REL_STD * abs(theta)
