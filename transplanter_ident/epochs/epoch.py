"""One GNSS epoch at the CG (the filter's input, z of paper eq. 7), a sequence of them, a rejection."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np


@dataclass(frozen=True)
class Epoch:
    """One GNSS epoch at the CG, with the inputs held over the interval that ends at ``t``."""

    t: float  # s
    longitudinal_velocity: float  # vx at t, m/s
    lateral_velocity: float  # vy at t, m/s
    heading: float  # psi at t, unwrapped ENU yaw, rad
    yaw_rate: float  # interval-mean r from heading increments, rad/s
    steering: float  # interval-mean front steering angle, rad
    steering_rate: float  # slope of the steering over the interval, rad/s
    speed: float  # interval-mean vx, m/s
    #: vy of the GNSS antenna in body axes at t, m/s: what the filter measures (h = vy + antenna_x r);
    #: ``lateral_velocity`` is the CG value from the interval-mean r, for display. None: the same.
    antenna_lateral_velocity: float | None = None
    #: the variances the GNSS messages report (0: not given, as in ROS), for ekf.measurement_noise_from_covariance:
    velocity_variance: float = 0.0  # of antenna_lateral_velocity, (m/s)^2
    heading_variance: float = 0.0  # of heading, rad^2
    yaw_rate_variance: float = 0.0  # of yaw_rate (two headings over the interval), (rad/s)^2

    def __post_init__(self) -> None:
        if self.antenna_lateral_velocity is None:
            object.__setattr__(self, "antenna_lateral_velocity", self.lateral_velocity)


class EpochArrays:
    """A sequence of epochs as columns (replay, tuner)."""

    def __init__(self, epochs: Sequence[Epoch] | None = None) -> None:
        names = [f.name for f in fields(Epoch)]
        data = np.array([[getattr(e, n) for n in names] for e in epochs or []], dtype=np.float64)
        self._data = data.reshape(-1, len(names))
        for i, name in enumerate(names):
            setattr(self, name, self._data[:, i])

    @classmethod
    def from_rows(cls, rows: np.ndarray) -> EpochArrays:
        """From an n x (number of Epoch fields) array, columns in the field order (the batch assembler)."""
        arrays = cls()
        arrays._data = np.ascontiguousarray(rows, dtype=np.float64).reshape(-1, len(fields(Epoch)))
        for i, f in enumerate(fields(Epoch)):
            setattr(arrays, f.name, arrays._data[:, i])
        return arrays

    def rows(self) -> np.ndarray:
        """A copy of the n x (number of Epoch fields) array, columns in the field order (:meth:`from_rows`)."""
        return self._data.copy()

    def __len__(self) -> int:
        return self._data.shape[0]

    def __getitem__(self, index: int) -> Epoch:
        return Epoch(*map(float, self._data[index]))

    def column(self, name: str) -> np.ndarray:
        """One field of every epoch, by its Epoch field name."""
        return getattr(self, name)


@dataclass(frozen=True)
class Rejection:
    """A sample that was not used, and why (DESIGN.md section 6).

    ``kind`` is the class of the reason (:mod:`.checks`: ``stamp_jump``, ``speed_limit``, ...): the
    diagnostics count rejections per kind, and a log throttle keyed by it stays bounded whatever
    numbers the reason text carries.
    """

    topic: str  # "velocity" | "heading" | "steering" | "epoch"
    stamp: float
    reason: str
    kind: str = "other"
