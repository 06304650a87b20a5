"""Reading and writing rosbag2 bags (MCAP) with rosbags; the only module that imports rosbags.

Reading (``replay``, ``tuner``): a rosbag2 directory (with ``metadata.yaml``) or a single
``.mcap`` file. The configured velocity, heading and steering topics are read in every
accepted message type (DESIGN.md section 3) into ``(role, stamp, values)`` samples, streamed
in log-time order, and turned into epochs by :class:`transplanter_ident.measurements.EpochAssembler`,
the same conversion the node uses:

* velocity, ``geometry_msgs/TwistStamped`` or ``TwistWithCovarianceStamped``: ``(linear.x, linear.y)``;
* heading, ``geometry_msgs/QuaternionStamped`` or ``sensor_msgs/Imu``: ``(yaw,)`` of the quaternion,
  ``atan2(2(wz + xy), 1 - 2(y^2 + z^2))``;
* steering, ``sensor_msgs/JointState`` (joint ``steering.joint_name``) or ``std_msgs/Float64``: ``(angle,)``.

The stamp is ``header.stamp`` in seconds; ``std_msgs/Float64`` has no header and a zero header
stamp means "unset", so those use the log time. Only the wanted connections are read
(``Reader.messages``), each message is deserialised with the Jazzy typestore and its fields are
taken by an extractor chosen once per connection.

Writing: :class:`BagWriter` writes an MCAP rosbag2 directory with the ROS 2 Jazzy typestore,
atomically (built under a temporary name, renamed when complete). :func:`write_sim_bag` writes a
simulated run (inputs plus ``/sim/*`` ground truth); :func:`write_output_bag` the node's outputs.

Every failure is a :class:`BagError` with a one-line message naming the bag and the reason.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from .cli_util import Progress, atomic_output_dir, one_line
from .measurements import (
    AssemblerSettings,
    EpochArrays,
    EpochAssembler,
    Rejection,
    assemble,
    quaternion_yaw,
    stamp_seconds,
)

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
TWIST_COV_STAMPED = "geometry_msgs/msg/TwistWithCovarianceStamped"
QUATERNION_STAMPED = "geometry_msgs/msg/QuaternionStamped"
IMU = "sensor_msgs/msg/Imu"
JOINT_STATE = "sensor_msgs/msg/JointState"
FLOAT64 = "std_msgs/msg/Float64"
VECTOR3_STAMPED = "geometry_msgs/msg/Vector3Stamped"

ROLES = ("velocity", "heading", "steering")
#: message types accepted per input role (DESIGN.md section 3)
ACCEPTED_TYPES: dict[str, tuple[str, ...]] = {
    "velocity": (TWIST_STAMPED, TWIST_COV_STAMPED),
    "heading": (QUATERNION_STAMPED, IMU),
    "steering": (JOINT_STATE, FLOAT64),
}

TRUTH_STIFFNESS_TOPIC = "/sim/cornering_stiffness"  # Vector3Stamped: x = Cf, y = Cr
TRUTH_VELOCITY_TOPIC = "/sim/body_velocity"  # TwistStamped at the CG: linear.x vx, linear.y vy, angular.z r

#: the node's outputs (DESIGN.md section 3), relative to its namespace
OUTPUT_NAMESPACE = "/estimator"
OUTPUT_STIFFNESS = "cornering_stiffness"
OUTPUT_STIFFNESS_STD = "cornering_stiffness_std"
OUTPUT_MODEL = "model_output"
OUTPUT_MEASUREMENT = "measurement"
OUTPUT_FRAME_ID = "base_link"

NS_PER_S = 1_000_000_000


class BagError(ValueError):
    """A bag that cannot be read or written; the message is one line naming the bag and the reason."""

    def __init__(self, message: str) -> None:
        super().__init__(one_line(message))


def seconds(ns: int) -> float:
    """Nanoseconds to seconds (the one conversion used for header stamps and log times)."""
    return ns / 1e9


def to_ns(t: float) -> int:
    """Seconds to integer nanoseconds (rounded)."""
    return int(round(t * 1e9))


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a pure rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def normalize_msgtype(msgtype: str) -> str:
    """``pkg/Type`` -> ``pkg/msg/Type``; ROS 2 names pass unchanged."""
    parts = msgtype.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else msgtype


# --------------------------------------------------------------------------- field extraction


class _Unusable(Exception):
    """A message that deserialises but lacks what is needed (the reason is the message)."""


#: errors of deserialising one message's bytes (rosbags wraps struct/unicode/value errors in SerdeError)
_DECODE_ERRORS = (SerdeError, ValueError, IndexError)

#: (deserialised message, log ns, steering joint name) -> (stamp s, values)
Extractor = Callable[[Any, int, str], tuple[float, tuple[float, ...]]]


def _stamp(msg: Any, log_ns: int) -> float:
    """``header.stamp`` in seconds, or the log time when the stamp is zero (unset)."""
    stamp = msg.header.stamp
    return stamp_seconds(stamp.sec, stamp.nanosec) if (stamp.sec or stamp.nanosec) else seconds(log_ns)


def _from_twist(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    linear = msg.twist.linear
    return _stamp(msg, log_ns), (linear.x, linear.y)


def _from_twist_cov(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    linear = msg.twist.twist.linear
    return _stamp(msg, log_ns), (linear.x, linear.y)


def _from_quaternion(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    q = msg.quaternion
    return _stamp(msg, log_ns), (quaternion_yaw(q.x, q.y, q.z, q.w),)


def _from_imu(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    q = msg.orientation
    return _stamp(msg, log_ns), (quaternion_yaw(q.x, q.y, q.z, q.w),)


def _from_joint_state(msg: Any, log_ns: int, joint: str) -> tuple[float, tuple[float, ...]]:
    if joint not in msg.name:
        raise _Unusable(f"joint {joint!r} not in the JointState")
    index = msg.name.index(joint)
    if index >= len(msg.position):
        raise _Unusable(f"joint {joint!r} has no position")
    return _stamp(msg, log_ns), (float(msg.position[index]),)


def _from_float64(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    return seconds(log_ns), (float(msg.data),)


def _from_vector3(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    v = msg.vector
    return _stamp(msg, log_ns), (v.x, v.y, v.z)


def _from_twist_truth(msg: Any, log_ns: int, _joint: str) -> tuple[float, tuple[float, ...]]:
    twist = msg.twist
    return _stamp(msg, log_ns), (twist.linear.x, twist.linear.y, twist.angular.z)


#: extractor of the input samples per accepted message type
EXTRACTORS: dict[str, Extractor] = {
    TWIST_STAMPED: _from_twist,
    TWIST_COV_STAMPED: _from_twist_cov,
    QUATERNION_STAMPED: _from_quaternion,
    IMU: _from_imu,
    JOINT_STATE: _from_joint_state,
    FLOAT64: _from_float64,
    VECTOR3_STAMPED: _from_vector3,
}


def decode_message(msgtype: str, data: bytes, log_ns: int, joint_name: str = "front_steering") -> tuple:
    """Decode one serialized input message to ``(stamp s, values)`` as the reader does (for tests/tools)."""
    msgtype = normalize_msgtype(msgtype)
    return EXTRACTORS[msgtype](TYPESTORE.deserialize_cdr(data, msgtype), log_ns, joint_name)


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Truth:
    """Ground truth of a simulated bag, on the stiffness topic's clock (bag time, s)."""

    t: np.ndarray
    cf: np.ndarray  # N/rad per tire
    cr: np.ndarray
    vx: np.ndarray  # m/s at the CG (NaN when the bag has no body velocity)
    vy: np.ndarray
    r: np.ndarray  # rad/s

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(Cf, Cr) at times ``t``, linearly interpolated (held beyond the ends)."""
        return np.interp(t, self.t, self.cf), np.interp(t, self.t, self.cr)


@dataclass
class BagData:
    """What one pass over a bag produced."""

    path: Path
    epochs: EpochArrays
    rejections: list[Rejection]
    truth: Truth | None
    counts: dict[str, int]  # decoded messages per role (velocity, heading, steering, truth)
    notes: list[str] = field(default_factory=list)  # non-fatal remarks (ignored truth topics, ...)


def _resolve(path: str | Path) -> Path:
    """The path rosbags should open: a rosbag2 directory, or a single storage file."""
    bag = Path(path)
    if not bag.exists():
        raise BagError(f"{bag}: no such file or directory")
    if bag.is_dir():
        if (bag / "metadata.yaml").exists():
            return bag
        files = sorted(bag.glob("*.mcap"))
        if len(files) == 1:  # a rosbag2 directory whose recorder died before writing metadata.yaml
            return files[0]
        raise BagError(f"{bag}: not a rosbag2 directory (no metadata.yaml"
                       f"{' and several .mcap files' if files else ' and no .mcap file'})")
    if bag.suffix not in (".mcap", ".db3"):
        raise BagError(f"{bag}: not a rosbag2 directory or .mcap file")
    if bag.stat().st_size == 0:
        raise BagError(f"{bag}: the file is empty (0 bytes)")
    return bag


def _reason(exc: BaseException) -> str:
    text = one_line(exc).rstrip(".")
    if isinstance(exc, OSError) and exc.strerror:
        text = exc.strerror
    return text or type(exc).__name__


@contextmanager
def open_reader(path: str | Path) -> Iterator[Reader]:
    """Open a bag for reading (rosbags ``Reader``); every failure becomes a :class:`BagError`.

    Errors raised while iterating messages inside the ``with`` block are wrapped too.
    """
    bag = _resolve(path)
    try:
        reader = Reader(bag)
        reader.open()
    except BagError:
        raise
    except Exception as exc:
        hint = " (truncated or corrupt MCAP?)" if bag.suffix == ".mcap" or bag.is_dir() else ""
        raise BagError(f"{path}: cannot open bag: {_reason(exc)}{hint}") from exc
    try:
        yield reader
    except BagError:
        raise
    except Exception as exc:
        raise BagError(f"{path}: cannot read bag: {_reason(exc)} (truncated or corrupt?)") from exc
    finally:
        try:
            reader.close()
        except Exception:  # noqa: BLE001, S110 - closing a broken reader must not mask the real error
            pass


#: connection id -> (role, normalised message type, extractor)
_Table = dict[int, tuple[str, str, Extractor]]


def _topic_types(reader: Reader) -> dict[str, list[Any]]:
    topics: dict[str, list[Any]] = {}
    for conn in reader.connections:
        topics.setdefault(conn.topic, []).append(conn)
    return topics


def _select(path: str | Path, reader: Reader, params: Any) -> _Table:
    """The input connections; BagError if an input topic is missing, mistyped or empty."""
    if reader.message_count == 0:
        raise BagError(f"{path}: the bag is empty (no messages)")
    topics = _topic_types(reader)
    table: _Table = {}
    for role in ROLES:
        topic = getattr(params.topics, role)
        conns = topics.get(topic)
        if not conns:
            have = ", ".join(sorted(topics)) or "none"
            raise BagError(f"{path}: no topic {topic} (the {role} input, parameter topics.{role}); "
                           f"topics in the bag: {have}")
        good = [c for c in conns if normalize_msgtype(c.msgtype) in ACCEPTED_TYPES[role]]
        if not good:
            got = ", ".join(sorted({c.msgtype for c in conns}))
            raise BagError(f"{path}: topic {topic} has type {got}, but the {role} input accepts "
                           f"{' or '.join(ACCEPTED_TYPES[role])}")
        if sum(c.msgcount for c in good) == 0:
            raise BagError(f"{path}: topic {topic} (the {role} input) has no messages")
        for conn in good:
            msgtype = normalize_msgtype(conn.msgtype)
            table[conn.id] = (role, msgtype, EXTRACTORS[msgtype])
    return table


def _select_truth(reader: Reader, notes: list[str]) -> _Table:
    """The ground truth connections; mistyped ones are noted and ignored."""
    topics = _topic_types(reader)
    table: _Table = {}
    for topic, msgtype, role, extract in (
        (TRUTH_STIFFNESS_TOPIC, VECTOR3_STAMPED, "truth_stiffness", _from_vector3),
        (TRUTH_VELOCITY_TOPIC, TWIST_STAMPED, "truth_velocity", _from_twist_truth),
    ):
        for conn in topics.get(topic, []):
            if normalize_msgtype(conn.msgtype) == msgtype:
                table[conn.id] = (role, msgtype, extract)
            else:
                notes.append(f"ground truth topic {topic} has type {conn.msgtype}, not {msgtype}: ignored")
    return table


def _settings(params: Any) -> AssemblerSettings:
    vehicle = params.config.vehicle
    return AssemblerSettings(velocity_frame=params.frames.velocity, heading_frame=params.frames.heading,
                             antenna_x=vehicle.antenna_x, antenna_y=vehicle.antenna_y,
                             max_steering=vehicle.max_steering)


class _Scan:
    """One streaming pass: yields input samples, collects truth, unusable messages and counts."""

    def __init__(self, path: str | Path, params: Any, *, truth: bool, progress: bool) -> None:
        self.path = path
        self.params = params
        self.want_truth = truth
        self.progress = progress
        self.rejections: list[Rejection] = []
        self.notes: list[str] = []
        self.counts: Counter[str] = Counter()
        self.truth_rows: dict[str, list[tuple[float, tuple[float, ...]]]] = {"truth_stiffness": [],
                                                                            "truth_velocity": []}

    def samples(self) -> Iterator[tuple[str, float, tuple[float, ...]]]:
        joint = self.params.steering.joint_name
        deserialize = TYPESTORE.deserialize_cdr
        counts, truth_rows = self.counts, self.truth_rows
        with open_reader(self.path) as reader:
            table = _select(self.path, reader, self.params)
            if self.want_truth:
                table.update(_select_truth(reader, self.notes))
            connections = [c for c in reader.connections if c.id in table]
            progress = None
            if self.progress:
                progress = Progress(sum(c.msgcount for c in connections), f"reading {self.path}")
            next_report = progress.next_at if progress is not None else math.inf
            for n, (conn, log_ns, data) in enumerate(reader.messages(connections=connections), 1):
                if n >= next_report:
                    progress.update(n)
                    next_report = progress.next_at
                role, msgtype, extract = table[conn.id]
                try:
                    stamp, values = extract(deserialize(data, msgtype), log_ns, joint)
                except _Unusable as exc:
                    self.rejections.append(Rejection(role.removeprefix("truth_"), seconds(log_ns), str(exc)))
                    continue
                except _DECODE_ERRORS:
                    reason = f"undecodable {conn.msgtype} message"
                    self.rejections.append(Rejection(role.removeprefix("truth_"), seconds(log_ns), reason))
                    continue
                counts[role] += 1
                if role in truth_rows:
                    truth_rows[role].append((stamp, values))
                else:
                    yield role, stamp, values
            if progress is not None:
                progress.done()


def _build_truth(rows: dict[str, list[tuple[float, tuple[float, ...]]]]) -> Truth | None:
    stiffness = sorted(rows["truth_stiffness"], key=lambda row: row[0])
    if not stiffness:
        return None
    t = np.array([row[0] for row in stiffness])
    stiff = np.array([row[1] for row in stiffness])
    velocity = sorted(rows["truth_velocity"], key=lambda row: row[0])
    if velocity:
        tv = np.array([row[0] for row in velocity])
        vel = np.array([row[1] for row in velocity])
        vx, vy, r = (np.interp(t, tv, vel[:, i]) for i in range(3))
    else:
        vx = vy = r = np.full(len(t), np.nan)
    return Truth(t=t, cf=stiff[:, 0], cr=stiff[:, 1], vx=vx, vy=vy, r=r)


def read_samples(path: str | Path, params: Any,
                 rejections: list[Rejection] | None = None) -> Iterator[tuple[str, float, tuple[float, ...]]]:
    """Stream ``(role, stamp s, values)`` input samples in log-time order.

    ``role`` is ``velocity`` (values east/north or north/east by frame), ``heading`` (yaw) or
    ``steering`` (angle). Messages that do not decode (a JointState without the steering joint,
    malformed bytes) are skipped and appended to ``rejections`` if given. ``params`` is a
    ``params_file.EstimatorParams`` (topics, steering.joint_name are used).
    """
    scan = _Scan(path, params, truth=False, progress=False)
    try:
        yield from scan.samples()
    finally:
        if rejections is not None:
            rejections.extend(scan.rejections)


def read_bag(path: str | Path, params: Any, *, truth: bool = True, progress: bool = False) -> BagData:
    """One streaming pass: epochs (via the node's EpochAssembler), rejections, ground truth, counts.

    Raises :class:`BagError` when the bag cannot be read, an input topic is missing or mistyped,
    or no epoch can be formed.
    """
    scan = _Scan(path, params, truth=truth, progress=progress)
    assembler = EpochAssembler(_settings(params))
    epochs = assemble(assembler, scan.samples())
    rejections = scan.rejections + assembler.drain_rejections()
    rejections.sort(key=lambda r: r.stamp)
    counts = {role: scan.counts.get(role, 0) for role in ROLES}
    if not epochs:
        summary = ", ".join(f"{counts[r]} {r}" for r in ROLES)
        top = summarize_rejections(rejections)[:1]
        why = f"; most common rejection: {top[0][0]}: {top[0][1]} ({top[0][2]}x)" if top else ""
        raise BagError(f"{path}: no epoch could be formed from {summary} messages{why}")
    truth_data = _build_truth(scan.truth_rows) if truth else None
    if truth:
        counts["truth"] = scan.counts.get("truth_stiffness", 0)
    return BagData(Path(path), EpochArrays(epochs), rejections, truth_data, counts, scan.notes)


def read_epochs(path: str | Path, params: Any) -> tuple[EpochArrays, list[Rejection]]:
    """The bag's epochs and the rejected samples (one streaming pass, ground truth skipped)."""
    data = read_bag(path, params, truth=False)
    return data.epochs, data.rejections


def read_truth(path: str | Path) -> Truth | None:
    """The ``/sim/*`` ground truth of a simulated bag, or None when the bag has none."""
    rows: dict[str, list[tuple[float, tuple[float, ...]]]] = {"truth_stiffness": [], "truth_velocity": []}
    with open_reader(path) as reader:
        table = _select_truth(reader, [])
        if not table:
            return None
        connections = [c for c in reader.connections if c.id in table]
        for conn, log_ns, data in reader.messages(connections=connections):
            role, msgtype, extract = table[conn.id]
            try:
                rows[role].append(extract(TYPESTORE.deserialize_cdr(data, msgtype), log_ns, ""))
            except _DECODE_ERRORS as exc:
                raise BagError(f"{path}: malformed ground truth message on {conn.topic}: {_reason(exc)}") from exc
    return _build_truth(rows)


def summarize_rejections(rejections: Sequence[Rejection]) -> list[tuple[str, str, int]]:
    """(topic, reason, count), most frequent first; per-sample numbers in reasons are merged."""
    counts: Counter[tuple[str, str]] = Counter()
    for rejection in rejections:
        reason = rejection.reason
        if reason.startswith("|") and "beyond max_steering" in reason:
            reason = "beyond max_steering" + reason.split("beyond max_steering", 1)[1]
        counts[(rejection.topic, reason)] += 1
    return [(topic, reason, n) for (topic, reason), n in counts.most_common()]


# --------------------------------------------------------------------------- writing


def _types() -> dict[str, Any]:
    return TYPESTORE.types


def _header(stamp_ns: int, frame_id: str) -> Any:
    types = _types()
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                        frame_id=frame_id)


