"""From RTK-GNSS velocity, heading and steering to the filter's epochs (paper section 2.1, z of eq. 7).

The paper obtains vy and r "by coordinate transformation" of the receiver's velocity and heading.
Here, for each GNSS epoch t_k (velocity and heading matched by stamp):

* heading: ENU yaw, or compass heading (clockwise from north) for ``ned``; unwrapped across +-pi;
* velocity: ENU or NED, rotated into the body frame by the heading;
* yaw rate: the interval mean over [t_{k-1}, t_k] from heading increments (never a derivative);
* timing: a GNSS sample stamped t describes the motion at t - ``gnss_delay`` (drivers that
  stamp on arrival); the epoch time and the steering interval use that time;
* lever arm: the filter measures the antenna's lateral velocity (h(x) = vy + ax r); the CG
  values vy_cg = vy - r ax (display) and vx_cg = vx + r ay (the speed input) use the interval r;
* inputs: vx averaged over [t_{k-1}, t_k], and the steering angle over the interval as its
  least-squares line (mean and slope) through the faster steering stream, interpolated
  linearly between its samples. The interval mean is DESIGN.md's input; the slope lets the
  exact model follow a ramp, which matters because at 2 m/s the lateral dynamics (time
  constant ~40 ms) are much faster than a 5 Hz GNSS interval.

An epoch is formed only once the steering stream covers its interval (a steering sample at or
after t_k), or, at the latest, when the next GNSS epoch is matched (then it is counted as
uncovered), so the result does not depend on whether GNSS or steering arrives first. Plain
functions and one small stateful assembler, no ROS types: the node, the bag reader and the
simulator tests all feed the same :class:`EpochAssembler`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.config.schema import FRAMES
from transplanter_ident.epochs.epoch import Epoch, Rejection
from transplanter_ident.epochs.frames import (
    body_velocity,
    heading_to_enu_yaw,
    quaternion_yaw,
    remove_lever_arm,
    unwrap_heading,
    velocity_to_enu,
)
from transplanter_ident.epochs.steering_line import interval_line

#: s: stamps closer than this count as the same instant (clocks written as float seconds)
STAMP_EPSILON = 1.0e-6
#: the most steering samples kept, whatever their rate (the buffer is also trimmed by time): 10 s at 2 kHz
MAX_STEERING_SAMPLES = 20_000


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
    gnss_delay: float = 0.0  # s: GNSS stamped t describes the motion at t - gnss_delay
    steering_buffer: float = 10.0  # s of steering history kept (bounded memory without GNSS)

    @classmethod
    def from_params(cls, params: EstimatorParams) -> AssemblerSettings:
        """Frames, lever arm, steering limit and GNSS timing from the parameters (node and bags alike)."""
        vehicle = params.config.vehicle
        return cls(velocity_frame=params.frames.velocity, heading_frame=params.frames.heading,
                   antenna_x=vehicle.antenna_x, antenna_y=vehicle.antenna_y, max_steering=vehicle.max_steering,
                   match_tolerance=params.gnss.pairing_tolerance, gnss_delay=params.gnss.delay)

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
    and records rejected samples in :attr:`rejections` (drained by the caller). An epoch waits
    until the steering covers its interval (see the module docstring), so online (node) and
    offline (bag order) results agree whichever stream arrives first. :meth:`finish` emits
    what still waits at the end of a recording.
    """

    def __init__(self, settings: AssemblerSettings) -> None:
        self.settings = settings
        self.rejections: list[Rejection] = []
        self._velocity: deque[tuple[float, float, float]] = deque(maxlen=32)
        self._heading: deque[tuple[float, float]] = deque(maxlen=32)
        self._steering: deque[tuple[float, float]] = deque(maxlen=MAX_STEERING_SAMPLES)
        self._last_steering_stamp = -math.inf
        self._pending: deque[tuple[float, float, float, float]] = deque()  # matched GNSS (t, east, north, yaw)
        self.uncovered_epochs = 0  # epochs formed before the steering covered their interval
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
        while len(self._steering) > 2 and self._steering[0][0] < stamp - self.settings.steering_buffer:
            self._steering.popleft()
        return self._flush(force=False)

    def finish(self) -> list[Epoch]:
        """Emit the epochs still waiting for steering (end of a recording)."""
        return self._flush(force=True)

    def _reject(self, topic: str, stamp: float, reason: str) -> list[Epoch]:
        self.rejections.append(Rejection(topic, stamp, reason))
        return []

    def _stale_gnss(self, stamp: float) -> bool:
        latest = self._pending[-1][0] if self._pending else (self._previous[0] if self._previous else None)
        return latest is not None and stamp - self.settings.gnss_delay <= latest

    def _match(self) -> list[Epoch]:
        tol = self.settings.match_tolerance
        for vi, (tv, east, north) in enumerate(self._velocity):
            for hi, (th, yaw) in enumerate(self._heading):
                if abs(tv - th) <= tol:
                    for _ in range(vi + 1):
                        self._velocity.popleft()
                    for _ in range(hi + 1):
                        self._heading.popleft()
                    self._pending.append((tv - self.settings.gnss_delay, east, north, yaw))
                    return self._flush(force=False)
        return []

    def _flush(self, *, force: bool) -> list[Epoch]:
        """Form the waiting epochs whose interval the steering covers (all of them if ``force``).

        An epoch also goes once a later one waits behind it: it has waited a whole GNSS period.
        """
        epochs: list[Epoch] = []
        while self._pending:
            t = self._pending[0][0]
            covered = self._last_steering_stamp >= t - STAMP_EPSILON
            if not (covered or force or len(self._pending) > 1):
                break
            if not covered and self._previous is not None:
                self.uncovered_epochs += 1
            epoch = self._gnss_epoch(*self._pending.popleft())
            if epoch is not None:
                epochs.append(epoch)
        return epochs

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
                     speed=0.5 * (vx_before + vx), antenna_lateral_velocity=vy_ant)

    def _steering_line(self, start: float, end: float) -> tuple[float, float] | None:
        samples = self._steering
        while len(samples) > 1 and samples[1][0] <= start:
            samples.popleft()
        if not samples or samples[-1][0] < end - self.settings.steering_timeout or samples[0][0] > end:
            return None  # nothing recent, or nothing before the interval's end (never extrapolate back)
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
