"""The Cramér-Rao bound of the stiffness from one drive, and how the filter's sigma compares (issue #11).

:func:`cramer_rao_bound` sums the output-error Fisher information of (ln Cf, ln Cr, b) at an
estimate (:mod:`transplanter_ident.ekf.information`) and inverts it. With the steering offset
estimated, the offset is a nuisance parameter: the bound of (ln Cf, ln Cr) is the 2 x 2 block of
the inverse of the full 3 x 3 information; with a fixed offset, the inverse of the 2 x 2 block.

The bound is local: it is the curvature of the likelihood at the estimate. Where the data hardly
pin the stiffness (the paper's slow held step), it depends strongly on where it is evaluated, so
it tells which direction is weak rather than how far off a wrong estimate is. A filter sigma
well below the bound means the filter claims more than the data hold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.ekf.identifiability import (
    SEGMENT,
    nuisances,
    stiffness_information,
    window_information,
)
from transplanter_ident.ekf.joint_ekf import kernel_input
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD, O_OFFSET, O_STEERING_GAIN
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.identifiability import Identifiability


@dataclass(frozen=True)
class CramerRaoBound:
    """The bound of (ln Cf, ln Cr) at an estimate: its covariance and how many epochs gave information."""

    covariance: np.ndarray  # (2, 2): (ln Cf, ln Cr); the relative variances of Cf and Cr
    epochs: int

    @property
    def relative_std(self) -> tuple[float, float]:
        """1-sigma of ln Cf and ln Cr, i.e. the relative 1-sigma of Cf and Cr."""
        return math.sqrt(max(self.covariance[0, 0], 0.0)), math.sqrt(max(self.covariance[1, 1], 0.0))

    @property
    def identifiability(self) -> Identifiability:
        front, rear = self.relative_std
        denominator = front * rear
        correlation = float(self.covariance[0, 1] / denominator) if denominator > 0.0 else 0.0
        return Identifiability.of(front, rear, max(-1.0, min(1.0, correlation)))

    def describe(self, filter_relative_std: tuple[float, float]) -> str:
        """One line: the bound, the filter's sigma as a multiple of it, and the weak direction."""
        front, rear = self.relative_std
        ratios = [f"{s / b:.2g}x" if b > 0.0 else "-" for s, b in zip(filter_relative_std, (front, rear), strict=True)]
        return (f"Cramér-Rao bound at the final estimate ({self.epochs} epochs, output error over {SEGMENT:g} s "
                f"segments): Cf +- {100 * front:.3g} %, Cr +- {100 * rear:.3g} %; the published 1-sigma is "
                f"{ratios[0]} / {ratios[1]} of it; {self.identifiability.describe()}")


def cramer_rao_bound(config: EstimatorConfig, epochs: EpochArrays, cornering_stiffness: tuple[float, float],  # noqa: PLR0913
                     steering_offset: float, segment: float = SEGMENT, steering_gain: float = 0.0) -> CramerRaoBound | None:
    """The bound at (Cf, Cr, offset, gain error) from these epochs; None in yaw_rate mode or without information."""
    options = config.options
    if not options.heading_state or len(epochs) < 2 or min(cornering_stiffness) <= 0.0:
        return None
    theta = np.array([math.log(cornering_stiffness[0]), math.log(cornering_stiffness[1]), steering_offset,
                      steering_gain])
    information, used = window_information(config, kernel_input(epochs), theta, segment)
    return bound_from_information(information, nuisances(options), used) if used > 0 else None


def bound_from_information(information: np.ndarray, nuisance: tuple[int, ...], epochs: int) -> CramerRaoBound | None:
    """The bound of (ln Cf, ln Cr) from the (4, 4) information of (ln Cf, ln Cr, b, g); None while singular.

    ``nuisance``: the information's indices taken out (:func:`.identifiability.nuisances`).
    """
    pinned = stiffness_information(information, nuisance)
    if not np.all(np.isfinite(pinned)) or np.linalg.det(pinned) <= 0.0:
        return None
    covariance = np.linalg.inv(pinned)
    if not (np.all(np.isfinite(covariance)) and covariance[0, 0] > 0.0 and covariance[1, 1] > 0.0):
        return None
    return CramerRaoBound(covariance, int(epochs))


def final_bound_line(config: EstimatorConfig, epochs: EpochArrays, final_row: np.ndarray) -> str:
    """The line replay and tuner print for a bag: the bound at the filter's final estimate (an output row)."""
    stiffness = (float(final_row[O_CF]), float(final_row[O_CR]))
    bound = cramer_rao_bound(config, epochs, stiffness, float(final_row[O_OFFSET]),
                             steering_gain=float(final_row[O_STEERING_GAIN]))
    if bound is None:
        why = "yaw_rate mode" if not config.options.heading_state else "no informative epochs"
        return f"Cramér-Rao bound: not computed ({why})"
    return bound.describe((float(final_row[O_CF_STD]) / stiffness[0], float(final_row[O_CR_STD]) / stiffness[1]))