def _vector3(xyz: Sequence[float]) -> Any:
    return _types()["geometry_msgs/msg/Vector3"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def _quaternion(q: Sequence[float]) -> Any:
    return _types()["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


class BagWriter:
    """Write an MCAP rosbag2 directory (ROS 2 Jazzy types), atomically.

    Use as a context manager; the bag appears at ``path`` only when the block ends without
    an exception. Each ``write_*`` helper takes the header stamp in integer nanoseconds and
    uses it as the log time too (``log_ns`` overrides). Connections are added on first use.
    """

    def __init__(self, path: str | Path, *, compress: bool = False, overwrite: bool = False) -> None:
        self.path = Path(path)
        self.compress = compress
        self.overwrite = overwrite
        self._writer: Writer | None = None
        self._connections: dict[tuple[str, str], Any] = {}
        self._dir_context: Any = None
        self.count = 0

    def __enter__(self) -> BagWriter:
        try:
            self._dir_context = atomic_output_dir(self.path, overwrite=self.overwrite)
            staging = self._dir_context.__enter__()
            self._writer = Writer(staging, version=9, storage_plugin=StoragePlugin.MCAP)
            if self.compress:
                self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            self._writer.open()
        except Exception as exc:
            if self._dir_context is not None:
                self._dir_context.__exit__(type(exc), exc, exc.__traceback__)
            raise BagError(f"{self.path}: cannot write bag: {_reason(exc)}") from exc
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> bool:
        writer, self._writer = self._writer, None
        try:
            if writer is not None:
                if exc_type is None:
                    writer.close()
                else:
                    try:
                        writer.close()
                    except Exception:  # noqa: BLE001, S110 - the original error matters, the dir is discarded
                        pass
        except Exception as close_exc:
            self._dir_context.__exit__(type(close_exc), close_exc, close_exc.__traceback__)
            raise BagError(f"{self.path}: cannot write bag: {_reason(close_exc)}") from close_exc
        try:
            self._dir_context.__exit__(exc_type, exc, tb)
        except Exception as move_exc:
            if exc_type is None:
                raise BagError(f"{self.path}: cannot write bag: {_reason(move_exc)}") from move_exc
        return False

    def write(self, topic: str, msgtype: str, msg: Any, log_ns: int) -> None:
        """Serialize ``msg`` (a typestore message of ``msgtype``) and write it at ``log_ns``."""
        if self._writer is None:
            raise BagError(f"{self.path}: bag is not open for writing")
        key = (topic, msgtype)
        conn = self._connections.get(key)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=TYPESTORE)
            self._connections[key] = conn
        self._writer.write(conn, int(log_ns), TYPESTORE.serialize_cdr(msg, msgtype))
        self.count += 1

    def write_twist(self, topic: str, stamp_ns: int, linear: Sequence[float], angular: Sequence[float] = (0, 0, 0),
                    *, frame_id: str = "", log_ns: int | None = None) -> None:
        """geometry_msgs/TwistStamped."""
        types = _types()
        twist = types["geometry_msgs/msg/Twist"](linear=_vector3(linear), angular=_vector3(angular))
        msg = types[TWIST_STAMPED](header=_header(stamp_ns, frame_id), twist=twist)
        self.write(topic, TWIST_STAMPED, msg, stamp_ns if log_ns is None else log_ns)

    def write_twist_with_covariance(self, topic: str, stamp_ns: int, linear: Sequence[float],
                                    angular: Sequence[float] = (0, 0, 0), covariance: Sequence[float] | None = None,
                                    *, frame_id: str = "", log_ns: int | None = None) -> None:
        """geometry_msgs/TwistWithCovarianceStamped (covariance: 36 values, default zeros)."""
        types = _types()
        twist = types["geometry_msgs/msg/Twist"](linear=_vector3(linear), angular=_vector3(angular))
        cov = np.zeros(36) if covariance is None else np.asarray(covariance, dtype=np.float64).reshape(36)
        msg = types[TWIST_COV_STAMPED](header=_header(stamp_ns, frame_id),
                                       twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist,
                                                                                           covariance=cov))
        self.write(topic, TWIST_COV_STAMPED, msg, stamp_ns if log_ns is None else log_ns)

    def write_quaternion(self, topic: str, stamp_ns: int, quaternion: Sequence[float], *, frame_id: str = "",
                         log_ns: int | None = None) -> None:
        """geometry_msgs/QuaternionStamped; ``quaternion`` is (x, y, z, w)."""
        msg = _types()[QUATERNION_STAMPED](header=_header(stamp_ns, frame_id), quaternion=_quaternion(quaternion))
        self.write(topic, QUATERNION_STAMPED, msg, stamp_ns if log_ns is None else log_ns)

    def write_imu(self, topic: str, stamp_ns: int, orientation: Sequence[float], *, frame_id: str = "",
                  orientation_variance: float = 0.0, log_ns: int | None = None) -> None:
        """sensor_msgs/Imu carrying only an orientation (angular velocity and acceleration marked unknown)."""
        unknown = np.zeros(9)
        unknown[0] = -1.0  # REP 145: covariance[0] = -1 means "no estimate of this quantity"
        orientation_cov = np.zeros(9)
        orientation_cov[[0, 4, 8]] = orientation_variance
        msg = _types()[IMU](header=_header(stamp_ns, frame_id), orientation=_quaternion(orientation),
                            orientation_covariance=orientation_cov, angular_velocity=_vector3((0, 0, 0)),
                            angular_velocity_covariance=unknown, linear_acceleration=_vector3((0, 0, 0)),
                            linear_acceleration_covariance=unknown.copy())
        self.write(topic, IMU, msg, stamp_ns if log_ns is None else log_ns)

    def write_joint_state(self, topic: str, stamp_ns: int, names: Sequence[str], positions: Sequence[float], *,
                          frame_id: str = "", log_ns: int | None = None) -> None:
        """sensor_msgs/JointState with positions only."""
        empty = np.zeros(0)
        msg = _types()[JOINT_STATE](header=_header(stamp_ns, frame_id), name=list(names),
                                    position=np.asarray(positions, dtype=np.float64), velocity=empty,
                                    effort=empty)
        self.write(topic, JOINT_STATE, msg, stamp_ns if log_ns is None else log_ns)

    def write_float64(self, topic: str, log_ns: int, value: float) -> None:
        """std_msgs/Float64 (no header: the log time is its only stamp)."""
        self.write(topic, FLOAT64, _types()[FLOAT64](data=float(value)), log_ns)

    def write_vector3(self, topic: str, stamp_ns: int, xyz: Sequence[float], *, frame_id: str = "",
                      log_ns: int | None = None) -> None:
        """geometry_msgs/Vector3Stamped."""
        msg = _types()[VECTOR3_STAMPED](header=_header(stamp_ns, frame_id), vector=_vector3(xyz))
        self.write(topic, VECTOR3_STAMPED, msg, stamp_ns if log_ns is None else log_ns)


