"""Beyond the paper: two CUSUM tests for a stiffness change (a new surface; DESIGN.md section 7).

* the variance test: the log-likelihood ratio of the innovations' covariance scaled by
  ``ekf.change_scale`` against as modelled, from the NIS (chi^2 with 2 degrees of freedom),
  l = -ln s + NIS (1 - 1/s) / 2;
* the directional test: each stiffness update normalised by its own std,
  u = d theta / sqrt(P^-_thth - P^+_thth), is N(0, 1) while the model holds (the update K e has
  covariance K S K^T = P^- - P^+). On a new surface the updates keep pushing one way. Two one-sided
  CUSUMs per stiffness test a mean shift of +-``ekf.change_shift`` (delta): l = delta (|u| - delta / 2)
  in the shift's direction. Through sensors noisier than the default, a 40 % drop barely raises
  the innovations' variance while the estimate follows it at the random walk's pace; its updates
  show it within seconds. GNSS errors correlated over a few epochs (a receiver's own filter) make
  the updates so too (lag-1 correlation rho ~0.6 at 0.5 s), and sums of them grow faster than the
  test assumes: each u is scaled by sqrt((1 - rho) / (1 + rho)), the long-run std of an AR(1) series,
  with rho = E[u_k u_k-1] / E[u^2] measured over ``ekf.noise_memory`` (uncentred, from 0 and 1).
  A second pair per stiffness tests a smaller shift, ``ekf.change_ramp_shift``, to its own alarm level
  ``ekf.change_ramp_threshold``: a surface that changes over a minute lets the estimate lag by several
  std while each update pushes it by only ~0.3 of its std, which the step's shift never sums to an alarm
  (a 30 % rise over 60 s at 2 m/s: up to 13 % behind for a minute, 29 % of the valid epochs outside +-2 sigma
  without this test; docs/real_sensors.md, *A slow change*).

Either sum past its threshold is an alarm: for ``change_hold`` s the stiffness random walk runs at
``change_process_noise``, so the estimate moves to the new surface over several epochs rather than
one large, badly linearised step; the tires' saturation is measured anew and all sums restart.
Each epoch adds at most half its test's threshold: one outlier alone never raises an alarm.

Halfway to an alarm already counts (:func:`write_change_evidence`, the validity's "change suspected"):
an estimate that lags a new surface by more than its band is not published as valid while the
test gathers the rest.

The decorrelated updates also go out (layout.O_UPDATE_F/R; 0 at an alarm and while the raised
density lasts) for the validity's drift test, which sums them over a longer span: a stiffness that
drifts, rather than steps, keeps them pushing one way by less than the directional test's shift.
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.layout import (
    M_ADAPT_UNTIL,
    M_CUSUM,
    M_SATURATION_INFORMATION,
    M_SATURATION_SCORE,
    M_SHIFT,
    M_SHIFT_LAG,
    M_SHIFT_LAST,
    M_SHIFT_POWER,
    N_SHIFT,
    N_SHIFT_SUMS,
    O_CHANGE,
    O_CHANGE_EVIDENCE,
    O_CUSUM,
    O_UPDATE_F,
    O_UPDATE_R,
    S_CHANGE_HOLD,
    S_CUSUM_CAP,
    S_CUSUM_SCALE,
    S_CUSUM_THRESHOLD,
    S_NOISE_MEMORY,
    S_RAMP_SHIFT,
    S_RAMP_THRESHOLD,
    S_SHIFT,
    S_SHIFT_THRESHOLD,
)
from transplanter_ident.jit import inline_kernel


@inline_kernel
def normalised_update(before, after, variance_before, variance_after):
    """The update (after - before) / sqrt(P^- - P^+) of one stiffness state; 0 where the step did not update it."""
    reduction = variance_before - variance_after
    return (after - before) / math.sqrt(reduction) if reduction > 0.0 else 0.0


#: the largest lag-1 correlation of the updates the scaling takes
MAX_CORRELATION = 0.95


@inline_kernel
def decorrelated(memo, k, u, weight):
    """The update u of stiffness k scaled to its long-run std by the updates' lag-1 correlation (moments over ``weight``)."""
    memo[M_SHIFT_POWER + k] += weight * (u * u - 1.0 - memo[M_SHIFT_POWER + k])
    memo[M_SHIFT_LAG + k] += weight * (u * memo[M_SHIFT_LAST + k] - memo[M_SHIFT_LAG + k])
    memo[M_SHIFT_LAST + k] = u
    power = 1.0 + memo[M_SHIFT_POWER + k]
    rho = min(max(memo[M_SHIFT_LAG + k] / power, 0.0), MAX_CORRELATION) if power > 0.0 else 0.0
    return u * math.sqrt((1.0 - rho) / (1.0 + rho))


