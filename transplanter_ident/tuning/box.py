"""The search space of the optimisers: a box of lower and upper bounds (paper eq. 22's log10 ranges)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Box:
    """The search box: lower[d] <= x[d] <= upper[d]."""

    lower: tuple[float, ...]
    upper: tuple[float, ...]
    names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if len(self.lower) != len(self.upper) or not self.lower:
            raise ValueError("box: lower and upper must be non-empty and of equal length")
        if self.names and len(self.names) != len(self.lower):
            raise ValueError("box: one name per dimension")
        for low, high in zip(self.lower, self.upper, strict=True):
            if not (math.isfinite(low) and math.isfinite(high) and low < high):
                raise ValueError(f"box: need finite lower < upper, got [{low}, {high}]")

    @property
    def dimension(self) -> int:
        """D, the number of dimensions."""
        return len(self.lower)

    @property
    def low(self) -> np.ndarray:
        """Lower bounds as an array."""
        return np.asarray(self.lower, dtype=np.float64)

    @property
    def high(self) -> np.ndarray:
        """Upper bounds as an array."""
        return np.asarray(self.upper, dtype=np.float64)

    @property
    def width(self) -> np.ndarray:
        """Width per dimension, upper - lower."""
        return self.high - self.low

    def clip(self, x: np.ndarray) -> np.ndarray:
        """The points ``x`` clipped into the box."""
        return np.clip(x, self.low, self.high)

    def uniform(self, rng: np.random.Generator, count: int) -> np.ndarray:
        """``count`` points uniformly distributed in the box."""
        return self.low + rng.random((count, self.dimension)) * self.width

    @classmethod
    def cube(cls, dimension: int, low: float, high: float) -> Box:
        """[low, high]^dimension."""
        return cls((float(low),) * dimension, (float(high),) * dimension)
