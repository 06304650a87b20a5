"""Beyond the paper: a steering play left out of ``vehicle.steering_play``, measured from the innovations.

A linkage with a free travel p between the steering sensor and the wheels (:mod:`..epochs.steering_play`)
puts the sensor p/2 ahead of the wheels towards the motion (p > 0; p < 0: behind them), so the true
wheel angle is the filter's minus (p/2) d, with d the direction the steering moves: a steering offset of
+(p/2) d over the interval, a square wave in phase with the steering rate. 0.1 deg left out moves Cf by
about 10 % at 2 m/s while the estimate stays valid (docs/robustness.md).

Per radian of play the offset is d / 2, d = the interval's steering rate over ``PLAY_RATE``, clipped to
+-1 (a held wheel moves no linkage). :func:`.adaptation.propagate_bias` carries it through the filter's F
and K (the stiffness and the offset take up what they can), which gives the innovation per radian that
the rest leaves; :func:`.adaptation.score_signature` fits the innovations to it (O_PLAY_ESTIMATE, its std;
memory ``ekf.saturation_memory``, as the other constant errors), and the stiffness's share per radian is
the sensitivity O_PLAY_SENS_F/R. The validity tests both, as for a GNSS delay
(evaluation/model_errors.py); ``ekf.steering_play_uncertainty`` holds that share of a play's 1-sigma in
the band (adaptation.held_bias_variance), as for the steering gain.
"""

from __future__ import annotations

from transplanter_ident.ekf.adaptation import propagate_bias
from transplanter_ident.ekf.layout import M_PLAY_BIAS
from transplanter_ident.jit import inline_kernel

#: rad/s: the steering rate from which the linkage is taken to lie against one side of its play
PLAY_RATE = 0.02


@inline_kernel
def propagate_play_bias(memo, n, nd, h1, updated, steering_rate, ws):
    """The estimate's first-order bias per radian of steering play left out (memo M_PLAY_BIAS); returns H b."""
    direction = min(max(steering_rate / PLAY_RATE, -1.0), 1.0)
    return propagate_bias(memo, M_PLAY_BIAS, n, nd, h1, updated, 0.0, 0.0, 0.5 * direction, ws)