@inline_kernel
def shift_test(settings, k):
    """Test k's (0: the step's, 1: the slow change's) shift delta and alarm level (delta 0: the test is off)."""
    if k == 0:
        return settings[S_SHIFT], settings[S_SHIFT_THRESHOLD]
    return settings[S_RAMP_SHIFT], settings[S_RAMP_THRESHOLD]


@inline_kernel
def shift_alarm(memo, settings, dt, u_f, u_r, out):
    """Add this epoch's updates to the directional CUSUMs; True if one passed its test's alarm level.

    The decorrelated updates go to out[O_UPDATE_F], out[O_UPDATE_R].
    """
    weight = min(1.0, dt / settings[S_NOISE_MEMORY])
    scaled_f, scaled_r = decorrelated(memo, 0, u_f, weight), decorrelated(memo, 1, u_r, weight)
    out[O_UPDATE_F], out[O_UPDATE_R] = scaled_f, scaled_r
    alarm = False
    for i in range(N_SHIFT):  # per test: Cf up, Cf down, Cr up, Cr down
        delta, threshold = shift_test(settings, i // N_SHIFT_SUMS)
        if delta <= 0.0:
            continue
        u = scaled_f if i % N_SHIFT_SUMS < 2 else scaled_r
        if i % 2 == 1:
            u = -u
        g = max(0.0, memo[M_SHIFT + i] + min(delta * (u - 0.5 * delta), 0.5 * threshold))
        memo[M_SHIFT + i] = g
        alarm = alarm or g > threshold
    return alarm


@inline_kernel
def write_change_evidence(memo, settings, out):
    """out[O_CHANGE_EVIDENCE]: the directional tests' largest CUSUM as a fraction of its test's alarm level."""
    largest = 0.0
    for i in range(N_SHIFT):
        largest = max(largest, memo[M_SHIFT + i] / shift_test(settings, i // N_SHIFT_SUMS)[1])
    out[O_CHANGE_EVIDENCE] = largest


@inline_kernel
def detect_change(memo, settings, t, dt, nis, u_f, u_r, out):
    """Both tests on one updated epoch (NIS, and the normalised updates u_f, u_r); an alarm as the module says."""
    scale = settings[S_CUSUM_SCALE]
    llr = min(-math.log(scale) + 0.5 * nis * (1.0 - 1.0 / scale), settings[S_CUSUM_CAP])
    g = max(0.0, memo[M_CUSUM] + llr)
    adapting = t <= memo[M_ADAPT_UNTIL]
    alarm = shift_alarm(memo, settings, dt, u_f, u_r, out) or g > settings[S_CUSUM_THRESHOLD]
    if adapting or alarm:  # the catch-up after an alarm is no drift
        out[O_UPDATE_F], out[O_UPDATE_R] = 0.0, 0.0
    if alarm:  # a new surface: the tire's saturation is measured anew
        memo[M_ADAPT_UNTIL] = t + settings[S_CHANGE_HOLD]
        memo[M_SATURATION_SCORE] = 0.0
        memo[M_SATURATION_INFORMATION] = 0.0
        out[O_CHANGE] = 1.0
        g = 0.0
        for i in range(N_SHIFT):
            memo[M_SHIFT + i] = 0.0
    memo[M_CUSUM] = g
    out[O_CUSUM] = g
