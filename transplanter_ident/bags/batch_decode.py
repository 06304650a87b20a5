"""Decoding a bag's input messages in batches: one numpy view per run of equally laid-out messages.

Deserialising every message with rosbags costs more than the rest of a replay. The messages of one
connection are nearly always laid out alike: the same length, the same frame ids and joint names,
only the stamps and the numbers differ. For such a group the fields are read at fixed byte
offsets as columns. A group is checked first:

* its *structure* (every byte but the stamp and the float data: the encapsulation, string lengths
  and contents, sequence counts, padding) equals that of a template message, and
* the template decodes with rosbags, and the extractor of :mod:`.messages` gives bit for bit the
  stamp and values read at the offsets (the layout is derived from the template's own strings).

Only floats and the stamp may differ within a group, and any bit pattern of those decodes, so every
message of the group decodes as rosbags would decode it, to the same numbers. A message outside every
group (malformed bytes, an odd layout, a big-endian encapsulation) takes the per-message path of
:mod:`.reader`, with its rejections. The result is the same samples, in the same (log time) order.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from transplanter_ident.bags.messages import (
    FLOAT32,
    FLOAT64,
    IMU,
    JOINT_STATE,
    ODOMETRY,
    POSE_COV_STAMPED,
    QUATERNION_STAMPED,
    TWIST_COV_STAMPED,
    TWIST_STAMPED,
    TYPESTORE,
    VECTOR3_STAMPED,
)
from transplanter_ident.epochs.frames import YAW_VARIANCE_IMU, YAW_VARIANCE_POSE

CDR_LE = b"\x00\x01\x00\x00"
#: templates tried per message length of a connection before the rest go one by one (a message that cannot
#: be one goes one by one itself)
MAX_TEMPLATES = 4
#: the byte offset of the CDR payload (after the encapsulation header)
PAYLOAD = 4


@dataclass(frozen=True)
class Layout:
    """Where one message type's wanted fields lie in a template message (absolute byte offsets)."""

    size: int  # the message length in bytes
    stamped: bool  # header.stamp at PAYLOAD (sec int32, nanosec uint32)
    fields: tuple[int, ...]  # offsets of the float values, in the extractor's order
    data: tuple[tuple[int, int], ...]  # [start, end) byte ranges of float data (excluded from the structure)
    itemsize: int = 8  # bytes per value: float64, or 4 for std_msgs/Float32


def _u32(buf: bytes, pos: int) -> int:
    return struct.unpack_from("<I", buf, PAYLOAD + pos)[0]


def _align(pos: int, n: int) -> int:
    return (pos + n - 1) // n * n


def _string_end(buf: bytes, pos: int) -> int:
    """Payload position after a CDR string that starts (before alignment) at ``pos``."""
    pos = _align(pos, 4)
    return pos + 4 + _u32(buf, pos)


def _seq_f64(buf: bytes, pos: int) -> tuple[int, int, int]:
    """(data start, count, end) of a sequence<float64> that starts at ``pos`` (payload positions)."""
    pos = _align(pos, 4)
    count = _u32(buf, pos)
    start = _align(pos + 4, 8) if count else pos + 4
    return start, count, start + 8 * count


def _fixed(buf: bytes, extra: int, offsets: Sequence[int]) -> Layout:
    """A header, then ``extra`` bytes of float64 fields: the wanted ones at ``offsets`` after the header."""
    base = _align(_string_end(buf, 8), 8)
    return Layout(PAYLOAD + base + extra, True, tuple(PAYLOAD + base + o for o in offsets),
                  ((PAYLOAD + base, PAYLOAD + base + extra),))


def _odometry(buf: bytes, role: str) -> Layout:
    base = _align(_string_end(buf, _string_end(buf, 8)), 8)
    offsets = (344, 352, 392, 392 + 56) if role == "velocity" else (24, 32, 40, 48, 56 + 8 * YAW_VARIANCE_POSE)
    return Layout(PAYLOAD + base + 680, True, tuple(PAYLOAD + base + o for o in offsets),
                  ((PAYLOAD + base, PAYLOAD + base + 680),))


