"""Beyond the paper: the tire's linear range and stiffness changes (DESIGN.md section 7).

* :func:`beyond_linear_range`: whether the tire forces (the stiffness times the slip angles of
  eq. 3, against what a tire at ``min_friction`` could give), the slip angles themselves or the
  lateral acceleration have left the range where the linear tire of eq. 2 holds; the step then
  updates only the motion;
* the change tests (a new surface) are in :mod:`.change`;
* :func:`propagate_tire_bias`: the bias the linear tire takes if the surface is as slippery as
  ``ekf.min_friction`` (first order, through the filter's own F and K); the reported stiffness
  standard deviations include it; :func:`propagate_delay_bias`: likewise per second of GNSS delay
  left out of ``gnss.delay`` (the std holds it times ``ekf.delay_uncertainty``);
  :func:`propagate_scale_bias`: per unit of steering-sensor gain left out of
  ``vehicle.steering_scale`` (times ``ekf.steering_scale_uncertainty``), :func:`propagate_inertia_bias`
  per unit of ln Iz left out of ``vehicle.iz`` (times ``ekf.yaw_inertia_uncertainty``;
  :func:`held_bias_variance` sums what the std holds); :func:`score_signature` measures that delay, that gain, and how
  far the tires saturate, from the innovations (evaluation/model_errors.py tests the measures; with
  :func:`carry_bias`, :mod:`.relaxation_signature` and :mod:`.heading_signature` measure a relaxation
  length and a misaligned heading);
  :func:`saturation_share` turns the latter into the correction of Cf, Cr and the bias the std keeps;
* :func:`learn_noise_scales` / :func:`noise_scale`: R as the innovations show it (covariance
  matching, E[e e^T] = H P^- H^T + R), never below the configured R. Sensors noisier than R would
  otherwise look like a stiffness change to the CUSUM at every epoch and narrow the band
  (noise_correlation.restart_noise_when_near drops what the filter's own start showed of R).
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.layout import (
    B_DIRECT,
    B_INERTIA,
    G_K0,
    G_K1,
    M_BIAS,
    M_DELAY_BIAS,
    M_DELAY_INFORMATION,
    M_DELAY_SCORE,
    M_DELAY_SETTLED,
    M_HEADING_BIAS,
    M_INERTIA_BIAS,
    M_NOISE_SECOND,
    M_NOISE_SPAN_SECOND,
    M_NOISE_SPAN_VY,
    M_NOISE_VY,
    M_PLAY_BIAS,
    M_RELAXATION_BIAS,
    M_SATURATION_INFORMATION,
    M_SATURATION_SCORE,
    M_SCALE_BIAS,
    O_LAT_ACC,
    O_SLIP_F,
    O_SLIP_R,
    S_DELAY_MEMORY,
    S_DELAY_UNCERTAINTY,
    S_INERTIA_UNCERTAINTY,
    S_LINEAR_RANGE,
    S_MAX_LAT_ACC,
    S_MAX_NOISE_SCALE,
    S_MAX_SLIP,
    S_MAX_UTILISATION,
    S_MIN_FRICTION,
    S_NOISE_ADAPTATION,
    S_NOISE_MEMORY,
    S_PLAY_UNCERTAINTY,
    S_RELAXATION_UNCERTAINTY,
    S_SATURATION_CORRECTION,
    S_SATURATION_MEMORY,
    S_SATURATION_PRIOR,
    S_SCALE_UNCERTAINTY,
    V_BIAS,
    VEH_LF,
    VEH_LR,
    VEH_MASS,
    W_BIAS,
    W_F,
    W_GAIN,
    W_VEC,
)
from transplanter_ident.ekf.measurement_row import vy_row_times
from transplanter_ident.jit import inline_kernel


@inline_kernel
def beyond_linear_range(vehicle, settings, speed, steering, offset, vy, yaw_rate, cf, cr, out):
    """Whether the tire forces, the slip angles or the lateral acceleration leave the linear tire's range.

    From the last estimate of vy and r (which the measurements keep close to the truth), not
    from the prediction (a wrong stiffness must not make the tires look saturated) nor from
    the differenced yaw rate (its noise would select the epochs). The force test is the stiffness
    (cf, cr, N/rad) times the slip against ``max_tire_utilisation`` of what the tire gives at
    ``min_friction`` (:func:`friction_utilisation`): the linear range in slip is mu Fz / C, wider
    for a soft tire than for a stiff one, so no one slip angle bounds it for every tire.
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
    if abs(slip_f) > limit or abs(slip_r) > limit or abs(lateral_acceleration) > settings[S_MAX_LAT_ACC]:
        return True
    most = settings[S_MAX_UTILISATION]
    return most > 0.0 and max(friction_utilisation(settings, vehicle, slip_f, cf, True),
                              friction_utilisation(settings, vehicle, slip_r, cr, False)) > most


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


