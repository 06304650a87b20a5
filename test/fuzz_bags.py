"""Seeded bad bags for the fuzz suite (test_fuzz.py): mutations of one small simulated bag.

Two kinds, each a function ``(rng, base) -> Mutant``:

* message-level (:data:`MESSAGE_MUTATIONS`): the base bag's messages are decoded once, copied,
  changed (NaN/huge fields, reversed/duplicate/future/past/out-of-range stamps, dropped or
  repeated messages, bad quaternions, missing or duplicate joints, standing or reversing) and
  written again with :class:`transplanter_ident.bags.BagWriter`;
* byte-level (:data:`BYTE_MUTATIONS`): the MCAP file or metadata.yaml is damaged (truncated,
  flipped or zeroed bytes, a chunk dropped or repeated, counts that lie, metadata missing or garbage).

No ROS; rosbags only through the package's bags layer.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import random
import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from transplanter_ident.bags import TYPESTORE, BagWriter, open_reader
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.simulator import simulate

INPUTS = ("/gnss/vel", "/gnss/heading", "/steering_angle")
TRUTH_CF, TRUTH_CR = 8000.0, 10000.0  # the sine scenario's stiffness (per tire)
BAD_FLOATS = (math.nan, math.inf, -math.inf, 1.0e300, -1.0e300, 1.0e30, -1.0e-300, 0.0, 5.0e8)
MCAP_MAGIC = b"\x89MCAP0\r\n"
CHUNK_OPCODE = 0x06


@dataclass
class Message:
    topic: str
    msgtype: str
    msg: Any  # a rosbags message (mutable dataclass)
    log_ns: int


@dataclass
class Base:
    """The base bag (a rosbag2 directory) and its messages, decoded once."""

    path: Path
    messages: list[Message]

    def copy_messages(self) -> list[Message]:
        return [Message(m.topic, m.msgtype, copy.deepcopy(m.msg), m.log_ns) for m in self.messages]


@dataclass
class Mutant:
    """What a mutation did: a one-line description; ``write`` builds the bag at a path."""

    description: str
    write: Callable[[Path], None]
    params: dict[str, Any] = field(default_factory=dict)  # extra parameters (ekf, gnss) for replay


def make_base(directory: Path, seed: int = 1, duration: float = 20.0) -> Base:
    """A 20 s sine drive at 2 m/s: GNSS 5 Hz, steering 20 Hz, with the ground truth (about 800 messages)."""
    from transplanter_ident.bags import write_sim_bag

    path = directory / "base"
    write_sim_bag(simulate(build_config("sine", duration=duration, gnss_rate=5.0, steering_rate=20.0, seed=seed)),
                  path)
    messages = []
    with open_reader(path) as reader:
        for conn, log_ns, data in reader.messages():
            messages.append(Message(conn.topic, conn.msgtype, TYPESTORE.deserialize_cdr(data, conn.msgtype), log_ns))
    return Base(path, messages)


def write_messages(messages: list[Message], path: Path) -> None:
    with BagWriter(path) as bag:
        for m in messages:
            bag.write(m.topic, m.msgtype, m.msg, m.log_ns)


def _inputs(messages: list[Message]) -> list[Message]:
    return [m for m in messages if m.topic in INPUTS]


def _numeric_fields(msg: Any, prefix: str = "") -> list[tuple[Any, str]]:
    """(owner, attribute) of every float field (and float array) of a message."""
    out = []
    for f in dataclasses.fields(msg):
        value = getattr(msg, f.name)
        if dataclasses.is_dataclass(value):
            out.extend(_numeric_fields(value))
        elif isinstance(value, float) or (isinstance(value, np.ndarray) and value.dtype.kind == "f"):
            out.append((msg, f.name))
    return out


def _set_float(owner: Any, name: str, value: float, rng: random.Random) -> None:
    current = getattr(owner, name)
    if isinstance(current, np.ndarray):
        if current.size:
            current = current.copy()
            current[rng.randrange(current.size)] = value
            setattr(owner, name, current)
    else:
        setattr(owner, name, value)


def _stamp_ns(msg: Any) -> int | None:
    header = getattr(msg, "header", None)
    return None if header is None else header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def _set_stamp(msg: Any, sec: int, nanosec: int) -> None:
    if getattr(msg, "header", None) is not None:
        msg.header.stamp.sec = max(-(2**31), min(2**31 - 1, int(sec)))
        msg.header.stamp.nanosec = max(0, min(2**32 - 1, int(nanosec)))


def _shift_stamp(msg: Any, seconds: float) -> None:
    ns = _stamp_ns(msg)
    if ns is not None:
        total = ns + round(seconds * 1e9)
        _set_stamp(msg, total // 1_000_000_000, total % 1_000_000_000)


def _pick(rng: random.Random, messages: list[Message], count: int) -> list[Message]:
    pool = _inputs(messages)
    return rng.sample(pool, min(count, len(pool)))


def _message_mutant(description: str, change: Callable[[list[Message]], list[Message] | None], base: Base,
                    params: dict[str, Any] | None = None) -> Mutant:
    def write(path: Path) -> None:
        messages = base.copy_messages()
        changed = change(messages)
        write_messages(messages if changed is None else changed, path)

    return Mutant(description, write, params or {})


# --------------------------------------------------------------------------- message-level mutations


def bad_fields(rng: random.Random, base: Base) -> Mutant:
    count = rng.choice((1, 3, 10, 40))
    value = rng.choice(BAD_FLOATS)

    def change(messages: list[Message]) -> None:
        for m in _pick(rng, messages, count):
            fields = _numeric_fields(m.msg)
            if fields:
                owner, name = rng.choice(fields)
                _set_float(owner, name, value, rng)

    return _message_mutant(f"{count} input fields set to {value!r}", change, base)


def stamp_jumps(rng: random.Random, base: Base) -> Mutant:
    kind = rng.choice(("future", "past", "far_future", "reversed", "duplicate", "zero", "nanosec_overflow"))
    count = rng.choice((1, 2, 5))

    def change(messages: list[Message]) -> None:
        picked = _pick(rng, messages, count)
        for m in picked:
            ns = _stamp_ns(m.msg)
            if ns is None:
                continue
            if kind == "future":
                _shift_stamp(m.msg, rng.choice((0.5, 5.0, 60.0, 3600.0)))
            elif kind == "past":
                _shift_stamp(m.msg, -rng.choice((0.5, 5.0, 60.0, 3600.0)))
            elif kind == "far_future":
                _set_stamp(m.msg, 2**31 - 1, 999_999_999)
            elif kind == "reversed":
                _shift_stamp(m.msg, -0.3)
            elif kind == "duplicate":
                _shift_stamp(m.msg, -0.05)
            elif kind == "zero":
                _set_stamp(m.msg, 0, 0)
            else:
                _set_stamp(m.msg, ns // 1_000_000_000, 2**32 - 1)

    return _message_mutant(f"{count} input stamp(s) {kind}", change, base)


def stamps_out_of_range(rng: random.Random, base: Base) -> Mutant:
    """Every stamp moved near an end of the int32 seconds range (the log times stay)."""
    where = rng.choice(("negative", "int32_end", "int32_end_nanosec"))

    def change(messages: list[Message]) -> None:
        first = min(ns for m in messages if (ns := _stamp_ns(m.msg)) is not None)
        for m in messages:
            ns = _stamp_ns(m.msg)
            if ns is None:
                continue
            offset = (ns - first) / 1e9
            if where == "negative":
                _shift_stamp(m.msg, -first / 1e9 - 100.0)
            elif where == "int32_end":
                _set_stamp(m.msg, 2**31 - 30 + int(offset), ns % 1_000_000_000)
            else:
                _set_stamp(m.msg, 2**31 - 1, min(2**32 - 1, int(offset * 1e8)))

    return _message_mutant(f"stamps moved: {where}", change, base)


def drop_or_repeat(rng: random.Random, base: Base) -> Mutant:
    kind = rng.choice(("drop", "repeat", "drop_topic_half", "shuffle_window"))
    fraction = rng.choice((0.05, 0.2, 0.4))

    def change(messages: list[Message]) -> list[Message]:
        if kind == "drop":
            return [m for m in messages if m.topic not in INPUTS or rng.random() >= fraction]
        if kind == "repeat":
            out = []
            for m in messages:
                out.append(m)
                if m.topic in INPUTS and rng.random() < fraction:
                    out.append(Message(m.topic, m.msgtype, copy.deepcopy(m.msg), m.log_ns))
            return out
        if kind == "drop_topic_half":
            topic = rng.choice(INPUTS)
            stamps = sorted(m.log_ns for m in messages)
            cut = stamps[len(stamps) // 2]
            return [m for m in messages if not (m.topic == topic and m.log_ns > cut)]
        start = rng.randrange(len(messages) - 40)
        window = messages[start:start + 40]
        payloads = [(m.topic, m.msgtype, m.msg) for m in window]
        rng.shuffle(payloads)
        for m, (topic, msgtype, msg) in zip(window, payloads, strict=True):
            m.topic, m.msgtype, m.msg = topic, msgtype, msg
        return messages

    return _message_mutant(f"messages {kind} ({fraction:g})", change, base)


def bad_orientation_or_joint(rng: random.Random, base: Base) -> Mutant:
    kind = rng.choice(("quaternion_norm_3", "zero_quaternion", "joint_missing", "joint_duplicate", "no_position",
                       "empty_names"))
    count = rng.choice((1, 5, 30))

    def change(messages: list[Message]) -> None:
        heading = [m for m in messages if m.topic == "/gnss/heading"]
        steering = [m for m in messages if m.topic == "/steering_angle"]
        for m in rng.sample(heading if kind.endswith("quaternion") or kind.startswith("quaternion") else steering,
                            count):
            if kind == "quaternion_norm_3":
                q = m.msg.quaternion
                q.x, q.y, q.z, q.w = 3 * q.x, 3 * q.y, 3 * q.z, 3 * q.w
            elif kind == "zero_quaternion":
                q = m.msg.quaternion
                q.x = q.y = q.z = q.w = 0.0
            elif kind == "joint_missing":
                m.msg.name = ["rear_steering"]
            elif kind == "joint_duplicate":
                m.msg.name = ["front_steering", "front_steering"]
                m.msg.position = np.array([float(m.msg.position[0]), 0.6])
            elif kind == "no_position":
                m.msg.position = np.zeros(0)
            else:
                m.msg.name = []

    return _message_mutant(f"{count} {kind}", change, base)


def motion(rng: random.Random, base: Base) -> Mutant:
    """Standing, reversing or absurdly fast for a stretch (velocity scaled)."""
    factor = rng.choice((0.0, -1.0, 0.05, 60.0))

    def change(messages: list[Message]) -> None:
        vel = [m for m in messages if m.topic == "/gnss/vel"]
        start = rng.randrange(len(vel) // 2)
        for m in vel[start:start + len(vel) // 3]:
            m.msg.twist.linear.x *= factor
            m.msg.twist.linear.y *= factor

    return _message_mutant(f"velocity scaled by {factor:g} for a third of the drive", change, base)


def bad_parameters(rng: random.Random, base: Base) -> Mutant:
    """The clean bag with extreme (valid) parameters."""
    params = rng.choice((
        {"gnss": {"delay": -1.0}}, {"gnss": {"delay": 10.0}}, {"gnss": {"pairing_tolerance": 0.001}},
        {"ekf": {"min_speed": 20.0}}, {"ekf": {"process_noise": [1.0e6, 1.0e6, 1.0e6, 1.0e6]}},
        {"ekf": {"measurement_noise": [1.0e6, 1.0e6]}}, {"ekf": {"measurement_noise": [1.0e-300, 1.0e-300]}},
        {"ekf": {"initial_covariance": [1.0e10, 1.0e10, 1.0e10, 1.0e10]}}, {"ekf": {"max_interval": 0.001}},
        {"ekf": {"stiffness_state": "linear", "discretization": "euler"}}, {"ekf": {"measurement": "yaw_rate"}},
        {"vehicle": {"max_steering": 0.001}}, {"vehicle": {"mass": 1.0e5, "lf": 20.0, "lr": 0.01}},
    ))
    return Mutant(f"parameters {params}", lambda path: shutil.copytree(base.path, path), params)


MESSAGE_MUTATIONS = (bad_fields, stamp_jumps, stamps_out_of_range, drop_or_repeat, bad_orientation_or_joint, motion,
                     bad_parameters)


# --------------------------------------------------------------------------- byte-level mutations


def _mcap(base: Base) -> tuple[Path, bytes]:
    path = next(base.path.glob("*.mcap"))
    return path, path.read_bytes()


def _byte_mutant(description: str, base: Base, data: bytes | None, metadata: str | None = None,
                 drop_metadata: bool = False) -> Mutant:
    def write(path: Path) -> None:
        shutil.copytree(base.path, path)
        mcap = next(path.glob("*.mcap"))
        if data is not None:
            mcap.write_bytes(data)
        if drop_metadata:
            (path / "metadata.yaml").unlink()
        elif metadata is not None:
            (path / "metadata.yaml").write_text(metadata)

    return Mutant(description, write)


def _records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of the top-level MCAP records after the magic (stops at anything malformed)."""
    out, pos = [], len(MCAP_MAGIC)
    while pos + 9 <= len(data) - len(MCAP_MAGIC):
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        end = pos + 9 + length
        if end > len(data):
            break
        out.append((opcode, pos, end))
        pos = end
    return out