def _joint_state(buf: bytes, index: int) -> Layout:
    pos = _align(_string_end(buf, 8), 4)
    names = _u32(buf, pos)
    pos += 4
    for _ in range(names):
        pos = _string_end(buf, pos)
    data = []
    for _ in range(3):  # position, velocity, effort
        start, count, pos = _seq_f64(buf, pos)
        data.append((PAYLOAD + start, PAYLOAD + pos))
    return Layout(PAYLOAD + pos, True, (data[0][0] + 8 * index,), tuple(data))


def layout_of(msgtype: str, buf: bytes, role: str, template: Any, joint: str) -> Layout | None:
    """The layout of ``buf`` (a template message of ``msgtype``, decoded as ``template``), or None."""
    if msgtype == TWIST_STAMPED:
        return _fixed(buf, 48, (0, 8, 40) if role == "truth_velocity" else (0, 8))
    if msgtype == TWIST_COV_STAMPED:
        return _fixed(buf, 48 + 288, (0, 8, 48, 48 + 56))
    if msgtype == QUATERNION_STAMPED:
        return _fixed(buf, 32, (0, 8, 16, 24))
    if msgtype == IMU:  # orientation, then orientation_covariance[YAW_VARIANCE_IMU]
        return _fixed(buf, 296, (0, 8, 16, 24, 32 + 8 * YAW_VARIANCE_IMU))
    if msgtype == POSE_COV_STAMPED:  # pose.orientation, then pose.covariance[YAW_VARIANCE_POSE]
        return _fixed(buf, 344, (24, 32, 40, 48, 56 + 8 * YAW_VARIANCE_POSE))
    if msgtype == VECTOR3_STAMPED:
        return _fixed(buf, 24, (0, 8, 16))
    if msgtype == ODOMETRY:
        return _odometry(buf, role)
    if msgtype == JOINT_STATE:
        names = list(template.name)
        return _joint_state(buf, names.index(joint)) if joint in names else None
    if msgtype == FLOAT64:
        return Layout(PAYLOAD + 8, False, (PAYLOAD,), ((PAYLOAD, PAYLOAD + 8),))
    if msgtype == FLOAT32:
        return Layout(PAYLOAD + 4, False, (PAYLOAD,), ((PAYLOAD, PAYLOAD + 4),), itemsize=4)
    return None


def width_of(msgtype: str, role: str) -> int:
    """How many values the extractor of ``msgtype`` gives for ``role`` (:mod:`.messages`)."""
    if msgtype in (JOINT_STATE, FLOAT64, FLOAT32):
        return 1
    if msgtype == TWIST_STAMPED:
        return 3 if role == "truth_velocity" else 2
    if msgtype in (IMU, POSE_COV_STAMPED) or (msgtype == ODOMETRY and role == "heading"):
        return 5  # the quaternion and the yaw variance
    return 3 if msgtype == VECTOR3_STAMPED else 4


def _structure_mask(layout: Layout) -> np.ndarray:
    mask = np.ones(layout.size, dtype=bool)
    if layout.stamped:
        mask[PAYLOAD:PAYLOAD + 8] = False
    for start, end in layout.data:
        mask[start:end] = False
    return mask