#: m/s^2, for the static axle loads
GRAVITY = 9.81


@inline_kernel
def friction_utilisation(settings, vehicle, slip, stiffness, front):
    """The normalised slip |C alpha| / (mu Fz) of one tire: its linear force over its limit at ``min_friction``.

    Fz is the static load of one tire of the axle. 0 when mu <= 0 (off).
    """
    mu = settings[S_MIN_FRICTION]
    if not mu > 0.0:
        return 0.0
    lf, lr = vehicle[VEH_LF], vehicle[VEH_LR]
    load = 0.5 * vehicle[VEH_MASS] * GRAVITY * (lr if front else lf) / (lf + lr)
    return abs(stiffness * slip) / (mu * load)


@inline_kernel
def saturation_deficit(settings, vehicle, slip, stiffness, front):
    """ln(F / (C alpha)) of one tire whose force is mu Fz tanh(C alpha / (mu Fz)), mu = ``min_friction``.

    A smooth saturating curve with the small-slip stiffness C and the friction limit mu Fz (Fz: the
    static load of one tire of the axle). It is ~ -x^2 / 3 at the normalised slip x = C alpha / (mu Fz):
    the linear tire overstates the force by 4 % at a third of the friction limit. 0 when mu <= 0 (off).
    """
    x = min(friction_utilisation(settings, vehicle, slip, stiffness, front), 20.0)
    if x < 1.0e-4:
        return -x * x / 3.0
    return math.log(math.tanh(x) / x)


@inline_kernel
def propagate_bias(memo, slot, n, nd, h1, updated, d_f, d_r, d_b, ws):
    """B = E[x_true - x] to first order, in memo[slot:slot + n], when the truth moves differently.

    Over an interval the true motion follows the parameters shifted by (d_f, d_r, d_b) (theta_f,
    theta_r, steering offset): the prediction misses F[:, theta] d (the filter's own Jacobian,
    ws[W_F]) (:func:`carry_bias`). Returns H b before the update.
    """
    for i in range(nd):
        ws[W_BIAS, B_DIRECT, i] = ws[W_F, i, nd] * d_f + ws[W_F, i, nd + 1] * d_r + ws[W_F, i, nd + 2] * d_b
    return carry_bias(memo, slot, n, nd, h1, updated, B_DIRECT, ws, 0.0)


@inline_kernel
def carry_bias(memo, slot, n, nd, h1, updated, direct, ws, measured):
    """B <- F b + g over the interval, g in ws[W_BIAS, direct] (the motion the prediction misses); then the update.

    ``measured``: what the model error adds to the vy measurement (heading_signature.py; 0 for the others).
    An update (gain K in ws[W_GAIN], zero rows where the step held them) takes b <- (I - K (H b + m)).
    Called once the step is accepted; returns H b + m before the update: the innovation the error leaves.
    """
    for i in range(n):
        acc = memo[slot + i]
        if i < nd:
            acc = ws[W_BIAS, direct, i]
            for j in range(n):
                acc += ws[W_F, i, j] * memo[slot + j]
        ws[W_VEC, V_BIAS, i] = acc
    hb0 = vy_row_times(ws, n, ws[W_VEC, V_BIAS]) + measured  # H[0] b (measurement_row.py)
    hb1 = ws[W_VEC, V_BIAS, h1]
    for i in range(n):
        b = ws[W_VEC, V_BIAS, i]
        if updated:
            b -= ws[W_GAIN, G_K0, i] * hb0 + ws[W_GAIN, G_K1, i] * hb1
        memo[slot + i] = b
    return hb0, hb1