def truncate(rng: random.Random, base: Base) -> Mutant:
    _, data = _mcap(base)
    cut = rng.randrange(len(data))
    return _byte_mutant(f"mcap truncated at {cut}/{len(data)} bytes", base, data[:cut])


def flip_bytes(rng: random.Random, base: Base) -> Mutant:
    _, data = _mcap(base)
    out = bytearray(data)
    count = rng.choice((1, 4, 16, 64))
    start = rng.randrange(len(out))
    for k in range(count):
        out[(start + k * rng.choice((1, 7))) % len(out)] ^= rng.randrange(1, 256)
    return _byte_mutant(f"{count} bytes flipped from {start}", base, bytes(out))


def zero_range(rng: random.Random, base: Base) -> Mutant:
    _, data = _mcap(base)
    start = rng.randrange(len(data))
    length = rng.choice((8, 100, 1000))
    out = data[:start] + bytes(min(length, len(data) - start)) + data[start + length:]
    return _byte_mutant(f"{length} bytes zeroed from {start}", base, out)


def chunks(rng: random.Random, base: Base) -> Mutant:
    _, data = _mcap(base)
    found = [r for r in _records(data) if r[0] == CHUNK_OPCODE]
    if not found:
        return flip_bytes(rng, base)
    _, start, end = rng.choice(found)
    if rng.random() < 0.6:
        return _byte_mutant(f"chunk at {start} dropped", base, data[:start] + data[end:])
    return _byte_mutant(f"chunk at {start} repeated", base, data[:end] + data[start:end] + data[end:])


