"""The steering input: its least-squares line over one GNSS interval, and a wheel's angle as the single-track one.

The steering stream is faster than GNSS; joined by straight lines between its samples, its
mean and least-squares slope over [t_{k-1}, t_k] are what the exact model integrates as a ramp
(DESIGN.md section 1, input timing). :func:`interval_line_kernel` is the same computation,
compiled, for the batch assembler (epochs/batch.py).

:func:`single_track_angle`: the bicycle model (paper eq. 4) has one front wheel on the centre line;
a sensor on the left or right wheel reads that wheel's angle, and with Ackermann geometry (the
wheels' axes meet on the rear axle's line) cot delta = cot delta_wheel + k, k = +-track / (2 wheelbase).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence

import numpy as np

from transplanter_ident.jit import entry_kernel


def interval_line(times: Sequence[float], values: Sequence[float], start: float,
                  end: float) -> tuple[float, float]:
    """Mean and least-squares slope over [start, end] of the samples joined by straight lines.

    The signal is held constant before the first and after the last sample. ``times``
    strictly ascending, at least one sample, end > start. Exact (Simpson) integrals per segment.
    """
    first = bisect.bisect_right(times, start)
    last = bisect.bisect_left(times, end)
    knots = [start, *times[first:last], end]
    level = [_interpolate(times, values, start), *values[first:last], _interpolate(times, values, end)]
    centre = 0.5 * (start + end)
    area = moment = 0.0
    for i in range(len(knots) - 1):
        a, b, ya, yb = knots[i], knots[i + 1], level[i], level[i + 1]
        area += 0.5 * (b - a) * (ya + yb)
        moment += (b - a) / 6.0 * ((a - centre) * ya + (a + b - 2.0 * centre) * (ya + yb) + (b - centre) * yb)
    span = end - start
    return area / span, moment * 12.0 / span**3


def _interpolate(times: Sequence[float], values: Sequence[float], t: float) -> float:
    """Linear interpolation, held constant beyond the first and last sample."""
    i = bisect.bisect_right(times, t)
    if i == 0:
        return values[0]
    if i == len(times):
        return values[-1]
    t0, t1 = times[i - 1], times[i]
    return values[i - 1] + (values[i] - values[i - 1]) * (t - t0) / (t1 - t0)


@entry_kernel
def interval_line_kernel(times, values, start, end):  # noqa: ANN001, ANN201 - float64 arrays and floats
    """:func:`interval_line` on arrays, operation for operation (the batch assembler's kernel; tested bit for bit)."""
    first = np.searchsorted(times, start, side="right")
    last = np.searchsorted(times, end, side="left")
    centre = 0.5 * (start + end)
    area = 0.0
    moment = 0.0
    a, ya = start, _interpolate_kernel(times, values, start)
    for i in range(first, last + 1):
        if i < last:
            b, yb = times[i], values[i]
        else:
            b, yb = end, _interpolate_kernel(times, values, end)
        area += 0.5 * (b - a) * (ya + yb)
        moment += (b - a) / 6.0 * ((a - centre) * ya + (a + b - 2.0 * centre) * (ya + yb) + (b - centre) * yb)
        a, ya = b, yb
    span = end - start
    return area / span, moment * 12.0 / span ** 3.0


@entry_kernel
def _interpolate_kernel(times, values, t):  # noqa: ANN001, ANN201
    i = np.searchsorted(times, t, side="right")
    if i == 0:
        return values[0]
    if i == len(times):
        return values[-1]
    t0, t1 = times[i - 1], times[i]
    return values[i - 1] + (values[i] - values[i - 1]) * (t - t0) / (t1 - t0)


def ackermann_ratio(wheel: str, track: float, wheelbase: float) -> float:
    """K of :func:`single_track_angle` for a sensor on the ``wheel`` (center, left or right) front wheel."""
    return {"center": 0.0, "left": 1.0, "right": -1.0}[wheel] * track / (2.0 * wheelbase)


def single_track_angle(wheel_angle: float, ratio: float) -> float:
    """The single-track steering angle from one front wheel's (rad, + left): cot delta = cot wheel + ``ratio``."""
    if ratio == 0.0:
        return wheel_angle
    return math.atan2(math.sin(wheel_angle), math.cos(wheel_angle) + ratio * math.sin(wheel_angle))
