"""Steering signals, speed profiles and stiffness schedules of the simulated drives.

Steering: sine, step with a ramp (the paper's test), and multisine. Field work pairs a steering
signal with a speed profile: rows with small path-tracking corrections, and headland U-turns
at a lower speed and a large steering angle. The stiffness schedule switches Cf and Cr at given
times (a surface change).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

#: a function of time (array in, array out)
Signal = Callable[[np.ndarray], np.ndarray]



@dataclass(frozen=True)
class SineSteering:
    """delta(t) = amplitude * sin(2 pi t / period), rad."""

    amplitude: float
    period: float

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return self.amplitude * np.sin((2.0 * math.pi / self.period) * np.asarray(t, dtype=float))


@dataclass(frozen=True)
class StepSteering:
    """0 before ``start``, a linear ramp over ``ramp`` seconds, then ``amplitude`` (rad)."""

    amplitude: float
    start: float = 1.0
    ramp: float = 0.5

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        if self.ramp <= 0.0:
            return np.where(t >= self.start, self.amplitude, 0.0)
        return self.amplitude * np.clip((t - self.start) / self.ramp, 0.0, 1.0)


@dataclass(frozen=True)
class MultisineSteering:
    """Sum of sines with the given periods and phases; each has amplitude / n, so |delta| <= amplitude."""

    amplitude: float
    periods: tuple[float, ...]
    phases: tuple[float, ...]

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        out = np.zeros_like(t)
        for period, phase in zip(self.periods, self.phases, strict=True):
            out = out + np.sin((2.0 * math.pi / period) * t + phase)
        return (self.amplitude / len(self.periods)) * out


def sine_steering(amplitude: float, period: float) -> Signal:
    """A sine steer of the given amplitude (rad) and period (s)."""
    require_positive("period", period)
    require_finite("amplitude", amplitude)
    return SineSteering(float(amplitude), float(period))


def step_steering(amplitude: float, start: float = 1.0, ramp: float = 0.5) -> Signal:
    """The paper's step test (20 or 30 degrees), ramped over ``ramp`` s (0 = ideal step)."""
    require_finite("amplitude", amplitude)
    require_finite("start", start)
    if not (math.isfinite(ramp) and ramp >= 0.0):
        raise ValueError(f"ramp must be >= 0, got {ramp!r}")
    return StepSteering(float(amplitude), float(start), float(ramp))


def multisine_steering(amplitude: float, periods: Sequence[float], seed: int = 0) -> Signal:
    """A multi-sine steer with random phases drawn from ``seed``; |delta| never exceeds ``amplitude``."""
    require_finite("amplitude", amplitude)
    if len(periods) == 0:
        raise ValueError("multisine_steering needs at least one period")
    for period in periods:
        require_positive("period", period)
    phases = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi, size=len(periods))
    return MultisineSteering(float(amplitude), tuple(float(p) for p in periods), tuple(phases.tolist()))


