"""From RTK-GNSS velocity, heading and steering to the filter's epochs (paper section 2.1, z of eq. 7).

The paper obtains vy and r "by coordinate transformation" of the receiver's velocity and heading.
Here, for each GNSS epoch t_k (velocity and heading paired by stamp, :mod:`.pairing`):

* heading: ENU yaw, or compass heading (clockwise from north) for ``ned``, of the heading source;
  minus ``vehicle.heading_offset`` (the source's yaw relative to the vehicle x axis, e.g. a
  dual-antenna baseline mounted across the vehicle); unwrapped across +-pi. A single antenna
  (``ekf.measurement: course``, :attr:`~.settings.AssemblerSettings.course`): no heading samples; each
  velocity's direction is its epoch's heading, which the filter models as the antenna's course
  (reversing, :mod:`.course`: + pi, and the speed negative);
* velocity: ENU or NED, rotated into the body frame by the heading; or already in body axes at
  the antenna (a nav_msgs/Odometry twist, :meth:`EpochAssembler.add_body_velocity`, turned by
  ``body_velocity_rotation`` when its child frame is the heading source's);
* yaw rate: the interval mean over [t_{k-1}, t_k] from heading increments (never a derivative);
* timing: a GNSS sample stamped t describes the motion at t - ``gnss_delay`` (drivers that
  stamp on arrival); the epoch time and the steering interval use that time;
* lever arm: the filter measures the antenna's lateral velocity (h(x) = vy + ax r); the CG
  values vy_cg = vy - r ax (display) and vx_cg = vx + r ay (the speed input) use the interval r;
* inputs: vx averaged over [t_{k-1}, t_k], and the steering angle over the interval as its
  least-squares line (mean and slope) through the faster steering stream, interpolated
  linearly between its samples. The interval mean is DESIGN.md's input; the slope lets the
  exact model follow a ramp, which matters because at 2 m/s the lateral dynamics (time
  constant ~40 ms) are much faster than a 5 Hz GNSS interval. Each steering sample is first
  made the single-track angle (:meth:`.settings.AssemblerSettings.wheel_angle`: the sensor's
  scale, the linkage's play (:mod:`.steering_play`), and the Ackermann map for a sensor on one wheel).

Bad input (DESIGN.md section 6, issue #14) is rejected with a reason and a kind (:mod:`.checks`):
non-finite values, invalid markers, quaternions that are no orientation, stamps out of order, a
stamp far from the others (:mod:`.stamps`: an outlier, never the new reference; a lasting time
step re-synchronises by itself), and the vehicle's physical limits: |speed|, a steering spike
(faster than max_steering_rate; a second in a row is a real jump), then per epoch |yaw rate| and
|lateral speed| at the CG. An epoch beyond a limit is dropped and does not become the
next epoch's start, so one bad heading costs one epoch, not two; two in a row re-anchor.

An epoch is formed only once the steering stream covers its interval (a steering sample at or after t_k), or
at the latest when a GNSS epoch more than ``steering.max_wait`` later is matched (then it is counted as
uncovered): the result does not depend on which of GNSS and steering arrives first, nor on a steering driver
lagging the GNSS by less. Plain functions and one small stateful assembler, no ROS types: the node, the bag
reader and the simulator tests all feed the same :class:`EpochAssembler`.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from transplanter_ident.epochs import checks
from transplanter_ident.epochs.course import CourseTracker
from transplanter_ident.epochs.epoch import Epoch, Rejection
from transplanter_ident.epochs.frames import (
    body_velocity,
    heading_to_enu_yaw,
    interval_rate_variance,
    lateral_variance,
    quaternion_yaw,
    remove_lever_arm,
    unwrap_heading,
    velocity_to_enu,
)
from transplanter_ident.epochs.pairing import GnssPairer, PairingStats, Unpaired
from transplanter_ident.epochs.settings import AssemblerSettings
from transplanter_ident.epochs.stamps import StampGuard, Verdict
from transplanter_ident.epochs.steering_line import interval_line

#: s: stamps closer than this count as the same instant (clocks written as float seconds)
STAMP_EPSILON = 1.0e-6
#: consecutive epochs beyond a physical limit after which the latest sample becomes the new start
REANCHOR_AFTER = 2
#: the most steering samples kept, whatever their rate (the buffer is also trimmed by time): 10 s at 2 kHz
MAX_STEERING_SAMPLES = 20_000


@dataclass
class _Anchor:
    """The start of the next interval: time, unwrapped yaw, CG vx, the yaw's reported variance (0: none)."""

    t: float
    yaw: float
    vx: float
    yaw_variance: float


