"""The validity decision's per-epoch checks (DESIGN.md section 7): one set of predicates, online and offline.

Each takes floats (:class:`~.validity.ValidityMonitor`, one epoch) or arrays (:func:`~.validity_batch.decide_batch`,
every epoch of a replay) alike, with numpy's operations, so both decide alike; the model errors'
tests are :mod:`.model_errors`'.

* :func:`pinned`: a stiffness at (within 1 % of) a bound of ``ekf.stiffness_bounds`` (a hard failure);
* :func:`relative_stds`, :func:`unconverged`: the relative 1-sigma of Cf and Cr, the worse beyond
  ``validity.max_rel_std`` (NaN fails);
* :func:`noisier`: the innovations show R's variance x more than ``validity.max_noise_factor``;
* :func:`change_suspected`: the directional change test past ``validity.max_change_evidence`` of its alarm;
* :func:`consistency_nis`: the NIS the window's chi^2 test takes, against R as the innovations show it.
"""

from __future__ import annotations

import numpy as np

from transplanter_ident.config.parameters import ValiditySettings

#: a stiffness within this factor of a bound is pinned there
BOUND_MARGIN = 1.01


def pinned(value, bounds: tuple[float, float]):  # noqa: ANN001, ANN201 - floats or arrays alike
    """Whether a stiffness (N/rad) sits at a bound: a wrong frame, lever arm or steering sign."""
    low, high = bounds
    return (value <= low * BOUND_MARGIN) | (value >= high / BOUND_MARGIN)


def relative_stds(cf, cr, cf_std, cr_std):  # noqa: ANN001, ANN201 - floats or arrays alike
    """(front, rear, worse): the relative 1-sigma of Cf and Cr, and the larger (NaN as Python's ``max`` takes it)."""
    front, rear = cf_std / cf, cr_std / cr
    return front, rear, np.where(rear > front, rear, front)


def unconverged(worst, settings: ValiditySettings):  # noqa: ANN001, ANN201
    """Whether the worse relative 1-sigma is not within ``max_rel_std`` (NaN: not)."""
    return np.logical_not(worst <= settings.max_rel_std)


def noisier(factor_velocity, factor_second, settings: ValiditySettings):  # noqa: ANN001, ANN201
    """Whether the factor on R the innovations show, velocity's or heading's (yaw rate's), passes ``max_noise_factor``."""
    return np.maximum(factor_velocity, factor_second) > settings.max_noise_factor


def change_suspected(evidence, settings: ValiditySettings):  # noqa: ANN001, ANN201
    """Whether the directional change test's CUSUM, over its alarm level, passes ``max_change_evidence``."""
    return evidence > settings.max_change_evidence


def consistency_nis(factor_velocity, factor_second, measured, configured, settings: ValiditySettings):  # noqa: ANN001, ANN201
    """The NIS the window's consistency test takes (window_checks.soft_checks).

    Against R as the innovations show it (layout.O_NIS, ``measured``) where the factors on R are within
    ``max_noise_factor`` (not :func:`noisier`), else against the configured R (O_NIS_CONFIGURED, ``configured``).
    """
    return np.where(np.maximum(factor_velocity, factor_second) <= settings.max_noise_factor, measured, configured)
