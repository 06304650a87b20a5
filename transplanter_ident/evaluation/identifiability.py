"""Which combination of Cf and Cr the data pin down, from the covariance of (ln Cf, ln Cr).

The eigen-decomposition of the 2x2 covariance of the log stiffnesses (the filter's P block, or the
inverse Fisher information of :mod:`.cramer_rao`; DESIGN.md section 7, "Identifiability"): the
1-sigma of the overall scale sqrt(Cf Cr) and of the ratio Cf / Cr, and the weakest direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Identifiability:
    """Which combination of the stiffnesses the data pin down (from the covariance of ln Cf, ln Cr).

    At 1 m/s on a held step the overall scale is nearly unknown while the ratio Cf/Cr is sharp; a
    controller that needs only the ratio (the understeer gradient's sign) can still use it.
    """

    scale_std: float  # relative 1-sigma of sqrt(Cf Cr), the overall stiffness scale
    ratio_std: float  # relative 1-sigma of Cf / Cr
    weak_direction: tuple[float, float]  # unit vector in (ln Cf, ln Cr) of the largest uncertainty
    weak_std: float  # 1-sigma along it
    condition: float  # largest / smallest variance

    @classmethod
    def of(cls, rel_front: float, rel_rear: float, correlation: float) -> Identifiability:
        """From the relative 1-sigma of Cf and Cr (= the 1-sigma of their logs) and their correlation."""
        a, b = rel_front ** 2, rel_rear ** 2
        c = correlation * rel_front * rel_rear
        half_trace, det = 0.5 * (a + b), a * b - c * c
        spread = math.sqrt(max(half_trace ** 2 - det, 0.0))
        big, small = half_trace + spread, max(half_trace - spread, 0.0)
        vector = (c, big - a) if abs(c) > 1e-300 else ((1.0, 0.0) if a >= b else (0.0, 1.0))
        norm = math.hypot(*vector)
        return cls(scale_std=0.5 * math.sqrt(max(a + b + 2.0 * c, 0.0)), ratio_std=math.sqrt(max(a + b - 2.0 * c, 0.0)),
                   weak_direction=(vector[0] / norm, vector[1] / norm), weak_std=math.sqrt(big),
                   condition=big / small if small > 0.0 else math.inf)

    def describe(self) -> str:
        return (f"scale sqrt(Cf Cr) +- {100 * self.scale_std:.2g} %, ratio Cf/Cr +- {100 * self.ratio_std:.2g} %; "
                f"weakest along ({self.weak_direction[0]:+.2f}, {self.weak_direction[1]:+.2f}) in (ln Cf, ln Cr), "
                f"1-sigma {100 * self.weak_std:.2g} %")