@inline_kernel
def propagate_tire_bias(memo, vehicle, settings, n, nd, h1, updated, slip_f, slip_r, cf, cr,
                        log_state, ws):
    """The estimate's first-order bias (memo M_BIAS) if the tires saturate at ``min_friction``.

    The true motion follows the stiffness C e^d (d = :func:`saturation_deficit` of the interval's
    slip). With ``log_state`` theta = ln C, else theta = C (d C, to first order); the parameter
    entries are the stiffness bias (ln C or N/rad). Returns H b of the prediction: the innovation
    such a tire causes (:func:`score_signature`).
    """
    d_f = saturation_deficit(settings, vehicle, slip_f, cf, True)
    d_r = saturation_deficit(settings, vehicle, slip_r, cr, False)
    if not log_state:
        d_f, d_r = cf * d_f, cr * d_r
    return propagate_bias(memo, M_BIAS, n, nd, h1, updated, d_f, d_r, 0.0, ws)


@inline_kernel
def propagate_delay_bias(memo, n, nd, h1, updated, steering_rate, ws):
    """The estimate's first-order bias per second of GNSS delay not in ``gnss.delay`` (memo M_DELAY_BIAS).

    GNSS stamped tau late describes the motion that the steering tau earlier caused: the true wheel
    angle is the filter's minus tau times the steering rate, a steering offset of tau * rate. Returns
    H b of the prediction: the innovation per second of such a delay (:func:`score_signature`).
    """
    return propagate_bias(memo, M_DELAY_BIAS, n, nd, h1, updated, 0.0, 0.0, steering_rate, ws)


@inline_kernel
def propagate_scale_bias(memo, n, nd, h1, updated, steering, ws):
    """The estimate's first-order bias per unit of steering gain left out of the configured one (M_SCALE_BIAS).

    A sensor whose gain is 1 + eps times the configured one makes the true wheel angle the filter's
    plus eps times the (scaled) sensor angle: a steering offset of -eps * steering over the interval.
    Returns H b of the prediction: the innovation per unit of such a gain (:func:`score_signature`;
    a yaw inertia off ``vehicle.iz`` leaves a look-alike).
    """
    return propagate_bias(memo, M_SCALE_BIAS, n, nd, h1, updated, 0.0, 0.0, -steering, ws)


@inline_kernel
def propagate_inertia_bias(memo, settings, n, nd, h1, updated, ws):
    """The estimate's first-order bias per unit of ln Iz left out of ``vehicle.iz`` (memo M_INERTIA_BIAS).

    Iz scales the yaw equation alone (paper eq. 1), which no shift of theta or the offset mimics: the
    prediction misses d x_{k+1} / d ln Iz, which :func:`.prediction.make_prediction`'s
    ``predict_inertia_gain`` left in ws[W_BIAS, B_INERTIA]. Only with ``ekf.yaw_inertia_uncertainty`` > 0.
    """
    if settings[S_INERTIA_UNCERTAINTY] > 0.0:
        carry_bias(memo, M_INERTIA_BIAS, n, nd, h1, updated, B_INERTIA, ws, 0.0)


@inline_kernel
def held_bias_variance(memo, settings, i, unpinned):
    """The variance that state i's std holds for the biases of the model's known errors.

    The tire's (the share ``unpinned`` of it), and at their configured 1-sigma the delay's, the steering
    gain's, the yaw inertia's, the relaxation length's and the steering play's (``ekf.*_uncertainty``).
    """
    tire = memo[M_BIAS + i]
    delay = memo[M_DELAY_BIAS + i] * settings[S_DELAY_UNCERTAINTY]
    scale = memo[M_SCALE_BIAS + i] * settings[S_SCALE_UNCERTAINTY]
    inertia = memo[M_INERTIA_BIAS + i] * settings[S_INERTIA_UNCERTAINTY]
    lag = memo[M_RELAXATION_BIAS + i] * settings[S_RELAXATION_UNCERTAINTY]
    play = memo[M_PLAY_BIAS + i] * settings[S_PLAY_UNCERTAINTY]
    return unpinned * tire * tire + delay * delay + scale * scale + inertia * inertia + lag * lag + play * play


