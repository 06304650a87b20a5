"""The filter: epochs -> estimates (paper eqs. 4, 9-14, 21).

:mod:`.model` states eq. 4 once and discretises it; :mod:`.kernels` is the compiled EKF step;
:mod:`.entries` its cached per-size entry points; :mod:`.layout` names every array slot;
:mod:`.joint_ekf` is the Python face used by the node, replay and the tuner.
"""

from transplanter_ident.ekf.joint_ekf import (
    Estimate,
    FilterArrays,
    JointEKF,
    run_sequence,
    sequence_objective,
)
from transplanter_ident.ekf.layout import DIVERGENCE_PENALTY, MAE, N_OUTPUTS, NLL, StepStatus

__all__ = [
    "DIVERGENCE_PENALTY", "MAE", "NLL", "N_OUTPUTS", "Estimate", "FilterArrays", "JointEKF", "StepStatus",
    "run_sequence", "sequence_objective",
]