class EpochAssembler:
    """Matches velocity and heading by stamp and turns them, with steering, into epochs.

    Feed samples in arrival order; each ``add_*`` returns the epochs completed by that sample
    and records rejected samples in :attr:`rejections` (drained by the caller). An epoch waits
    until the steering covers its interval (see the module docstring), so online (node) and
    offline (bag order) results agree whichever stream arrives first. :attr:`pairing` counts
    paired and unpaired GNSS samples, :attr:`uncovered_epochs` the epochs formed before the
    steering covered them (for the diagnostics).
    """

    def __init__(self, settings: AssemblerSettings) -> None:
        self.settings = settings
        self.rejections: list[Rejection] = []
        self._pairer = GnssPairer(settings.match_tolerance)
        self._guard = StampGuard(settings.max_stamp_jump)
        self._steering: deque[tuple[float, float]] = deque(maxlen=MAX_STEERING_SAMPLES)
        self._last_steering_stamp = -math.inf
        self._last_steering_angle = 0.0
        self._steering_spikes = 0  # consecutive steering samples rejected as spikes
        self._linkage = settings.linkage()  # the steering play's state, over every accepted sample (batch alike)
        self._pending: deque[tuple[float, float, float, float]] = deque()  # paired GNSS (t, vx_ant, vy_ant, yaw)
        self.uncovered_epochs = 0  # epochs formed before the steering covered their interval
        self._previous: _Anchor | None = None
        self._beyond_limits = 0  # consecutive epochs dropped for a physical limit
        self._course = CourseTracker(settings.antenna_slip_per_tan, settings.wheelbase)  # one antenna: which way

    @property
    def pairing(self) -> PairingStats:
        """Paired epochs, samples given up without a partner and the latest miss's offset."""
        return self._pairer.stats

    def reset(self) -> None:
        """Forget everything (after a filter reset or a time jump)."""
        self.__init__(self.settings)

    def drain_rejections(self) -> list[Rejection]:
        """Return and clear the rejections since the last call."""
        out, self.rejections = self.rejections, []
        return out

    def add_velocity(self, stamp: float, first: float, second: float, variance_first: float = 0.0,
                     variance_second: float = 0.0) -> list[Epoch]:
        """A GNSS ground velocity, (east, north) or (north, east) by frame; variances 0 when unknown."""
        frame = self.settings.velocity_frame
        east, north = velocity_to_enu(first, second, frame)
        variance_east, variance_north = velocity_to_enu(variance_first, variance_second, frame)
        return self._add_velocity(stamp, ("enu", east, north, variance_east, variance_north), (first, second),
                                  (variance_first, variance_second))

    def add_body_velocity(self, stamp: float, vx: float, vy: float, variance_x: float = 0.0,
                          variance_y: float = 0.0) -> list[Epoch]:
        """A velocity already in body axes at the antenna (x forward, y left), e.g. a nav_msgs/Odometry twist."""
        return self._add_velocity(stamp, ("body", vx, vy, variance_x, variance_y), (vx, vy), (variance_x, variance_y))

    def add_heading(self, stamp: float, heading: float, variance: float = 0.0) -> list[Epoch]:
        """A GNSS heading sample (ENU yaw, or compass heading for ``ned``) of the heading source, rad.

        ``variance``: its reported variance, rad^2 (0, or not a positive number: not given).
        """
        if not (math.isfinite(stamp) and math.isfinite(heading)):
            return self._reject("heading", stamp, "non-finite value", checks.NON_FINITE)
        motion_time = stamp - self.settings.gnss_delay
        if not self._stamp_ok("heading", stamp, motion_time):
            return []
        newest = self._pairer.newest("heading")
        if self._stale_gnss(stamp):
            return self._reject("heading", stamp, "stamp not after the previous epoch", checks.STAMP_ORDER)
        if newest is not None and stamp <= newest:
            return self._reject("heading", stamp, "stamp not after the previous heading sample", checks.STAMP_ORDER)
        self._guard.accept("heading", motion_time)
        yaw = heading_to_enu_yaw(heading, self.settings.heading_frame) - self.settings.heading_offset
        return self._pair("heading", stamp, (yaw, variance if variance > 0.0 else 0.0))

    def add_heading_quaternion(self, stamp: float, x: float, y: float, z: float, w: float,
                               variance: float = 0.0) -> list[Epoch]:
        """A GNSS heading given as an orientation quaternion (QuaternionStamped, Imu, Pose, Odometry)."""
        problem = checks.quaternion_problem(x, y, z, w)
        if problem is not None:
            return self._reject("heading", stamp, problem[1], problem[0])
        return self.add_heading(stamp, quaternion_yaw(x, y, z, w), variance)

    def add_steering(self, stamp: float, angle: float) -> list[Epoch]:
        """A front steering angle sample, rad, positive to the left."""
        if not (math.isfinite(stamp) and math.isfinite(angle)):
            return self._reject("steering", stamp, "non-finite value", checks.NON_FINITE)
        if abs(angle) > self.settings.max_steering:
            return self._reject("steering", stamp, f"|{angle:.3f}| rad beyond max_steering "
                                f"{self.settings.max_steering:.3f}", checks.STEERING_LIMIT)
        if not self._stamp_ok("steering", stamp, stamp):
            return []
        if stamp <= self._last_steering_stamp:
            return self._reject("steering", stamp, "stamp not after the previous steering sample", checks.STAMP_ORDER)
        change = abs(angle - self._last_steering_angle)
        allowed = self.settings.max_steering_rate * (stamp - self._last_steering_stamp) + checks.STEERING_NOISE
        if change > allowed and self._steering_spikes + 1 < REANCHOR_AFTER:
            self._steering_spikes += 1  # one spike is rejected; the next sample in a row is a real jump
            return self._reject("steering", stamp, f"{change:.3g} rad from the previous sample, beyond "
                                f"vehicle.max_steering_rate {self.settings.max_steering_rate:g} rad/s",
                                checks.STEERING_RATE)
        self._steering_spikes = 0
        self._guard.accept("steering", stamp)
        self._last_steering_stamp = stamp
        self._last_steering_angle = angle
        self._steering.append((stamp, self.settings.wheel_angle(angle, self._linkage)))
        while len(self._steering) > 2 and self._steering[0][0] < stamp - self.settings.steering_buffer:
            self._steering.popleft()
        return self._flush()

    def _add_velocity(self, stamp: float, payload: tuple[str, float, float], raw: tuple[float, float],
                      variances: tuple[float, float]) -> list[Epoch]:
        if not all(math.isfinite(v) for v in (stamp, *raw)):
            return self._reject("velocity", stamp, "non-finite value", checks.NON_FINITE)
        marker = checks.covariance_problem(*variances)
        if marker is not None:
            return self._reject("velocity", stamp, marker, checks.INVALID_MARKER)
        speed = math.hypot(*raw)
        if speed > self.settings.max_speed:
            return self._reject("velocity", stamp, f"speed {speed:.3g} m/s beyond vehicle.max_speed "
                                f"{self.settings.max_speed:g}", checks.SPEED_LIMIT)
        motion_time = stamp - self.settings.gnss_delay
        if not self._stamp_ok("velocity", stamp, motion_time):
            return []
        newest = self._pairer.newest("velocity")
        if self._stale_gnss(stamp):
            return self._reject("velocity", stamp, "stamp not after the previous epoch", checks.STAMP_ORDER)
        if newest is not None and stamp <= newest:
            return self._reject("velocity", stamp, "stamp not after the previous velocity sample",
                                checks.STAMP_ORDER)
        self._guard.accept("velocity", motion_time)
        if self.settings.course:
            return self._course_epoch(stamp, payload)
        return self._pair("velocity", stamp, payload)

    def _course_epoch(self, stamp: float, payload: tuple[str, float, float, float, float]) -> list[Epoch]:
        """A single antenna: the velocity's own direction is the epoch's heading (a course; + pi and -|v| reversing)."""
        frame, east, north, variance_east, variance_north = payload
        if frame != "enu":
            return self._reject("velocity", stamp, "a velocity in body axes has no course: ekf.measurement course "
                                "needs a velocity in ENU or NED", checks.OTHER)
        heading = self._course.heading(stamp, east, north, self._steering[-1][1] if self._steering else 0.0)
        vx_ant, vy_ant = body_velocity(east, north, heading)  # vy 0 by construction
        self._pending.append((stamp - self.settings.gnss_delay, vx_ant, vy_ant, heading,
                              lateral_variance(variance_east, variance_north, heading), 0.0))
        return self._flush()

    def _stamp_ok(self, stream: str, stamp: float, motion_time: float) -> bool:
        """False (and a rejection) for an outlier stamp; after a time step, the stream's state restarts."""
        verdict, reason = self._guard.check(stream, motion_time)
        if verdict is Verdict.OUTLIER:
            self._reject(stream, stamp, reason, checks.STAMP_JUMP)
            return False
        if verdict is Verdict.RESYNC:
            self._reject(stream, stamp, reason, checks.RESYNC)
            self._restart_stream(stream)
        return True

    def _restart_stream(self, stream: str) -> None:
        """A stream's time base stepped: drop what belongs to the old one."""
        if stream == "steering":
            self._steering.clear()
            self._last_steering_stamp = -math.inf
            return
        self._pairer.clear(stream)
        for t, *_ in self._pending:
            self.rejections.append(Rejection("epoch", t, "dropped: the GNSS time base stepped", checks.RESYNC))
        self._pending.clear()
        self._previous = None

    def _reject(self, topic: str, stamp: float, reason: str, kind: str = checks.OTHER) -> list[Epoch]:
        self.rejections.append(Rejection(topic, stamp, reason, kind))
        return []

    def _stale_gnss(self, stamp: float) -> bool:
        latest = self._pending[-1][0] if self._pending else (self._previous.t if self._previous else None)
        return latest is not None and stamp - self.settings.gnss_delay <= latest

    def _pair(self, role: str, stamp: float, payload: object) -> list[Epoch]:
        pairs, given_up = self._pairer.add(role, stamp, payload)
        for sample in given_up:
            self._reject_unpaired(sample)
        for tv, (frame, a, b, variance_a, variance_b), (yaw, yaw_variance) in pairs:
            turn = yaw if frame == "enu" else -self.settings.body_velocity_rotation
            vx_ant, vy_ant = body_velocity(a, b, turn)
            vy_variance = lateral_variance(variance_a, variance_b, turn)
            self._pending.append((tv - self.settings.gnss_delay, vx_ant, vy_ant, yaw, vy_variance, yaw_variance))
        return self._flush() if pairs else []

    def _reject_unpaired(self, sample: Unpaired) -> None:
        other = "heading" if sample.role == "velocity" else "velocity"
        if sample.surplus:
            self._reject(sample.role, sample.stamp, f"the {sample.role} arrives faster than the {other}: only the "
                         f"samples with a {other} within gnss.pairing_tolerance are used", checks.SURPLUS)
            return
        tolerance = self.settings.match_tolerance
        if sample.offset is None:
            nearest = f"no {other} sample yet"
        else:
            gap = sample.offset if sample.role == "velocity" else -sample.offset
            nearest = f"the nearest {other} stamp is {1e3 * abs(gap):.0f} ms {'later' if gap > 0 else 'earlier'}"
        self._reject(sample.role, sample.stamp, f"no {other} within gnss.pairing_tolerance {1e3 * tolerance:g} ms "
                     f"({nearest})", checks.UNPAIRED)

    def _flush(self) -> list[Epoch]:
        """Form the waiting epochs whose interval the steering covers.

        An epoch also goes once a GNSS epoch more than ``steering_wait`` later waits behind it
        (counted in :attr:`uncovered_epochs`).
        """
        epochs: list[Epoch] = []
        while self._pending:
            t = self._pending[0][0]
            covered = self._last_steering_stamp >= t - STAMP_EPSILON
            if not (covered or self._pending[-1][0] - t > self.settings.steering_wait):
                break
            if not covered and self._previous is not None:
                self.uncovered_epochs += 1
            epoch = self._gnss_epoch(*self._pending.popleft())
            if epoch is not None:
                epochs.append(epoch)
        return epochs

    def _gnss_epoch(self, t: float, vx_ant: float, vy_ant: float, yaw: float, vy_variance: float,
                    yaw_variance: float) -> Epoch | None:
        previous = self._previous
        settings = self.settings
        if previous is None:
            self._previous = _Anchor(t, yaw, vx_ant, yaw_variance)
            return None
        unwrapped = unwrap_heading(previous.yaw, yaw)
        dt = t - previous.t
        yaw_rate = (unwrapped - previous.yaw) / dt
        vx, vy = remove_lever_arm(vx_ant, vy_ant, yaw_rate, settings.antenna_x, settings.antenna_y)
        if settings.course:  # the filter turns the antenna's |v| into the CG's vx itself (measurement_row.course_speed)
            vx, vy = vx_ant, math.nan  # and one antenna does not measure vy
        limit = self._limit_problem(yaw_rate, vy)
        if limit is not None:
            self._beyond_limits += 1
            if self._beyond_limits >= REANCHOR_AFTER:  # the start itself may be the bad sample
                self._previous = _Anchor(t, yaw, vx, yaw_variance)
                self._beyond_limits = 0
            topic, reason, kind = limit
            self.rejections.append(Rejection(topic, t, reason, kind))
            return None
        self._beyond_limits = 0
        self._previous = _Anchor(t, unwrapped, vx, yaw_variance)
        steering = self._steering_line(previous.t, t)
        if steering is None:
            self.rejections.append(Rejection("epoch", t, "no recent steering angle", checks.NO_STEERING))
            return None
        return Epoch(t=t, longitudinal_velocity=vx, lateral_velocity=vy, heading=unwrapped,
                     yaw_rate=yaw_rate, steering=steering[0], steering_rate=steering[1],
                     speed=0.5 * (previous.vx + vx), antenna_lateral_velocity=vy_ant,
                     velocity_variance=vy_variance, heading_variance=yaw_variance,
                     yaw_rate_variance=interval_rate_variance(previous.yaw_variance, yaw_variance, dt))

    def _limit_problem(self, yaw_rate: float, vy: float) -> tuple[str, str, str] | None:
        """(topic, reason, kind) when the epoch is beyond the vehicle's yaw-rate or lateral-speed limit."""
        settings = self.settings
        if abs(yaw_rate) > settings.max_yaw_rate:
            return ("heading", f"yaw rate {yaw_rate:+.3g} rad/s beyond vehicle.max_yaw_rate {settings.max_yaw_rate:g}",
                    checks.YAW_RATE_LIMIT)
        if abs(vy) > settings.max_lateral_speed:
            return ("velocity", f"lateral speed {vy:+.3g} m/s beyond vehicle.max_lateral_speed "
                    f"{settings.max_lateral_speed:g}", checks.LATERAL_SPEED_LIMIT)
        return None

    def _steering_line(self, start: float, end: float) -> tuple[float, float] | None:
        samples = self._steering
        while len(samples) > 1 and samples[1][0] <= start:
            samples.popleft()
        if not samples or samples[-1][0] < end - self.settings.steering_timeout or samples[0][0] > end:
            return None  # nothing recent, or nothing before the interval's end (never extrapolate back)
        times, values = zip(*samples, strict=True)
        return interval_line(times, values, start, end)


#: sample names of :func:`assemble` -> the assembler method that takes them
INPUTS = {"velocity": "add_velocity", "velocity_body": "add_body_velocity", "heading": "add_heading",
          "heading_quaternion": "add_heading_quaternion", "steering": "add_steering"}


def assemble(assembler: EpochAssembler, samples: Iterable[tuple[str, float, tuple[float, ...]]]) -> list[Epoch]:
    """Feed (input, stamp, values) samples in order; return the epochs (offline use).

    input: ``velocity`` (v1, v2[, variance1, variance2]) in frames.velocity, ``velocity_body`` (vx, vy[,
    variances]) in body axes, ``heading`` (yaw,), ``heading_quaternion`` (x, y, z, w) or ``steering`` (angle,).
    """
    adders = {name: getattr(assembler, method) for name, method in INPUTS.items()}
    epochs: list[Epoch] = []
    for name, stamp, values in samples:
        epochs.extend(adders[name](stamp, *values))
    return epochs
