"""The validity decision's hysteresis (DESIGN.md section 7), one kernel for the monitor and the batch.

Valid only after every check held for ``hold_on`` s; invalid once any failed for ``hold_off`` s, at
once for a hard (plausibility or bound) failure. :class:`~.validity.ValidityMonitor` calls
:func:`hysteresis_step` once per epoch, :func:`~.validity_batch.decide_batch`'s kernel in its loop.

state (N_HYSTERESIS,) float: [valid (0 or 1), good since (s), bad since (s)], indexed by layout.H_*;
NaN for a time not set (:func:`initial_state`).
"""

from __future__ import annotations

import numpy as np

from transplanter_ident.ekf.layout import H_BAD_SINCE, H_GOOD_SINCE, H_VALID, N_HYSTERESIS
from transplanter_ident.jit import entry_kernel


def initial_state() -> np.ndarray:
    """Not valid, no check held or failed yet."""
    state = np.full(N_HYSTERESIS, np.nan)
    state[H_VALID] = 0.0
    return state


@entry_kernel(runtime=False)
def hysteresis_step(state, t, hard, failing, hold_on, hold_off):  # noqa: ANN001, ANN201
    """The decision after the epoch at ``t`` (``failing``: a check failed, ``hard``: a hard one); updates ``state``."""
    if failing:
        state[H_GOOD_SINCE] = np.nan
        if np.isnan(state[H_BAD_SINCE]):
            state[H_BAD_SINCE] = t
        if hard or t - state[H_BAD_SINCE] >= hold_off:
            state[H_VALID] = 0.0
    else:
        state[H_BAD_SINCE] = np.nan
        if np.isnan(state[H_GOOD_SINCE]):
            state[H_GOOD_SINCE] = t
        if t - state[H_GOOD_SINCE] >= hold_on:
            state[H_VALID] = 1.0
    return state[H_VALID] > 0.5