def _columns(rows: np.ndarray, layout: Layout, log_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(stamps s, values n x k) of equally laid-out messages (rows: n x size uint8), as the extractors give them."""
    values = np.empty((rows.shape[0], len(layout.fields)), dtype=np.float64)
    kind = "<f8" if layout.itemsize == 8 else "<f4"  # a float32 widens exactly, as float(msg.data) does
    for j, offset in enumerate(layout.fields):
        values[:, j] = np.ascontiguousarray(rows[:, offset:offset + layout.itemsize]).view(kind)[:, 0]
    log_s = log_ns / 1e9
    if not layout.stamped:
        return log_s, values
    sec = np.ascontiguousarray(rows[:, PAYLOAD:PAYLOAD + 4]).view("<i4")[:, 0].astype(np.int64)
    nanosec = np.ascontiguousarray(rows[:, PAYLOAD + 4:PAYLOAD + 8]).view("<u4")[:, 0].astype(np.int64)
    stamps = (sec * 1_000_000_000 + nanosec) / 1e9
    return np.where((sec != 0) | (nanosec != 0), stamps, log_s), values


def _same(a: tuple[float, tuple[float, ...]], b: tuple[float, tuple[float, ...]]) -> bool:
    """Bit for bit equal (stamp, values)."""
    return len(a[1]) == len(b[1]) and np.array([a[0], *a[1]]).tobytes() == np.array([b[0], *b[1]]).tobytes()


@dataclass
class Decoded:
    """Samples of one (connection, role) in message order: ``index`` into the pass, stamps, values."""

    index: np.ndarray  # int64, message number in the pass
    stamps: np.ndarray
    values: np.ndarray  # n x k
    slow: np.ndarray  # int64, message numbers left to the per-message path


Extract = Callable[[Any, int, str], tuple[float, tuple[float, ...]]]


def decode_connection(msgtype: str, role: str, extract: Extract, joint: str, index: np.ndarray,
                      log_ns: np.ndarray, datas: Sequence[bytes], width: int) -> Decoded:
    """Decode the messages ``datas`` (numbers ``index``, log times ``log_ns``) of one connection in groups."""
    lengths = np.fromiter((len(d) for d in datas), dtype=np.int64, count=len(datas))
    out_index, out_stamps, out_values, slow = [], [], [], []
    for length in np.unique(lengths):
        members = np.flatnonzero(lengths == length)
        rows = np.frombuffer(b"".join([datas[i] for i in members]), dtype=np.uint8).reshape(len(members), int(length))
        for _ in range(MAX_TEMPLATES):
            if not len(members):
                break
            layout = _template_layout(msgtype, role, extract, joint, rows[0].tobytes(), int(log_ns[members[0]]))
            if layout is None or layout.size != length or len(layout.fields) != width:
                slow.append(index[members[:1]])  # this one goes alone; the next may serve as the template
                members, rows = members[1:], rows[1:]
                continue
            mask = _structure_mask(layout)
            match = np.all(rows[:, mask] == rows[0, mask], axis=1)
            stamps, values = _columns(rows[match], layout, log_ns[members[match]])
            last = int(np.flatnonzero(match)[-1])
            if not _decodes_to(msgtype, extract, joint, rows[last].tobytes(), int(log_ns[members[last]]),
                               (float(stamps[-1]), tuple(values[-1].tolist()))):
                break
            out_index.append(index[members[match]])
            out_stamps.append(stamps)
            out_values.append(values)
            members, rows = members[~match], rows[~match]
        slow.append(index[members])
    cat = (lambda parts, empty: np.concatenate(parts) if parts else empty)  # noqa: E731
    order_index = cat(out_index, np.zeros(0, np.int64))
    order = np.argsort(order_index, kind="stable")
    return Decoded(order_index[order], cat(out_stamps, np.zeros(0))[order],
                   cat(out_values, np.zeros((0, width)))[order], np.sort(cat(slow, np.zeros(0, np.int64))))


def _decodes_to(msgtype: str, extract: Extract, joint: str, buf: bytes, log_ns: int,
                expected: tuple[float, tuple[float, ...]]) -> bool:
    try:
        return _same(extract(TYPESTORE.deserialize_cdr(buf, msgtype), log_ns, joint), expected)
    except Exception:  # noqa: BLE001 - the per-message path decides
        return False


def _template_layout(msgtype: str, role: str, extract: Extract, joint: str, buf: bytes, log_ns: int) -> Layout | None:
    """The layout of one message if it decodes and its fields read at the offsets match the extractor's."""
    if buf[:PAYLOAD] != CDR_LE:
        return None
    try:
        msg = TYPESTORE.deserialize_cdr(buf, msgtype)
        expected = extract(msg, log_ns, joint)
        layout = layout_of(msgtype, buf, role, msg, joint)
    except Exception:  # noqa: BLE001 - any failure: the per-message path decides (and says why)
        return None
    if layout is None or layout.size != len(buf):
        return None
    rows = np.frombuffer(buf, dtype=np.uint8).reshape(1, -1)
    stamps, values = _columns(rows, layout, np.array([log_ns], dtype=np.int64))
    return layout if _same(expected, (float(stamps[0]), tuple(values[0]))) else None
