"""The offline fast path of :class:`~.assembler.EpochAssembler`: a whole bag's samples to epochs at once.

The streaming assembler costs a few microseconds of Python per sample; a 1 h, 20 Hz bag has ~324k
samples. Offline all samples are known, so this module

0. takes out the samples rejected on their own values (:mod:`.early_rejections`: NaN, invalid
   markers, limits of speed and steering, bad quaternions), which the assembler's state never sees;
1. checks, vectorised, that every sample would be *accepted* by the streaming assembler and that
   velocity and heading pair one to one with nothing given up: finite values, no invalid markers,
   quaternions of norm 1, speeds and steering angles within their limits, every stamp consistent
   for :class:`~.stamps.StampGuard` (near its stream's previous one, or vouched for by another
   stream), steering stamps increasing, GNSS samples arriving as consecutive (velocity, heading)
   pairs within ``gnss.pairing_tolerance`` that no earlier sample makes stale;
2. runs the assembler's own sequential logic in a compiled kernel (:func:`_epochs_kernel`): the
   steering buffer with its time and length trimming, the pending epochs that wait until the
   steering covers them, the anchors, heading unwrapping, the physical limits with re-anchoring,
   and :func:`~.steering_line.interval_line` (its compiled twin), with the same floating-point operations in the same
   order (the trigonometry is done in Python's ``math``, as the assembler does).

Anything else (an outlier stamp, a sample given up by the pairer, a resync, the ``heading``
yaw input) returns None, and the caller feeds the same samples to the streaming
assembler. Either way the epochs, rejections and counters are bit for bit those of the streaming
assembler (a test compares them on clean, driver-shaped, gapped and fuzzed bags).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from transplanter_ident.epochs import checks
from transplanter_ident.epochs.assembler import (
    MAX_STEERING_SAMPLES,
    REANCHOR_AFTER,
    STAMP_EPSILON,
    AssemblerSettings,
)
from transplanter_ident.epochs.early_rejections import KINDS, early_rejections, stateless_bad
from transplanter_ident.epochs.epoch import EpochArrays, Rejection
from transplanter_ident.epochs.frames import wrap_angle
from transplanter_ident.epochs.pairing import PairingStats
from transplanter_ident.epochs.steering_line import interval_line_kernel
from transplanter_ident.jit import entry_kernel

#: the value columns of a merged sample, and the widths each input comes in (fewer: the add_* defaults)
WIDTH = 5
WIDTHS = {"velocity": (2, 4), "velocity_body": (2, 4), "heading_quaternion": (4, 5), "steering": (1,)}
#: the guard stream of each kind: velocity, heading, steering
_STREAM = np.array([0, 0, 1, 2])

# per-pair outcome codes of the kernel
PENDING, ANCHOR, EPOCH, YAW_LIMIT, LATERAL_LIMIT, NO_STEERING = -1, 0, 1, 2, 3, 4


@dataclass(frozen=True)
class SampleStream:
    """Samples of one assembler input: ``keys`` give the arrival order across streams (unique, any int)."""

    name: str  # an assembler input: velocity, velocity_body, heading_quaternion, steering
    keys: np.ndarray  # int64
    stamps: np.ndarray  # s
    values: np.ndarray  # n x k, as the input's add_* method takes them after the stamp


@dataclass
class BatchResult:
    """What the streaming assembler would have produced: epochs, rejections, pairing and coverage counts."""

    epochs: EpochArrays
    rejections: list[Rejection]
    pairing: PairingStats
    uncovered_epochs: int
    rejected: list[int]  # per epoch, the rejections since the previous one (epochs.counted.assemble_counting)

    def drain_rejections(self) -> list[Rejection]:
        """Return and clear the rejections (as :meth:`EpochAssembler.drain_rejections`)."""
        out, self.rejections = self.rejections, []
        return out


def assemble_batch(settings: AssemblerSettings, streams: Sequence[SampleStream],
                   source_keys: Sequence[int] = ()) -> BatchResult | None:
    """The streaming assembler's result for these samples, or None when the fast path does not apply.

    ``source_keys``: per rejection made while the samples were read (bag decoding), the key of the first
    sample read after it; they count in :attr:`BatchResult.rejected` as epochs.counted.assemble_counting counts.
    """
    if settings.course or any(s.name not in KINDS for s in streams):  # a course: the streaming assembler's epochs
        return None
    merged = _merge(streams)
    if merged is None:
        return None
    keys, kind, stamp, values = merged
    bad = stateless_bad(settings, kind, stamp, values)
    early = early_rejections(settings, kind, stamp, values, bad)
    if early is None:
        return None
    position = np.flatnonzero(~bad)  # arrival positions of the samples the assembler's state sees
    kind, stamp, values = kind[position], stamp[position], values[position]
    yaw = _accepted(settings, kind, stamp, values)
    if yaw is None:
        return None
    pairs = _pairs(settings, kind, stamp, values, yaw)
    if pairs is None:
        return None
    steer = np.flatnonzero(kind == KINDS["steering"])
    source_at = np.searchsorted(keys, np.asarray(source_keys, dtype=np.int64), side="left")
    wheel = settings.wheel_angles(values[steer, 0])  # the streaming assembler's conversion, sample by sample
    return _run(settings, pairs, steer, stamp[steer], wheel, position, early, source_at)


def _merge(streams: Sequence[SampleStream]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """(key, kind, stamp, values n x 5) in arrival order; variances absent are 0.0, as the add_* defaults."""
    total = sum(len(s.keys) for s in streams)
    keys = np.empty(total, dtype=np.int64)
    kind = np.empty(total, dtype=np.int64)
    stamp = np.empty(total)
    values = np.zeros((total, WIDTH))
    at = 0
    for s in streams:
        n, width = len(s.keys), s.values.shape[1] if s.values.ndim == 2 else 0
        if width not in WIDTHS[s.name]:
            return None
        keys[at:at + n], kind[at:at + n], stamp[at:at + n] = s.keys, KINDS[s.name], s.stamps
        values[at:at + n, :width] = s.values
        at += n
    order = np.argsort(keys, kind="stable")
    if total > 1 and np.any(np.diff(keys[order]) == 0):
        return None
    return keys[order], kind[order], stamp[order], values[order]


def _accepted(settings: AssemblerSettings, kind: np.ndarray, stamp: np.ndarray,
              values: np.ndarray) -> np.ndarray | None:
    """The yaw of every sample (heading samples; NaN elsewhere) when every sample passes every check, else None."""
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.isfinite(stamp)
        is_vel, is_head, is_steer = kind <= 1, kind == 2, kind == 3
        v = values
        if not finite.all():
            return None
        if not np.isfinite(v[is_vel, :2]).all() or np.isnan(v[is_vel, 2:]).any() or (v[is_vel, 2:] < 0.0).any():
            return None
        if is_vel.any() and max(map(math.hypot, v[is_vel, 0].tolist(), v[is_vel, 1].tolist())) > settings.max_speed:
            return None
        q = v[is_head, :4]
        if not np.isfinite(q).all():
            return None
        norm_sq = q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3]
        if (norm_sq < 1e-12).any() or (np.abs(np.sqrt(norm_sq) - 1.0) > checks.QUATERNION_NORM_TOLERANCE).any():
            return None
        if not np.isfinite(v[is_steer, 0]).all() or (np.abs(v[is_steer, 0]) > settings.max_steering).any():
            return None
        steer_stamps = stamp[is_steer]
        if (np.diff(steer_stamps) <= 0.0).any():
            return None
        allowed = settings.max_steering_rate * np.diff(steer_stamps) + checks.STEERING_NOISE
        if (np.abs(np.diff(v[is_steer, 0])) > allowed).any():
            return None  # a steering spike: the streaming assembler's sequential check decides
        motion = np.where(is_steer, stamp, stamp - settings.gnss_delay)
        if not _guard_consistent(settings.max_stamp_jump, _STREAM[kind], motion):
            return None
    yaw = np.full(len(kind), np.nan)
    x, y, z, w = q.T  # frames.quaternion_yaw, elementwise
    yaw[is_head] = list(map(math.atan2, (2.0 * (w * z + x * y)).tolist(), (1.0 - 2.0 * (y * y + z * z)).tolist()))
    return yaw


def _guard_consistent(max_jump: float, stream: np.ndarray, motion: np.ndarray) -> bool:
    """Whether :class:`~.stamps.StampGuard` finds every stamp consistent when every sample is accepted."""
    n = len(stream)
    position = np.arange(n)
    last = np.full((3, n), np.nan)  # motion time of each stream's latest sample before i
    for s in range(3):
        latest = np.maximum.accumulate(np.where(stream == s, position, -1))
        before = np.concatenate(([-1], latest[:-1]))
        last[s] = np.where(before >= 0, motion[np.maximum(before, 0)], np.nan)
    own = last[stream, position]
    near = np.abs(motion[None, :] - last) <= max_jump  # NaN (no sample yet) is never near
    others = np.ones((3, n), dtype=bool)
    others[stream, position] = False
    near_own = near[stream, position]
    near_other = (near & others).any(axis=0)
    no_others = (np.isnan(last) | ~others).all(axis=0)
    own_none = np.isnan(own)
    went_back = ~own_none & (motion < own)
    return bool(np.all(near_own | (own_none & no_others) | (near_other & ~went_back)))


@dataclass(frozen=True)
class _Pairs:
    t: np.ndarray  # epoch time (velocity stamp - delay)
    vx_ant: np.ndarray
    vy_ant: np.ndarray
    yaw: np.ndarray
    vy_variance: np.ndarray  # frames.lateral_variance of the velocity's variances (0: not given)
    yaw_variance: np.ndarray  # the heading's reported variance (0: not given)
    done: np.ndarray  # arrival position of the pair's second sample


def _pairs(settings: AssemblerSettings, kind: np.ndarray, stamp: np.ndarray, values: np.ndarray,
           yaw: np.ndarray) -> _Pairs | None:
    """The GNSS pairs when the samples arrive as consecutive (velocity, heading) pairs that nothing gives up."""
    gnss = np.flatnonzero(kind <= 2)
    count = len(gnss) // 2
    first, second = gnss[0:2 * count:2], gnss[1:2 * count:2]
    head_first = kind[first] == 2
    if np.any(head_first == (kind[second] == 2)):
        return None
    v_at = np.where(head_first, second, first)
    h_at = np.where(head_first, first, second)
    tv, th = stamp[v_at], stamp[h_at]
    if np.any(~(np.abs(tv - th) <= settings.match_tolerance)):
        return None
    openers = gnss[0::2]  # the first sample of each pair, and a last one left waiting
    if len(openers) > 1:
        opener_is_head = kind[openers[1:]] == 2
        other_before = np.where(opener_is_head, tv[:len(openers) - 1], th[:len(openers) - 1])
        if np.any(stamp[openers[1:]] < other_before - settings.match_tolerance):
            return None  # the pairer's prune would give it up
    t = tv - settings.gnss_delay
    later = gnss[2:]  # every GNSS sample after the first pair must be newer than the previous pair's epoch
    if len(later) and np.any(stamp[later] - settings.gnss_delay <= t[(np.arange(len(later)) + 2) // 2 - 1]):
        return None
    yaw_h = yaw[h_at] if settings.heading_frame == "enu" else math.pi / 2.0 - yaw[h_at]
    yaw_h = yaw_h - settings.heading_offset
    yaw_variance = np.where(values[h_at, 4] > 0.0, values[h_at, 4], 0.0)
    vx_ant, vy_ant, vy_variance = _body(settings, kind[v_at], values[v_at], yaw_h)
    return _Pairs(t, vx_ant, vy_ant, yaw_h, vy_variance, yaw_variance, np.maximum(first, second))


def _body(settings: AssemblerSettings, kind: np.ndarray, values: np.ndarray,
          yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vx, vy) at the antenna in body axes and vy's variance: frames.body_velocity and lateral_variance, elementwise."""
    enu = kind == 0
    swap = enu & (settings.velocity_frame != "enu")
    east, north = np.where(swap, values[:, 1], values[:, 0]), np.where(swap, values[:, 0], values[:, 1])
    var_east, var_north = np.where(swap, values[:, 3], values[:, 2]), np.where(swap, values[:, 2], values[:, 3])
    turn = np.where(enu, yaw, -settings.body_velocity_rotation)
    c = np.array(list(map(math.cos, turn.tolist())))
    s = np.array(list(map(math.sin, turn.tolist())))
    given = (var_east > 0.0) & (var_north > 0.0)
    vy_variance = np.where(given, s * s * var_east + c * c * var_north, 0.0)
    return c * east + s * north, -s * east + c * north, vy_variance