@dataclass(frozen=True)
class Headlands:
    """Rows of ``row_time`` s, each followed by a U-turn of ``turn_time`` s; ramps of ``ramp`` s in and out.

    :meth:`turning` is 0 in a row, 1 in a turn, linear in the ramps; turns alternate left and right.
    """

    row_time: float = 40.0
    turn_time: float = 10.0
    ramp: float = 2.0

    def turning(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(share of the turn, +1 for a left turn / -1 for a right one) at times ``t``."""
        t = np.asarray(t, dtype=float)
        period = self.row_time + self.turn_time
        index = np.floor(t / period)
        into = t - index * period
        share = np.minimum(np.clip((into - self.row_time) / self.ramp, 0.0, 1.0),
                           np.clip((period - into) / self.ramp, 0.0, 1.0))
        return share, np.where(index % 2 == 0, 1.0, -1.0)


@dataclass(frozen=True)
class Constant:
    """A constant signal."""

    value: float

    def __call__(self, t: np.ndarray) -> np.ndarray:
        return np.full(np.shape(t), self.value)


@dataclass(frozen=True)
class HeadlandBlend:
    """``row(t)`` in the rows, ``turn`` in the headland turns (signed by the turn's side if ``sided``), linear between."""

    headlands: Headlands
    row: Signal
    turn: float
    sided: bool

    def __call__(self, t: np.ndarray) -> np.ndarray:
        share, side = self.headlands.turning(t)
        return (1.0 - share) * self.row(t) + share * (side if self.sided else 1.0) * self.turn


def field_work(row_speed: float = 2.0, turn_speed: float = 1.2, lock: float = math.radians(30.0),
               tracking: float = math.radians(2.0), headlands: Headlands | None = None,
               seed: int = 0) -> tuple[Signal, Signal]:
    """(steering, speed profile) of field work: rows with a +-``tracking`` multisine, U-turns at ``lock``."""
    for name, value in (("row_speed", row_speed), ("turn_speed", turn_speed), ("lock", lock)):
        require_positive(name, value)
    headlands = headlands or Headlands()
    for name, value in (("row_time", headlands.row_time), ("turn_time", headlands.turn_time),
                        ("ramp", headlands.ramp)):
        require_positive(name, value)
    corrections = multisine_steering(tracking, (4.0, 7.0, 11.0, 17.0), seed=seed)
    return (HeadlandBlend(headlands, corrections, float(lock), sided=True),
            HeadlandBlend(headlands, Constant(float(row_speed)), float(turn_speed), sided=False))


@dataclass(frozen=True)
class StiffnessSchedule:
    """Piecewise-constant true cornering stiffness, N/rad per tire (the model's 2*C per axle).

    Segment i holds ``front[i]``, ``rear[i]`` from ``times[i]``. With ``transition > 0`` the
    change at ``times[i]`` is a linear blend over ``[times[i], times[i] + transition]``
    (overlapping blends add up; the value after the last blend is always the segment value).
    """

    times: tuple[float, ...] = (0.0,)
    front: tuple[float, ...] = (8000.0,)
    rear: tuple[float, ...] = (10000.0,)
    transition: float = 0.0

    def __post_init__(self) -> None:
        if not (len(self.times) == len(self.front) == len(self.rear) and len(self.times) > 0):
            raise ValueError(
                "stiffness schedule: times, front and rear must be non-empty and of equal length"
            )
        if self.times[0] != 0.0:
            raise ValueError(f"stiffness schedule must start at time 0.0, got {self.times[0]!r}")
        if any(not math.isfinite(b) or b <= a for a, b in zip(self.times[:-1], self.times[1:], strict=True)):
            raise ValueError(f"stiffness schedule times must be strictly ascending, got {self.times}")
        for value in (*self.front, *self.rear):
            require_positive("stiffness", value)
        if not (math.isfinite(self.transition) and self.transition >= 0.0):
            raise ValueError(f"stiffness transition must be >= 0, got {self.transition!r}")

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Cf, Cr) at times ``t`` (any shape), N/rad per tire."""
        t = np.asarray(t, dtype=float)
        return self._blend(t, self.front), self._blend(t, self.rear)

    def _blend(self, t: np.ndarray, values: tuple[float, ...]) -> np.ndarray:
        out = np.full(t.shape, values[0], dtype=float)
        for start, before, after in zip(self.times[1:], values[:-1], values[1:], strict=True):
            out = out + (after - before) * _ramp(t, start, self.transition)
        return out


def _ramp(t: np.ndarray, start: float, width: float) -> np.ndarray:
    if width <= 0.0:
        return (t >= start).astype(float)
    return np.clip((t - start) / width, 0.0, 1.0)



def require_positive(name: str, value: float) -> None:
    if isinstance(value, bool) or not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def require_finite(name: str, value: float) -> None:
    if isinstance(value, bool) or not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
