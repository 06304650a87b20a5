"""Beyond the paper: a heading misaligned with the vehicle, left out of ``vehicle.heading_offset``, measured.

A dual-antenna heading is the yaw of the antenna baseline; ``vehicle.heading_offset`` turns it into the
vehicle's. A baseline mounted delta (rad) off that (a bracket turned by a degree) makes the heading
psi + delta, and the body-frame velocity the assembler turns with it has the lateral component

    vy_antenna ~ vy + antenna_x r - vx delta      (to first order in delta),

a steady lateral velocity proportional to the speed that no motion of eq. 4 gives (a straight run at
r = 0 has vy = 0 whatever the stiffness or the steering offset). The heading's own offset is taken up
by the heading state at once (it integrates r from the first measured heading), so only the vy
measurement carries it. At 2 m/s 1 deg is 0.035 m/s, about the default R's 1-sigma: the innovations
then look like GNSS noisier than R, which the validity named before this measure existed.

Per unit of delta the measurement bias is m0 = -vx on the vy innovation and nothing on the second;
:func:`.adaptation.carry_bias` carries it through the filter's F and K (the motion states and the
stiffness take up what they can), which gives the innovation per radian the rest leaves.
:func:`.adaptation.score_signature` fits the innovations to it (O_HEADING_ESTIMATE, its std; memory
``ekf.saturation_memory``, as the other constant errors), and the stiffness's share per radian is the
sensitivity O_HEADING_SENS_F/R. The validity tests both, as for a GNSS delay (evaluation/model_errors.py).
The step runs it only with ``ekf.estimate_heading_offset`` false: else delta is the filter's state h
(:mod:`.measurement_row`), and nothing is left for the measure.
"""

from __future__ import annotations

from transplanter_ident.ekf.adaptation import carry_bias
from transplanter_ident.ekf.layout import B_DIRECT, M_HEADING_BIAS, W_BIAS
from transplanter_ident.jit import inline_kernel


@inline_kernel
def propagate_heading_bias(memo, n, nd, h1, updated, speed, ws):
    """The estimate's first-order bias per radian of heading misalignment (memo M_HEADING_BIAS).

    The prediction misses no motion (ws[W_BIAS, B_DIRECT] zero); the vy measurement is -speed off per
    radian. Returns the innovation per radian of the prediction: H b - speed, and H1 b.
    """
    for i in range(nd):
        ws[W_BIAS, B_DIRECT, i] = 0.0
    return carry_bias(memo, M_HEADING_BIAS, n, nd, h1, updated, B_DIRECT, ws, -speed)
