"""Beyond the paper: GNSS errors correlated in time widen R (DESIGN.md section 7; eq. 12's R).

The paper's EKF (eqs. 9-14) takes the measurement noise as white. A receiver that smooths its
velocity or heading (its own filter, slow multipath) makes the errors of successive epochs alike,
and the stiffness, read off responses seconds long, then averages far fewer independent errors than
the filter counts: its band is too narrow. For errors of lag-1 autocorrelation rho (a first-order
Gauss-Markov error sampled at the GNSS rate) the spectral density at low frequency is that of white
noise of variance R (1 + rho) / (1 - rho), so each measurement's R is widened by that factor:

* :func:`learn_noise_correlation`: rho of each measurement (vy at the antenna, then psi or r), from
  its innovations normalised by S with R unwidened, w = e / sqrt(S_ii), of successive accepted epochs,
  rho = E[w_k w_k-1] / max(E[w_k^2], 1), over ``ekf.noise_memory`` (a weighted mean, then exponential).
  Against S, not against the innovations' own mean square: a sensor quieter than R leaves innovations
  that are mostly the model's own error while the states converge, correlated but far smaller than S,
  and taken as noise correlated by their own measure they widened R up to 19x (GNSS 4x quieter than
  R, a gentle sine with a 1 deg offset: valid 13 % of the epochs, 67 % white);
* :func:`correlation_factor`: (1 + rho) / (1 - rho), rho within [0, ``MAX_CORRELATION``], 1 until
  ``CORRELATION_SETTLE`` s of pairs were seen or with ``ekf.noise_correlation`` off;
* :func:`learn_noise`: after an accepted epoch, both measures of R (with adaptation.learn_noise_scales);
* :func:`restart_noise_when_near`: the measure of R's variance starts again once the model is near;
* :func:`effective_noise`: R as the step takes it, the configured R times the factor the innovations'
  variance shows (adaptation.noise_scale) times this one.

The factor at zero frequency is conservative: the steering's seconds-long swings see a little less.
White errors give rho ~ 0 +- 1 / sqrt(n) and so a factor of a few percent at most.

R's variance is still matched (adaptation.learn_noise_scales) against S with R unwidened: the
heading's R enters the velocity's S (vx^2 R_psi), and matched against the widened one the velocity's
measured R fell (GNSS 3x noisier than R, one drive: R_psi x80, R_v x1.9, 18 false change alarms).
"""

from __future__ import annotations

from transplanter_ident.ekf.adaptation import DELAY_SETTLE, learn_noise_scales, noise_scale
from transplanter_ident.ekf.layout import (
    M_CORRELATION_LAG,
    M_CORRELATION_LAST,
    M_CORRELATION_LAST_T,
    M_CORRELATION_POWER,
    M_CORRELATION_SPAN,
    M_DELAY_SETTLED,
    M_NOISE_SECOND,
    M_NOISE_SETTLED,
    M_NOISE_SPAN_SECOND,
    M_NOISE_SPAN_VY,
    M_NOISE_VY,
    S_NOISE_CORRELATION,
    S_NOISE_MEMORY,
)
from transplanter_ident.ekf.sequence import innovation_covariance
from transplanter_ident.jit import inline_kernel

#: the largest lag-1 autocorrelation taken (a factor of 19 on R); beyond it the validity's check decides
MAX_CORRELATION = 0.9
#: s of paired epochs before the factor departs from 1 (a few pairs say little)
CORRELATION_SETTLE = 10.0


@inline_kernel
def correlation_of(memo, channel):
    """Rho of one measurement (0: vy, 1: the second) as measured so far: E[w_k w_k-1] / max(E[w^2], 1), in [0, MAX]."""
    power = memo[M_CORRELATION_POWER + channel]
    if not power > 0.0:
        return 0.0
    return min(max(memo[M_CORRELATION_LAG + channel] / max(power, 1.0), 0.0), MAX_CORRELATION)


@inline_kernel
def widening(rho):
    """(1 + rho) / (1 - rho): white noise of R times this has the low-frequency power of R's noise at lag-1 rho."""
    return (1.0 + rho) / (1.0 - rho)


@inline_kernel
def correlation_factor(memo, settings, channel):
    """The factor :func:`widening` on R of one measurement (0: vy, 1: the second); 1 until measured."""
    if settings[S_NOISE_CORRELATION] < 0.5 or memo[M_CORRELATION_SPAN] < CORRELATION_SETTLE:
        return 1.0
    return widening(correlation_of(memo, channel))


