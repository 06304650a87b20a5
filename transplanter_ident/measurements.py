"""From RTK-GNSS velocity, heading and steering to the filter's epochs (paper section 2.1, z of eq. 7).

The paper obtains vy and r "by coordinate transformation" of the receiver's velocity and heading.
Here, for each GNSS epoch t_k (velocity and heading matched by stamp):

* heading: ENU yaw, or compass heading (clockwise from north) for ``ned``; unwrapped across +-pi;
* velocity: ENU or NED, rotated into the body frame by the heading;
* yaw rate: the interval mean over [t_{k-1}, t_k] from heading increments (never a derivative);
* lever arm: v_cg = v_antenna - r x p_antenna, i.e. vy_cg = vy - r ax, vx_cg = vx + r ay;
* inputs: vx averaged over [t_{k-1}, t_k], and the steering angle over the interval as its
  least-squares line (mean and slope) through the faster steering stream, interpolated
  linearly between its samples. The interval mean is DESIGN.md's input; the slope lets the
  exact model follow a ramp, which matters because at 2 m/s the lateral dynamics (time
  constant ~40 ms) are much faster than a 5 Hz GNSS interval.

Plain functions and one small stateful assembler, no ROS types: the node, the bag reader and
the simulator tests all feed the same :class:`EpochAssembler`.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, fields

import numpy as np

FRAMES = ("enu", "ned")


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


class EpochArrays:
    """A sequence of epochs as columns (replay, tuner)."""

    def __init__(self, epochs: Sequence[Epoch] | None = None) -> None:
        names = [f.name for f in fields(Epoch)]
        data = np.array([[getattr(e, n) for n in names] for e in epochs or []], dtype=np.float64)
        self._data = data.reshape(-1, len(names))
        for i, name in enumerate(names):
            setattr(self, name, self._data[:, i])

    def __len__(self) -> int:
        return self._data.shape[0]

    def __getitem__(self, index: int) -> Epoch:
        return Epoch(*map(float, self._data[index]))

    def kernel_input(self) -> np.ndarray:
        """Columns [t, speed, steering, steering_rate, vy, psi, r] for ekf.run_kernel."""
        return np.ascontiguousarray(
            np.column_stack([self.t, self.speed, self.steering, self.steering_rate, self.lateral_velocity,
                             self.heading, self.yaw_rate])
        )


@dataclass(frozen=True)
class Rejection:
    """A sample that was not used, and why (DESIGN.md section 6)."""

    topic: str  # "velocity" | "heading" | "steering" | "epoch"
    stamp: float
    reason: str


def wrap_angle(angle: float) -> float:
    """Wrap to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def stamp_seconds(sec: int, nanosec: int) -> float:
    """A ROS time (sec, nanosec) in seconds, via integer nanoseconds (node and bag reader alike)."""
    return (sec * 1_000_000_000 + nanosec) / 1e9


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rotation about z) of an orientation quaternion; NaN if it is non-finite or of zero norm."""
    if not all(math.isfinite(c) for c in (x, y, z, w)) or x * x + y * y + z * z + w * w < 1e-12:
        return math.nan
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def heading_to_enu_yaw(heading: float, frame: str) -> float:
    """ENU yaw from an ENU yaw (``enu``) or a compass heading, clockwise from north (``ned``)."""
    return heading if frame == "enu" else math.pi / 2.0 - heading


def velocity_to_enu(first: float, second: float, frame: str) -> tuple[float, float]:
    """(east, north) from (east, north) for ``enu`` or (north, east) for ``ned``."""
    return (first, second) if frame == "enu" else (second, first)


def body_velocity(east: float, north: float, yaw: float) -> tuple[float, float]:
    """Rotate an ENU ground velocity into the body frame (x forward, y left)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return c * east + s * north, -s * east + c * north


def remove_lever_arm(vx: float, vy: float, yaw_rate: float, antenna_x: float,
                     antenna_y: float) -> tuple[float, float]:
    """CG velocity from the antenna's: v_cg = v_ant - r e_z x p_ant."""
    return vx + yaw_rate * antenna_y, vy - yaw_rate * antenna_x