@dataclass(frozen=True)
class SimBagOptions:
    """How :func:`write_sim_bag` encodes a simulated run."""

    velocity_topic: str = "/gnss/vel"
    heading_topic: str = "/gnss/heading"
    steering_topic: str = "/steering_angle"
    velocity_type: str = "twist"  # twist | twist-cov
    heading_type: str = "quaternion"  # quaternion | imu
    steering_type: str = "joint-state"  # joint-state | float64
    velocity_frame: str = "enu"  # enu | ned
    heading_frame: str = "enu"  # enu | ned (compass heading, clockwise from north)
    joint_name: str = "front_steering"
    start_time: float = 1_700_000_000.0  # s, bag time of simulation time 0
    truth: bool = True
    compress: bool = False
    overwrite: bool = False
    gnss_frame_id: str = "gnss_link"
    velocity_std: float = 0.02  # m/s, reported in TwistWithCovarianceStamped
    heading_std: float = math.radians(0.2)  # rad, reported in Imu

    def __post_init__(self) -> None:
        for name, choices in (("velocity_type", ("twist", "twist-cov")), ("heading_type", ("quaternion", "imu")),
                              ("steering_type", ("joint-state", "float64")), ("velocity_frame", ("enu", "ned")),
                              ("heading_frame", ("enu", "ned"))):
            if getattr(self, name) not in choices:
                raise ValueError(f"{name} must be one of {', '.join(choices)}, got {getattr(self, name)!r}")