@inline_kernel
def correlations(memo, settings):
    """(rho of vy, rho of the second measurement) that widen R now (both 0 with the option off or before they settle)."""
    if correlation_factor(memo, settings, 0) == 1.0 and correlation_factor(memo, settings, 1) == 1.0:
        return 0.0, 0.0
    return correlation_of(memo, 0), correlation_of(memo, 1)


@inline_kernel
def effective_noise(memo, settings, r_vy, r_second):
    """(R of vy, R of the second measurement) as the step takes them, from the configured (or reported) ones."""
    return (r_vy * noise_scale(memo, settings, M_NOISE_VY, M_NOISE_SPAN_VY) * correlation_factor(memo, settings, 0),
            r_second * noise_scale(memo, settings, M_NOISE_SECOND, M_NOISE_SPAN_SECOND)
            * correlation_factor(memo, settings, 1))


@inline_kernel
def learn_noise_correlation(memo, settings, t, dt, e0, e1, s00, s11):
    """One accepted epoch: pair its normalised innovations with the last ones if those were the previous epoch's.

    e0, e1: the innovations; s00, s11: their variances in S with R unwidened. A gated or skipped epoch breaks
    the pairs.
    """
    if settings[S_NOISE_CORRELATION] < 0.5 or not (s00 > 0.0 and s11 > 0.0):
        return
    w0, w1 = e0 / s00 ** 0.5, e1 / s11 ** 0.5
    if memo[M_CORRELATION_LAST_T] >= t - dt - 1.0e-6 and memo[M_CORRELATION_LAST_T] < t:
        span = min(memo[M_CORRELATION_SPAN] + dt, settings[S_NOISE_MEMORY])
        gain = dt / span
        memo[M_CORRELATION_LAG] += gain * (w0 * memo[M_CORRELATION_LAST] - memo[M_CORRELATION_LAG])
        memo[M_CORRELATION_LAG + 1] += gain * (w1 * memo[M_CORRELATION_LAST + 1] - memo[M_CORRELATION_LAG + 1])
        memo[M_CORRELATION_POWER] += gain * (w0 * w0 - memo[M_CORRELATION_POWER])
        memo[M_CORRELATION_POWER + 1] += gain * (w1 * w1 - memo[M_CORRELATION_POWER + 1])
        memo[M_CORRELATION_SPAN] = span
    memo[M_CORRELATION_LAST], memo[M_CORRELATION_LAST + 1] = w0, w1
    memo[M_CORRELATION_LAST_T] = t


@inline_kernel
def learn_noise(memo, settings, heading, t, dt, speed, e0, e1, hph00, hph01, hph11, configured0, configured1,
                velocity, correlation):
    """After an accepted epoch: R's variance as the innovations show it (adaptation.learn_noise_scales) and rho.

    R's variance is matched against S with R unwidened: H P^- H^T (hph*) plus the configured (or reported)
    R (configured0, configured1) times the learned variance factors. With the widened R the heading's share
    of the velocity's S (vx^2 R_psi) would be overstated and the velocity's measured R would fall (GNSS 3x
    noisier than R: R_v x1.9 where it is x9, and false change alarms). rho normalises by that S too.
    ``velocity``: vy's R is learnt too; ``correlation``: rho is (both False while a misaligned heading may hide in
    vy; a course measures no vy, only rho).
    """
    r0 = configured0 * noise_scale(memo, settings, M_NOISE_VY, M_NOISE_SPAN_VY)
    r1 = configured1 * noise_scale(memo, settings, M_NOISE_SECOND, M_NOISE_SPAN_SECOND)
    white00, _, white11 = innovation_covariance(heading, hph00, hph01, hph11, r0, r1, speed)
    learn_noise_scales(memo, settings, dt, e0, e1, white00 - r0, white11 - r1, r0, r1, configured0, configured1,
                       velocity)
    if correlation:
        learn_noise_correlation(memo, settings, t, dt, e0, e1, white00, white11)


@inline_kernel
def restart_noise_when_near(memo, known):
    """After an update: once the model is near (both stiffnesses ``known``, or DELAY_SETTLE s of data), R anew.

    What the innovations showed of R before damped the start (a larger R, a smaller step where the
    linearisation is poor), but it was no sensor's noise: on one drive at 10 Hz the start read the heading's R
    100x too small, and the factor still stood at 6.9 at 30 s, so the estimate was never valid. The measure
    then starts again as at the start (nothing learnt: the configured R), once per run.
    """
    if memo[M_NOISE_SETTLED] > 0.5 or not (known or memo[M_DELAY_SETTLED] >= DELAY_SETTLE):
        return
    for slot in range(M_NOISE_VY, M_NOISE_SPAN_SECOND + 1):
        memo[slot] = 0.0
    memo[M_NOISE_SETTLED] = 1.0
