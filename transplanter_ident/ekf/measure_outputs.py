"""The step's measures of what the configuration left out, as output columns (DESIGN.md section 7).

:func:`score_measures` fits each updated epoch's innovations to the signatures of the constant errors
(:func:`.adaptation.score_signature`). Every epoch, from what the step remembers (memo): the model
errors the innovations show (:func:`.adaptation.signature_estimate`: a GNSS delay, the tires'
saturation, a relaxation length, a steering gain, a heading misalignment, a steering play), the factors
on R and the innovations' correlation in time, and the directional change test's evidence; and
(:func:`write_sensitivities`, with Cf and Cr, :mod:`.outputs`) the stiffness's own sensitivity to
each error.
"""

from __future__ import annotations

from transplanter_ident.ekf.adaptation import noise_scale, score_signature, signature_estimate
from transplanter_ident.ekf.change import write_change_evidence
from transplanter_ident.ekf.layout import (
    M_DELAY_BIAS,
    M_DELAY_INFORMATION,
    M_DELAY_SCORE,
    M_HEADING_BIAS,
    M_HEADING_INFORMATION,
    M_HEADING_SCORE,
    M_NOISE_SECOND,
    M_NOISE_SPAN_SECOND,
    M_NOISE_SPAN_VY,
    M_NOISE_VY,
    M_PLAY_BIAS,
    M_PLAY_INFORMATION,
    M_PLAY_SCORE,
    M_RELAXATION_BIAS,
    M_RELAXATION_INFORMATION,
    M_RELAXATION_SCORE,
    M_SATURATION_INFORMATION,
    M_SATURATION_SCORE,
    M_SCALE_BIAS,
    M_SCALE_INFORMATION,
    M_SCALE_SCORE,
    O_DELAY_ESTIMATE,
    O_DELAY_ESTIMATE_STD,
    O_DELAY_SENS_F,
    O_HEADING_ESTIMATE,
    O_HEADING_ESTIMATE_STD,
    O_HEADING_SENS_F,
    O_NOISE_CORRELATION_SECOND,
    O_NOISE_CORRELATION_VY,
    O_NOISE_SCALE_SECOND,
    O_NOISE_SCALE_VY,
    O_PLAY_ESTIMATE,
    O_PLAY_ESTIMATE_STD,
    O_PLAY_SENS_F,
    O_RELAXATION,
    O_RELAXATION_SENS_F,
    O_RELAXATION_STD,
    O_SATURATION,
    O_SATURATION_STD,
    O_SCALE_ESTIMATE,
    O_SCALE_ESTIMATE_STD,
    O_SCALE_SENS_F,
    S_SATURATION_MEMORY,
)
from transplanter_ident.ekf.noise_correlation import correlations
from transplanter_ident.jit import inline_kernel


@inline_kernel
def score_measures(memo, settings, dt, lag0, gain0, gain1, head0, head1, play0, play1, e0, e1, s00, s01, s11, det):
    """One updated epoch's innovations fitted to the relaxation's (vy alone), the gain's, heading's and play's signatures."""
    memory = settings[S_SATURATION_MEMORY]
    score_signature(memo, M_RELAXATION_SCORE, M_RELAXATION_INFORMATION, memory, dt, lag0, 0.0, e0, 0.0, s00, 0.0, 1.0,
                    s00)  # relaxation_signature.py
    score_signature(memo, M_SCALE_SCORE, M_SCALE_INFORMATION, memory, dt, gain0, gain1, e0, e1, s00, s01, s11, det)
    score_signature(memo, M_HEADING_SCORE, M_HEADING_INFORMATION, memory, dt, head0, head1, e0, e1, s00, s01, s11, det)
    score_signature(memo, M_PLAY_SCORE, M_PLAY_INFORMATION, memory, dt, play0, play1, e0, e1, s00, s01, s11, det)


@inline_kernel
def write_measures(memo, settings, out):
    """The measures' output columns (layout.O_*) from memo: each a value and its std (0: not measured yet)."""
    out[O_DELAY_ESTIMATE], out[O_DELAY_ESTIMATE_STD] = signature_estimate(memo, M_DELAY_SCORE, M_DELAY_INFORMATION)
    out[O_SATURATION], out[O_SATURATION_STD] = signature_estimate(memo, M_SATURATION_SCORE, M_SATURATION_INFORMATION)
    out[O_RELAXATION], out[O_RELAXATION_STD] = signature_estimate(memo, M_RELAXATION_SCORE, M_RELAXATION_INFORMATION)
    out[O_SCALE_ESTIMATE], out[O_SCALE_ESTIMATE_STD] = signature_estimate(memo, M_SCALE_SCORE, M_SCALE_INFORMATION)
    out[O_HEADING_ESTIMATE], out[O_HEADING_ESTIMATE_STD] = signature_estimate(memo, M_HEADING_SCORE,
                                                                              M_HEADING_INFORMATION)
    out[O_PLAY_ESTIMATE], out[O_PLAY_ESTIMATE_STD] = signature_estimate(memo, M_PLAY_SCORE, M_PLAY_INFORMATION)
    out[O_NOISE_SCALE_VY] = noise_scale(memo, settings, M_NOISE_VY, M_NOISE_SPAN_VY)
    out[O_NOISE_SCALE_SECOND] = noise_scale(memo, settings, M_NOISE_SECOND, M_NOISE_SPAN_SECOND)
    out[O_NOISE_CORRELATION_VY], out[O_NOISE_CORRELATION_SECOND] = correlations(memo, settings)
    write_change_evidence(memo, settings, out)


@inline_kernel
def write_sensitivities(memo, i, k, c, dc, out):
    """Cf's (k = 0) or Cr's (k = 1) relative error (estimate - truth) per unit of each model error left out.

    From the first-order bias of its state i (memo, adaptation.carry_bias); c the stiffness, dc = dC/dtheta.
    """
    if c == 0.0:
        return
    out[O_DELAY_SENS_F + k] = -dc * memo[M_DELAY_BIAS + i] / c
    out[O_SCALE_SENS_F + k] = -dc * memo[M_SCALE_BIAS + i] / c
    out[O_RELAXATION_SENS_F + k] = -dc * memo[M_RELAXATION_BIAS + i] / c
    out[O_HEADING_SENS_F + k] = -dc * memo[M_HEADING_BIAS + i] / c
    out[O_PLAY_SENS_F + k] = -dc * memo[M_PLAY_BIAS + i] / c