def _run(settings: AssemblerSettings, pairs: _Pairs, steer_at: np.ndarray, steer_t: np.ndarray,
         steer_v: np.ndarray, position: np.ndarray, early: list[tuple[int, Rejection]],
         source_at: np.ndarray) -> BatchResult:
    events = np.concatenate((steer_at, pairs.done))
    is_pair = np.concatenate((np.zeros(len(steer_at), np.int64), np.ones(len(pairs.done), np.int64)))
    index = np.concatenate((np.arange(len(steer_at)), np.arange(len(pairs.done))))
    order = np.argsort(events, kind="stable")
    limits = np.array([settings.antenna_x, settings.antenna_y, settings.max_yaw_rate, settings.max_lateral_speed,
                       settings.steering_timeout, settings.steering_buffer, STAMP_EPSILON, settings.steering_wait])
    code = np.full(len(pairs.t), PENDING, dtype=np.int64)
    formed = np.zeros(len(pairs.t), dtype=np.int64)  # the event that formed each pair's epoch
    rows = np.zeros((len(pairs.t), len(ROW_FIELDS)))
    uncovered = _epochs_kernel(is_pair[order], index[order], steer_t, steer_v, pairs.t, pairs.vx_ant, pairs.vy_ant,
                               pairs.yaw, pairs.vy_variance, pairs.yaw_variance, limits, MAX_STEERING_SAMPLES,
                               REANCHOR_AFTER, code, rows, formed)
    at = position[events[order][formed]]  # arrival position of the sample whose add_* formed it
    rejections: list[tuple[int, Rejection]] = list(early)
    for k in np.flatnonzero(code >= YAW_LIMIT).tolist():
        t, row = float(rows[k, 0]), rows[k]
        if code[k] == YAW_LIMIT:
            rejection = Rejection("heading", t, f"yaw rate {row[4]:+.3g} rad/s beyond vehicle.max_yaw_rate "
                                  f"{settings.max_yaw_rate:g}", checks.YAW_RATE_LIMIT)
        elif code[k] == LATERAL_LIMIT:
            rejection = Rejection("velocity", t, f"lateral speed {row[2]:+.3g} m/s beyond vehicle.max_lateral_speed "
                                  f"{settings.max_lateral_speed:g}", checks.LATERAL_SPEED_LIMIT)
        else:
            rejection = Rejection("epoch", t, "no recent steering angle", checks.NO_STEERING)
        rejections.append((int(at[k]), rejection))
    rejections.sort(key=lambda item: item[0])  # stable: in the order the assembler makes them
    stats = PairingStats(pairs=len(pairs.t), tolerance=settings.match_tolerance)
    # per epoch, the rejections counted since the previous call of add_* that returned epochs (assemble_counting)
    counted = np.sort(np.concatenate((np.array([p for p, _ in rejections], dtype=np.int64), source_at)))
    upto = np.searchsorted(counted, at[code == EPOCH], side="right")
    rejected = np.diff(np.concatenate(([0], upto))).tolist()
    return BatchResult(EpochArrays.from_rows(rows[code == EPOCH]), [r for _, r in rejections], stats, int(uncovered),
                       rejected)