def metadata(rng: random.Random, base: Base) -> Mutant:
    text = (base.path / "metadata.yaml").read_text()
    kind = rng.choice(("missing", "garbage", "counts_up", "counts_down", "empty"))
    if kind == "missing":
        return _byte_mutant("metadata.yaml missing", base, None, drop_metadata=True)
    if kind == "garbage":
        return _byte_mutant("metadata.yaml garbage", base, None, "rosbag2_bagfile_information: [\n  {{{{: &a *a\n")
    if kind == "empty":
        return _byte_mutant("metadata.yaml empty", base, None, "")
    step = 7 if kind == "counts_up" else -7
    changed = text.replace("message_count: 101", f"message_count: {101 + step}")
    return _byte_mutant(f"metadata.yaml {kind}", base, None, changed)


def garbage_file(rng: random.Random, base: Base) -> Mutant:
    kind = rng.choice(("random", "empty", "magic_only"))
    _, data = _mcap(base)
    body = {"random": rng.randbytes(len(data)), "empty": b"", "magic_only": MCAP_MAGIC + MCAP_MAGIC}[kind]
    return _byte_mutant(f"mcap replaced: {kind}", base, body)


BYTE_MUTATIONS = (truncate, flip_bytes, zero_range, chunks, metadata, garbage_file)