def unwrap_heading(previous_unwrapped: float, wrapped: float) -> float:
    """Continue an unwrapped heading with a new wrapped sample (the shortest turn)."""
    return previous_unwrapped + wrap_angle(wrapped - previous_unwrapped)


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


@dataclass(frozen=True)
class AssemblerSettings:
    """How samples become epochs."""

    velocity_frame: str = "enu"
    heading_frame: str = "enu"
    antenna_x: float = 0.0
    antenna_y: float = 0.0
    max_steering: float = 0.7
    match_tolerance: float = 0.02  # s between velocity and heading stamps of one epoch
    steering_timeout: float = 0.5  # s: a newer steering sample must exist within this of t_k

    def __post_init__(self) -> None:
        for name in ("velocity_frame", "heading_frame"):
            if getattr(self, name) not in FRAMES:
                raise ValueError(f"frames.{name.split('_')[0]} must be enu or ned, got {getattr(self, name)!r}")


@dataclass
class _GnssSample:
    east: float
    north: float
    yaw: float  # unwrapped


class EpochAssembler:
    """Matches velocity and heading by stamp and turns them, with steering, into epochs.

    Feed samples in arrival order; each ``add_*`` returns the epochs completed by that sample
    (zero or one) and records rejected samples in :attr:`rejections` (drained by the caller).
    An epoch is emitted as soon as its velocity and heading have arrived, using the steering
    received so far, so online (node) and offline (bag order) results agree.
    """

    def __init__(self, settings: AssemblerSettings) -> None:
        self.settings = settings
        self.rejections: list[Rejection] = []
        self._velocity: deque[tuple[float, float, float]] = deque(maxlen=32)
        self._heading: deque[tuple[float, float]] = deque(maxlen=32)
        self._steering: deque[tuple[float, float]] = deque()
        self._last_steering_stamp = -math.inf
        self._previous: tuple[float, _GnssSample, float] | None = None  # (t, sample, vx_cg)

    def reset(self) -> None:
        """Forget everything (after a filter reset or a time jump)."""
        self.__init__(self.settings)

    def drain_rejections(self) -> list[Rejection]:
        """Return and clear the rejections since the last call."""
        out, self.rejections = self.rejections, []
        return out

    def add_velocity(self, stamp: float, first: float, second: float) -> list[Epoch]:
        """A GNSS velocity sample, (east, north) or (north, east) by frame."""
        if not all(math.isfinite(v) for v in (stamp, first, second)):
            return self._reject("velocity", stamp, "non-finite value")
        if self._stale_gnss(stamp):
            return self._reject("velocity", stamp, "stamp not after the previous epoch")
        if self._velocity and stamp <= self._velocity[-1][0]:
            return self._reject("velocity", stamp, "stamp not after the previous velocity sample")
        self._velocity.append((stamp, *velocity_to_enu(first, second, self.settings.velocity_frame)))
        return self._match()

    def add_heading(self, stamp: float, heading: float) -> list[Epoch]:
        """A GNSS heading sample (ENU yaw, or compass heading for ``ned``), rad."""
        if not (math.isfinite(stamp) and math.isfinite(heading)):
            return self._reject("heading", stamp, "non-finite value")
        if self._stale_gnss(stamp):
            return self._reject("heading", stamp, "stamp not after the previous epoch")
        if self._heading and stamp <= self._heading[-1][0]:
            return self._reject("heading", stamp, "stamp not after the previous heading sample")
        self._heading.append((stamp, heading_to_enu_yaw(heading, self.settings.heading_frame)))
        return self._match()

    def add_heading_quaternion(self, stamp: float, x: float, y: float, z: float, w: float) -> list[Epoch]:
        """A GNSS heading given as an orientation quaternion (QuaternionStamped, Imu)."""
        if not all(math.isfinite(c) for c in (x, y, z, w)):
            return self._reject("heading", stamp, f"non-finite orientation quaternion {(x, y, z, w)}")
        if x * x + y * y + z * z + w * w < 1e-12:
            return self._reject("heading", stamp, "orientation quaternion of zero norm")
        return self.add_heading(stamp, quaternion_yaw(x, y, z, w))

    def add_steering(self, stamp: float, angle: float) -> list[Epoch]:
        """A front steering angle sample, rad, positive to the left."""
        if not (math.isfinite(stamp) and math.isfinite(angle)):
            return self._reject("steering", stamp, "non-finite value")
        if abs(angle) > self.settings.max_steering:
            return self._reject("steering", stamp,
                                f"|{angle:.3f}| rad beyond max_steering {self.settings.max_steering:.3f}")
        if stamp <= self._last_steering_stamp:
            return self._reject("steering", stamp, "stamp not after the previous steering sample")
        self._last_steering_stamp = stamp
        self._steering.append((stamp, angle))
        return []

    def _reject(self, topic: str, stamp: float, reason: str) -> list[Epoch]:
        self.rejections.append(Rejection(topic, stamp, reason))
        return []

    def _stale_gnss(self, stamp: float) -> bool:
        return self._previous is not None and stamp <= self._previous[0]

    def _match(self) -> list[Epoch]:
        tol = self.settings.match_tolerance
        for vi, (tv, east, north) in enumerate(self._velocity):
            for hi, (th, yaw) in enumerate(self._heading):
                if abs(tv - th) <= tol:
                    for _ in range(vi + 1):
                        self._velocity.popleft()
                    for _ in range(hi + 1):
                        self._heading.popleft()
                    epoch = self._gnss_epoch(tv, east, north, yaw)
                    return [] if epoch is None else [epoch]
        return []

    def _gnss_epoch(self, t: float, east: float, north: float, yaw: float) -> Epoch | None:
        previous = self._previous
        if previous is None:
            sample = _GnssSample(east, north, yaw)
            vx_ant, vy_ant = body_velocity(east, north, yaw)
            self._previous = (t, sample, vx_ant)
            return None
        t0, before, vx_before = previous
        unwrapped = unwrap_heading(before.yaw, yaw)
        sample = _GnssSample(east, north, unwrapped)
        dt = t - t0
        yaw_rate = (unwrapped - before.yaw) / dt
        vx_ant, vy_ant = body_velocity(east, north, unwrapped)
        vx, vy = remove_lever_arm(vx_ant, vy_ant, yaw_rate, self.settings.antenna_x, self.settings.antenna_y)
        self._previous = (t, sample, vx)
        steering = self._steering_line(t0, t)
        if steering is None:
            self.rejections.append(Rejection("epoch", t, "no recent steering angle"))
            return None
        return Epoch(t=t, longitudinal_velocity=vx, lateral_velocity=vy, heading=unwrapped,
                     yaw_rate=yaw_rate, steering=steering[0], steering_rate=steering[1],
                     speed=0.5 * (vx_before + vx))

    def _steering_line(self, start: float, end: float) -> tuple[float, float] | None:
        samples = self._steering
        while len(samples) > 1 and samples[1][0] <= start:
            samples.popleft()
        if not samples or samples[-1][0] < end - self.settings.steering_timeout:
            return None
        times, values = zip(*samples, strict=True)
        return interval_line(times, values, start, end)


def assemble(assembler: EpochAssembler, samples: Iterable[tuple[str, float, tuple[float, ...]]]) -> list[Epoch]:
    """Feed (topic, stamp, values) samples in order; return the epochs (offline use).

    topic: velocity (v1, v2), heading (yaw,) or steering (angle,).
    """
    adders = {"velocity": assembler.add_velocity, "heading": assembler.add_heading,
              "steering": assembler.add_steering}
    epochs: list[Epoch] = []
    for topic, stamp, values in samples:
        epochs.extend(adders[topic](stamp, *values))
    return epochs