_STEER, _VEL, _HEAD, _TRUTH = 0, 1, 2, 3


def write_sim_bag(result: Any, path: str | Path, options: SimBagOptions | None = None) -> int:
    """Write a ``sim.SimResult`` as an MCAP rosbag2 directory; returns the number of messages.

    At equal times the steering sample is written before the GNSS velocity and heading (the
    steering at t_k is available when epoch t_k is formed), then the ground truth.
    """
    opt = options or SimBagOptions()
    start_ns = to_ns(opt.start_time)
    gnss_ns = start_ns + np.rint(np.asarray(result.gnss_time) * 1e9).astype(np.int64)
    steer_ns = start_ns + np.rint(np.asarray(result.steering_time) * 1e9).astype(np.int64)
    n_gnss, n_steer = len(gnss_ns), len(steer_ns)
    kinds = [np.full(n_steer, _STEER), np.full(n_gnss, _VEL), np.full(n_gnss, _HEAD)]
    times = [steer_ns, gnss_ns, gnss_ns]
    index = [np.arange(n_steer), np.arange(n_gnss), np.arange(n_gnss)]
    if opt.truth:
        kinds.append(np.full(n_gnss, _TRUTH))
        times.append(gnss_ns)
        index.append(np.arange(n_gnss))
    kind = np.concatenate(kinds)
    when = np.concatenate(times)
    idx = np.concatenate(index)
    order = np.lexsort((kind, when))

    vel = np.asarray(result.velocity_enu, dtype=np.float64)
    if opt.velocity_frame == "ned":
        vel = vel[:, ::-1]
    heading = np.asarray(result.heading, dtype=np.float64)
    if opt.heading_frame == "ned":  # compass heading, clockwise from north, in [0, 2 pi)
        heading = np.mod(math.pi / 2.0 - heading, 2.0 * math.pi)
    vel_cov = np.zeros(36)
    vel_cov[[0, 7, 14]] = opt.velocity_std**2
    vel_list, heading_list = vel.tolist(), heading.tolist()
    steer_list = np.asarray(result.steering, dtype=np.float64).tolist()
    gnss_list, steer_ns_list = gnss_ns.tolist(), steer_ns.tolist()
    truth = (np.column_stack([result.truth_cf, result.truth_cr]).tolist(),
             np.column_stack([result.truth_vx, result.truth_vy, result.truth_yaw_rate]).tolist())

    with BagWriter(path, compress=opt.compress, overwrite=opt.overwrite) as bag:
        for k, i in zip(kind[order].tolist(), idx[order].tolist(), strict=True):
            if k == _STEER:
                ns = steer_ns_list[i]
                if opt.steering_type == "float64":
                    bag.write_float64(opt.steering_topic, ns, steer_list[i])
                else:
                    bag.write_joint_state(opt.steering_topic, ns, [opt.joint_name], [steer_list[i]])
            elif k == _VEL:
                ns = gnss_list[i]
                linear = (vel_list[i][0], vel_list[i][1], 0.0)
                if opt.velocity_type == "twist-cov":
                    bag.write_twist_with_covariance(opt.velocity_topic, ns, linear, covariance=vel_cov,
                                                    frame_id=opt.gnss_frame_id)
                else:
                    bag.write_twist(opt.velocity_topic, ns, linear, frame_id=opt.gnss_frame_id)
            elif k == _HEAD:
                ns = gnss_list[i]
                q = yaw_quaternion(heading_list[i])
                if opt.heading_type == "imu":
                    bag.write_imu(opt.heading_topic, ns, q, frame_id=opt.gnss_frame_id,
                                  orientation_variance=opt.heading_std**2)
                else:
                    bag.write_quaternion(opt.heading_topic, ns, q, frame_id=opt.gnss_frame_id)
            else:
                ns = gnss_list[i]
                cf, cr = truth[0][i]
                vx, vy, r = truth[1][i]
                bag.write_vector3(TRUTH_STIFFNESS_TOPIC, ns, (cf, cr, 0.0), frame_id=OUTPUT_FRAME_ID)
                bag.write_twist(TRUTH_VELOCITY_TOPIC, ns, (vx, vy, 0.0), (0.0, 0.0, r), frame_id=OUTPUT_FRAME_ID)
        return bag.count