#: the Epoch fields of the kernel's rows, in order (the first fields of :class:`~.epoch.Epoch`)
ROW_FIELDS = ("t", "longitudinal_velocity", "lateral_velocity", "heading", "yaw_rate", "steering", "steering_rate",
              "speed", "antenna_lateral_velocity", "velocity_variance", "heading_variance", "yaw_rate_variance")


@entry_kernel
def _epochs_kernel(is_pair, index, ts, vs, pt, pvx, pvy, pyaw, pvar, pyvar, limits,  # noqa: ANN001, ANN201, PLR0913
                   max_samples, reanchor, code, rows, formed):
    """The assembler's steering buffer, pending queue, anchors and epochs, event by event (see the module)."""
    ax, ay, max_yaw_rate, max_lateral = limits[0], limits[1], limits[2], limits[3]
    timeout, keep, eps, wait = limits[4], limits[5], limits[6], limits[7]
    lo = hi = 0  # steering buffer: ts[lo:hi]
    last_steering = -np.inf
    pend_lo = pend_hi = 0  # pending pairs
    have_prev = False
    prev_t = prev_yaw = prev_vx = prev_yvar = 0.0
    beyond = 0
    uncovered = 0
    for e in range(len(is_pair)):
        if is_pair[e] == 0:
            stamp = ts[index[e]]
            last_steering = stamp
            hi = index[e] + 1
            if hi - lo > max_samples:
                lo = hi - max_samples
            while hi - lo > 2 and ts[lo] < stamp - keep:
                lo += 1
        else:
            pend_hi = index[e] + 1
        while pend_lo < pend_hi:
            k = pend_lo
            t = pt[k]
            covered = last_steering >= t - eps
            if not (covered or pt[pend_hi - 1] - t > wait):
                break
            if not covered and have_prev:
                uncovered += 1
            pend_lo += 1
            formed[k] = e
            rows[k, 0] = t
            if not have_prev:
                have_prev = True
                prev_t, prev_yaw, prev_vx, prev_yvar = t, pyaw[k], pvx[k], pyvar[k]
                code[k] = 0
                continue
            unwrapped = prev_yaw + wrap_angle(pyaw[k] - prev_yaw)
            dt = t - prev_t
            yaw_rate = (unwrapped - prev_yaw) / dt
            vx = pvx[k] + yaw_rate * ay
            vy = pvy[k] - yaw_rate * ax
            rows[k, 2] = vy
            rows[k, 4] = yaw_rate
            if abs(yaw_rate) > max_yaw_rate or abs(vy) > max_lateral:
                code[k] = 2 if abs(yaw_rate) > max_yaw_rate else 3
                beyond += 1
                if beyond >= reanchor:
                    prev_t, prev_yaw, prev_vx, prev_yvar = t, pyaw[k], vx, pyvar[k]
                    beyond = 0
                continue
            beyond = 0
            start, start_vx, start_yvar = prev_t, prev_vx, prev_yvar
            prev_t, prev_yaw, prev_vx, prev_yvar = t, unwrapped, vx, pyvar[k]
            while hi - lo > 1 and ts[lo + 1] <= start:
                lo += 1
            if hi == lo or ts[hi - 1] < t - timeout or ts[lo] > t:
                code[k] = 4
                continue
            mean, slope = interval_line_kernel(ts[lo:hi], vs[lo:hi], start, t)
            code[k] = 1
            rows[k, 1] = vx
            rows[k, 3] = unwrapped
            rows[k, 5] = mean
            rows[k, 6] = slope
            rows[k, 7] = 0.5 * (start_vx + vx)
            rows[k, 8] = pvy[k]
            rows[k, 9] = pvar[k]
            rows[k, 10] = pyvar[k]
            rows[k, 11] = (start_yvar + pyvar[k]) / (dt * dt) if start_yvar > 0.0 and pyvar[k] > 0.0 else 0.0
    return uncovered


def stream_samples(streams: Sequence[SampleStream], *, keys: bool = False) -> list[tuple]:
    """The samples in arrival order as :func:`~.assembler.assemble` takes them (the streaming fallback).

    ``keys``: (key, input, stamp, values) instead of (input, stamp, values).
    """
    merged = [(int(k), s.name, float(t), tuple(v)) for s in streams
              for k, t, v in zip(s.keys.tolist(), s.stamps.tolist(), s.values.tolist(), strict=True)]
    merged.sort(key=lambda row: row[0])
    return merged if keys else [(name, t, values) for _, name, t, values in merged]