@inline_kernel
def forget_motion_bias(memo, nd):
    """The motion states taken from a measurement carry no bias of the model (any kind)."""
    for i in range(nd):
        memo[M_BIAS + i] = 0.0
        memo[M_DELAY_BIAS + i] = 0.0
        memo[M_SCALE_BIAS + i] = 0.0
        memo[M_INERTIA_BIAS + i] = 0.0
        memo[M_RELAXATION_BIAS + i] = 0.0
        memo[M_HEADING_BIAS + i] = 0.0
        memo[M_PLAY_BIAS + i] = 0.0


@inline_kernel
def noise_scale(memo, settings, slot, span_slot):
    """The factor on R of one measurement (memo ``slot``, with its ``span_slot``): 1 until measured, in [1, max]."""
    if settings[S_NOISE_ADAPTATION] < 0.5 or not memo[span_slot] > 0.0:
        return 1.0
    return min(max(memo[slot], 1.0), settings[S_MAX_NOISE_SCALE])


@inline_kernel
def _learn_ratio(memo, settings, slot, span_slot, dt, innovation, prior, noise, r):
    """One channel: the sample (e^2 - prior) / r, weighted by (noise / (prior + noise))^2 (var e^2 = 2 S^2)."""
    s = prior + noise
    weight = (noise / s) ** 2 * dt
    span = min(memo[span_slot] + weight, settings[S_NOISE_MEMORY])
    if not span > 0.0:
        return
    memo[slot] += weight / span * ((innovation * innovation - prior) / r - memo[slot])
    memo[span_slot] = span


@inline_kernel
def learn_noise_scales(memo, settings, dt, e0, e1, prior0, prior1, noise0, noise1, r0, r1, velocity):
    """Covariance matching: (e_i^2 - prior_i) / R_i has the mean R_true,i / R_i.

    e0, e1: the innovations; prior0, prior1: what S holds besides this measurement's own noise (H P^- H^T,
    and in vy the heading's vx^2 R_psi); noise0, noise1: that noise as the step took it (R times the
    learned factor); r0, r1: this epoch's R as configured (or reported). Each sample weighs
    (noise / S)^2 (var e^2 = 2 S^2): an epoch whose prior is far less certain than its noise says
    little about R. A weighted mean over the first ``ekf.noise_memory`` seconds, then exponential with
    that time constant; once the model is near it starts again (noise_correlation.restart_noise_when_near). Only
    epochs that passed the gate count. ``velocity`` False: the second measurement's alone (kernels.py: vy's
    waits while a misaligned heading may still hide in it).
    """
    if settings[S_NOISE_ADAPTATION] < 0.5:
        return
    if velocity:
        _learn_ratio(memo, settings, M_NOISE_VY, M_NOISE_SPAN_VY, dt, e0, prior0, noise0, r0)
    _learn_ratio(memo, settings, M_NOISE_SECOND, M_NOISE_SPAN_SECOND, dt, e1, prior1, noise1, r1)


#: s of accepted data before the delay is scored: the filter's own start (offset and stiffness converging
#: from their priors) is not the small, linear response the bias propagation describes
DELAY_SETTLE = 10.0