def write_output_bag(path: str | Path, epochs: EpochArrays, outputs: np.ndarray, *,
                     namespace: str = OUTPUT_NAMESPACE, overwrite: bool = False) -> int:
    """Write the node's output topics for every epoch, stamped (and logged) at the epoch time.

    Epochs whose outputs are not all finite are skipped (the node never publishes NaN).
    Returns the number of epochs written.
    """
    from .ekf import O_CF, O_CF_STD, O_CR, O_CR_STD, O_R_MODEL, O_VY_MODEL  # numba: only when needed

    ns_prefix = namespace.rstrip("/")
    topics = {name: f"{ns_prefix}/{name}" for name in (OUTPUT_STIFFNESS, OUTPUT_STIFFNESS_STD, OUTPUT_MODEL,
                                                       OUTPUT_MEASUREMENT)}
    cols = [O_CF, O_CR, O_CF_STD, O_CR_STD, O_VY_MODEL, O_R_MODEL]
    written = 0
    with BagWriter(path, overwrite=overwrite) as bag:
        t_ns = [to_ns(t) for t in epochs.t.tolist()]
        meas = np.column_stack([epochs.longitudinal_velocity, epochs.lateral_velocity, epochs.yaw_rate]).tolist()
        out = outputs[:, cols].tolist()
        for ns, (vx, vy, r), (cf, cr, cf_std, cr_std, vy_model, r_model) in zip(t_ns, meas, out, strict=True):
            if not all(math.isfinite(v) for v in (vx, vy, r, cf, cr, cf_std, cr_std, vy_model, r_model)):
                continue
            bag.write_vector3(topics[OUTPUT_STIFFNESS], ns, (cf, cr, 0.0), frame_id=OUTPUT_FRAME_ID)
            bag.write_vector3(topics[OUTPUT_STIFFNESS_STD], ns, (cf_std, cr_std, 0.0), frame_id=OUTPUT_FRAME_ID)
            bag.write_twist(topics[OUTPUT_MODEL], ns, (0.0, vy_model, 0.0), (0.0, 0.0, r_model),
                            frame_id=OUTPUT_FRAME_ID)
            bag.write_twist(topics[OUTPUT_MEASUREMENT], ns, (vx, vy, 0.0), (0.0, 0.0, r),
                            frame_id=OUTPUT_FRAME_ID)
            written += 1
    return written
