"""The step's output row (layout.O_*): the motion states, Cf and Cr with the biases their std holds.

Cf, Cr are the stiffness states (paper eqs. 9-12's parameters, ``stiffness`` maps ln C or C) plus the
saturating tire's share of its bias (:func:`.adaptation.saturation_share`); their std holds P's
variance and the biases a configuration may leave out (:func:`.adaptation.held_bias_variance`). Then
the steering offset b, its gain's error g and the heading's misalignment h with their std, the Cf-Cr correlation, the
model's open-loop vy and r, and the measures of :mod:`.measure_outputs`.
"""

from __future__ import annotations

import math

from transplanter_ident.ekf.adaptation import held_bias_variance, saturation_share
from transplanter_ident.ekf.layout import (
    M_BIAS,
    O_CF,
    O_CF_STD,
    O_CORRELATION,
    O_HEADING_OFFSET,
    O_HEADING_OFFSET_STD,
    O_OFFSET,
    O_OFFSET_STD,
    O_R,
    O_R_MODEL,
    O_STATUS,
    O_STEERING_GAIN,
    O_STEERING_GAIN_STD,
    O_TIRE_BIAS_F,
    O_VY,
    O_VY_MODEL,
    X_R,
    X_VY,
)
from transplanter_ident.ekf.measure_outputs import write_measures, write_sensitivities
from transplanter_ident.jit import called_kernel


def make_outputs(nd, stiffness):  # noqa: ANN001, ANN201
    """``write_outputs(x, p, memo, settings, status, r_model, vy_model, out)`` for nd motion states.

    The parameter states follow the motion states: theta_f, theta_r, b, g, h at nd .. nd + 4.
    ``stiffness(x, settings, k)``: (C, dC/dtheta) of axle k (:func:`.prediction.make_prediction`).
    """
    nf, nr, nb, ng, nh = nd, nd + 1, nd + 2, nd + 3, nd + 4

    @called_kernel
    def write_outputs(x, p, memo, settings, status, r_model, vy_model, out):
        out[O_STATUS] = status.value
        out[O_VY] = x[X_VY]
        out[O_R] = x[X_R]
        share, unpinned = saturation_share(memo, settings)  # of the bias at min_friction (adaptation.py)
        for k in range(2):  # front, rear; the std holds the saturation, delay and steering gain biases
            c, dc = stiffness(x, settings, k)
            bias = memo[M_BIAS + nf + k]
            out[O_CF + k] = c + dc * share * bias
            held = held_bias_variance(memo, settings, nf + k, unpinned)
            out[O_CF_STD + k] = dc * math.sqrt(max(p[nf + k, nf + k], 0.0) + held)
            out[O_TIRE_BIAS_F + k] = dc * bias / c if c != 0.0 else 0.0
            write_sensitivities(memo, nf + k, k, c, dc, out)  # to a delay, a gain, a relaxation, a heading
        out[O_OFFSET] = x[nb]
        out[O_OFFSET_STD] = math.sqrt(max(p[nb, nb], 0.0))
        denominator = math.sqrt(max(p[nf, nf], 0.0) * max(p[nr, nr], 0.0))
        out[O_CORRELATION] = p[nf, nr] / denominator if denominator > 0.0 else 0.0
        out[O_VY_MODEL] = vy_model
        out[O_R_MODEL] = r_model
        write_measures(memo, settings, out)
        out[O_HEADING_OFFSET] = x[nh]
        out[O_HEADING_OFFSET_STD] = math.sqrt(max(p[nh, nh], 0.0))
        out[O_STEERING_GAIN] = x[ng]
        out[O_STEERING_GAIN_STD] = math.sqrt(max(p[ng, ng], 0.0))

    return write_outputs