@inline_kernel
def score_signature(memo, score_slot, information_slot, memory, dt, g0, g1, e0, e1, s00, s01, s11, det):
    """Least squares of the innovations e on a signature g (the innovation per unit of a model error).

    S the innovation covariance. Score sum g^T S^-1 e and information sum g^T S^-1 g, both forgetting
    with the time constant settings[S_DELAY_MEMORY]; the estimate is score / information, its std
    information^-1/2 (:func:`signature_estimate`). Only once DELAY_SETTLE s of data have been seen.
    """
    if memo[M_DELAY_SETTLED] < DELAY_SETTLE or not det > 0.0:
        return
    forget = math.exp(-dt / memory)
    w0 = (g0 * s11 - g1 * s01) / det  # S^-1 g
    w1 = (g1 * s00 - g0 * s01) / det
    memo[score_slot] = forget * memo[score_slot] + w0 * e0 + w1 * e1
    memo[information_slot] = forget * memo[information_slot] + w0 * g0 + w1 * g1


@inline_kernel
def score_model_errors(memo, settings, dt, g0, g1, tire0, tire1, e0, e1, s00, s01, s11, det):
    """One accepted epoch's innovations e against the signatures of a GNSS delay (g) and of a saturating tire."""
    memo[M_DELAY_SETTLED] += dt
    score_signature(memo, M_DELAY_SCORE, M_DELAY_INFORMATION, settings[S_DELAY_MEMORY], dt, g0, g1, e0, e1, s00, s01,
                    s11, det)
    score_signature(memo, M_SATURATION_SCORE, M_SATURATION_INFORMATION, settings[S_SATURATION_MEMORY], dt, tire0,
                    tire1, e0, e1, s00, s01, s11, det)


@inline_kernel
def signature_estimate(memo, score_slot, information_slot):
    """(estimate, its std) of :func:`score_signature`; (0, 0) before it has information."""
    information = memo[information_slot]
    if not information > 0.0:
        return 0.0, 0.0
    return memo[score_slot] / information, 1.0 / math.sqrt(information)


#: relative error of the first-order tire bias as a correction: told the friction (``saturation_correction``)
#: on mu 0.3, it leaves ~0 of the bias at +-15 deg steer (35 % of the friction limit) and ~25 % at +-25 deg,
#: and the measured share is ~1.6 at 3 m/s (bench/real_sensors.py's wet drives); the std holds half of it
FIRST_ORDER_ERROR = 0.5


#: the saturation a band holds reaches the measure's upper bound at this many std, if below 1 (a tire at
#: ``min_friction``): large slips that stay linear show a tire far grippier than that
SATURATION_REACH_SIGMAS = 1.0


@inline_kernel
def saturation_share(memo, settings):
    """(share, unpinned): Cf, Cr take share x their bias at ``min_friction``; the std holds unpinned x it^2.

    share = the posterior's mode of the saturation a (1: a tire at ``min_friction``, 0: a linear tire),
    with the prior N(0, ``saturation_prior``^2) bounded to a >= 0 (a tire never gives more than C alpha),
    from :func:`score_signature` on the signature of :func:`propagate_tire_bias`. unpinned = what is left
    to the reach (reach - share)^2, if positive, + the posterior variance + (FIRST_ORDER_ERROR x share)^2.
    The reach is a tire at ``min_friction`` (1), or the measure's upper bound (estimate +
    SATURATION_REACH_SIGMAS std) where the data exclude that tire: the band never leaves out the bias of
    the most slippery surface the data allow, as with the measure off (0, 1). With
    ``saturation_correction`` (the field's friction known): (1, 1).
    """
    if settings[S_SATURATION_CORRECTION] > 0.5:
        return 1.0, 1.0
    prior = settings[S_SATURATION_PRIOR]
    information = memo[M_SATURATION_INFORMATION]
    if not (prior > 0.0 and information > 0.0):
        return 0.0, 1.0
    variance = 1.0 / (information + 1.0 / (prior * prior))
    score = memo[M_SATURATION_SCORE]
    share = max(score * variance, 0.0)  # the mode under a >= 0: never more force than C alpha
    reach = min(1.0, (max(score, 0.0) + SATURATION_REACH_SIGMAS * math.sqrt(information)) / information)
    left = max(reach - share, 0.0)
    return share, left * left + variance + (FIRST_ORDER_ERROR * share) ** 2
