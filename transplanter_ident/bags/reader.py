"""Reading rosbag2 bags (MCAP) for ``replay`` and ``tuner``.

A bag is a rosbag2 directory (with ``metadata.yaml``) or a single ``.mcap`` file. The input
topics are streamed in log-time order as ``(role, stamp, values)`` samples (:mod:`.messages`)
and turned into epochs by :class:`transplanter_ident.epochs.assembler.EpochAssembler`, the same
conversion the node uses. :func:`read_bag` does the same in batches where that gives the same
result bit for bit (:mod:`.batch_read`, :mod:`transplanter_ident.epochs.batch`). Only the wanted connections are read (``Reader.messages``). A
simulated bag's ``/sim/*`` ground truth is read alongside.

Every failure is a :class:`~.errors.BagError` with a one-line message naming the bag and the reason.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader

from transplanter_ident.bags.batch_read import assemble_scan, message_samples, read_batch
from transplanter_ident.bags.errors import BagError
from transplanter_ident.bags.messages import (
    _DECODE_ERRORS,
    ACCEPTED_TYPES,
    INPUT_TYPES,
    ROLES,
    TRUTH_STIFFNESS_TOPIC,
    TRUTH_VELOCITY_TOPIC,
    TWIST_STAMPED,
    TYPESTORE,
    VECTOR3_STAMPED,
    Extractor,
    _from_twist_truth,
    _from_vector3,
    normalize_msgtype,
)
from transplanter_ident.epochs import checks
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler
from transplanter_ident.epochs.batch import BatchResult, SampleStream
from transplanter_ident.epochs.epoch import EpochArrays, Rejection
from transplanter_ident.epochs.settings import input_roles
from transplanter_ident.evaluation.windows import reason_class
from transplanter_ident.files import Progress, one_line


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
    rejected: tuple[int, ...] = ()  # per epoch, the rejections since the previous one (validity.Sample.rejected)


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


#: connection id -> [(role, assembler input, normalised message type, extractor)]: one nav_msgs/Odometry
#: connection may serve velocity and heading
_Table = dict[int, list[tuple[str, str, str, Extractor]]]


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
    for role in input_roles(params):
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
            name, extract = INPUT_TYPES[role][msgtype]
            table.setdefault(conn.id, []).append((role, name, msgtype, extract))
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
                table[conn.id] = [(role, role, msgtype, extract)]
            else:
                notes.append(f"ground truth topic {topic} has type {conn.msgtype}, not {msgtype}: ignored")
    return table


class _Scan:
    """One streaming pass: yields input samples, collects truth, unusable messages and counts."""

    def __init__(self, path: str | Path, params: Any, *, truth: bool, progress: bool) -> None:
        self.path = path
        self.params = params
        self.want_truth = truth
        self.progress = progress
        self.rejections: list[Rejection] = []
        self.release_keys: list[int] = []  # batch pass: the arrival key each rejection precedes (batch_read)
        self.notes: list[str] = []
        self.counts: Counter[str] = Counter()
        self.read_per_connection: Counter[int] = Counter()  # every message read, usable or not
        self.connections: list[Any] = []
        self.truth_rows: dict[str, list[tuple[float, tuple[float, ...]]]] = {"truth_stiffness": [],
                                                                            "truth_velocity": []}

    def _table(self, reader: Reader) -> _Table:
        table = _select(self.path, reader, self.params)
        if self.want_truth:
            table.update(_select_truth(reader, self.notes))
        return table

    def samples(self) -> Iterator[tuple[str, float, tuple[float, ...]]]:
        joint = self.params.steering.joint_name
        counts, truth_rows = self.counts, self.truth_rows
        with open_reader(self.path) as reader:
            table = self._table(reader)
            connections = [c for c in reader.connections if c.id in table]
            self.connections = connections
            read = self.read_per_connection
            progress = None
            if self.progress:
                progress = Progress(sum(c.msgcount for c in connections), f"reading {self.path}")
            next_report = progress.next_at if progress is not None else math.inf
            for n, (conn, log_ns, data) in enumerate(reader.messages(connections=connections), 1):
                if n >= next_report:
                    progress.update(n)
                    next_report = progress.next_at
                read[conn.id] += 1
                for _, role, name, stamp, values in message_samples(table[conn.id], conn, log_ns, data, joint,
                                                                    self.rejections):
                    counts[role] += 1
                    if role in truth_rows:
                        truth_rows[role].append((stamp, values))
                    else:
                        yield name, stamp, values
            if progress is not None:
                progress.done()

    def batch(self) -> list[SampleStream] | None:
        """The whole pass at once, decoded in batches (:mod:`.batch_read`); None: use :meth:`samples`."""
        with open_reader(self.path) as reader:
            return read_batch(self, reader, self._table(reader))

    def shortfall(self) -> list[str]:
        """Per topic whose count read differs from the bag's own count: "/gnss/vel: 82 of 601"."""
        read: Counter[str] = Counter()
        expected: Counter[str] = Counter()
        for conn in self.connections:
            read[conn.topic] += self.read_per_connection[conn.id]
            expected[conn.topic] += conn.msgcount
        return [f"{topic}: {read[topic]} of {expected[topic]}" for topic in expected if read[topic] != expected[topic]]


def _truth_columns(rows: Any, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(stamps, values) sorted by stamp (stable) from [(stamp, values)] rows or a (stamps, values) pair."""
    if isinstance(rows, tuple):
        stamps, values = rows
    else:
        stamps = np.array([row[0] for row in rows], dtype=np.float64)
        values = np.array([row[1] for row in rows], dtype=np.float64).reshape(-1, width)
    order = np.argsort(stamps, kind="stable")
    return stamps[order], values[order]


def _build_truth(rows: dict[str, Any]) -> Truth | None:
    t, stiff = _truth_columns(rows["truth_stiffness"], 3)
    if not len(t):
        return None
    tv, vel = _truth_columns(rows["truth_velocity"], 3)
    if len(tv):
        vx, vy, r = (np.interp(t, tv, vel[:, i]) for i in range(3))
    else:
        vx = vy = r = np.full(len(t), np.nan)
    return Truth(t=t, cf=stiff[:, 0], cr=stiff[:, 1], vx=vx, vy=vy, r=r)


def read_samples(path: str | Path, params: Any,
                 rejections: list[Rejection] | None = None) -> Iterator[tuple[str, float, tuple[float, ...]]]:
    """Stream ``(input, stamp s, values)`` samples in log-time order, as :func:`~..epochs.assembler.assemble` takes them.

    ``input`` is ``velocity`` (east/north or north/east by frame[, covariance diagonal]),
    ``velocity_body`` (an Odometry twist in body axes, covariance diagonal), ``heading_quaternion``
    (x, y, z, w) or ``steering`` (angle). Messages that do not decode (a JointState without the
    steering joint, malformed bytes) are skipped and appended to ``rejections`` if given. ``params``
    is a ``params_file.EstimatorParams`` (topics, steering.joint_name are used).
    """
    scan = _Scan(path, params, truth=False, progress=False)
    try:
        yield from scan.samples()
    finally:
        if rejections is not None:
            rejections.extend(scan.rejections)


def read_bag(path: str | Path, params: Any, *, truth: bool = True, progress: bool = False,
             allow_partial: bool = False, batch: bool = True) -> BagData:
    """One pass: epochs (those of the node's EpochAssembler), rejections, ground truth, counts.

    ``batch``: decode and assemble in batches where that gives the same result (:mod:`.batch_read`);
    False: message by message through the streaming assembler.

    Raises :class:`BagError` when the bag cannot be read, an input topic is missing or mistyped,
    or no epoch can be formed; and when fewer (or more) messages could be read than the bag's
    metadata counts (rosbags skips a corrupt MCAP chunk silently), unless ``allow_partial``: then
    the difference is a note.
    """
    def new_scan() -> _Scan:
        return _Scan(path, params, truth=truth, progress=progress)

    assembler, epochs, rejected, drained, scan = assemble_scan(new_scan, AssemblerSettings.from_params(params),
                                                               batch=batch)
    missing = scan.shortfall()
    if missing and not allow_partial:
        raise BagError(f"{path}: messages read differ from the bag's own counts ({'; '.join(missing)}): a corrupt "
                       "or truncated chunk was skipped (use --allow-partial to go on with what could be read)")
    if missing:
        scan.notes.append(f"partial bag: messages read of the bag's own counts: {'; '.join(missing)}")
    rejections = scan.rejections + drained + assembler.drain_rejections()
    rejections.sort(key=lambda r: r.stamp)
    counts = {role: scan.counts.get(role, 0) for role in ROLES}
    if not len(epochs):
        summary = ", ".join(f"{counts[r]} {r}" for r in ROLES)
        top = summarize_rejections(rejections)[:1]
        why = f"; most common rejection: {top[0][0]}: {top[0][1]} ({top[0][2]}x)" if top else ""
        notes = "".join(f"; {note}" for note in _input_notes(assembler, rejections))
        raise BagError(f"{path}: no epoch could be formed from {summary} messages{why}{notes}")
    truth_data = _build_truth(scan.truth_rows) if truth else None
    if truth:
        counts["truth"] = scan.counts.get("truth_stiffness", 0)
    notes = scan.notes + _input_notes(assembler, rejections)
    return BagData(Path(path), epochs, rejections, truth_data, counts, notes, tuple(rejected))


def _input_notes(assembler: EpochAssembler | BatchResult, rejections: Sequence[Rejection]) -> list[str]:
    """Plain-language notes on velocity/heading that did not pair and on time steps (replay prints them)."""
    notes = []
    stats = assembler.pairing
    if stats.misses:
        share = stats.misses / max(1, stats.misses + 2 * stats.pairs)
        note = (f"{stats.misses} GNSS velocity/heading samples ({100 * share:.0f} %) found no partner within "
                f"gnss.pairing_tolerance {1e3 * stats.tolerance:g} ms")
        if stats.last_offset is not None:
            late = "after" if stats.last_offset > 0 else "before"
            note += (f"; they missed by up to {1e3 * stats.largest_miss:.0f} ms (the last: heading stamped "
                     f"{1e3 * abs(stats.last_offset):.0f} ms {late} the velocity): if they describe one receiver "
                     f"epoch, set gnss.pairing_tolerance above {1e3 * stats.largest_miss:.0f} ms")
        notes.append(note)
    if assembler.uncovered_epochs:
        notes.append(f"{assembler.uncovered_epochs} epoch(s) were formed before a steering sample at or after their "
                     "end arrived (the last steering value was held over the end of the interval)")
    resyncs = [r for r in rejections if r.kind == checks.RESYNC and r.topic != "epoch"]
    if resyncs:
        notes.append(f"{len(resyncs)} input time step(s) re-synchronised; the first: {resyncs[0].topic} at "
                     f"t={resyncs[0].stamp:.3f}: {resyncs[0].reason}")
    return notes


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
            role, _name, msgtype, extract = table[conn.id][0]
            try:
                rows[role].append(extract(TYPESTORE.deserialize_cdr(data, msgtype), log_ns, ""))
            except _DECODE_ERRORS as exc:
                raise BagError(f"{path}: malformed ground truth message on {conn.topic}: {_reason(exc)}") from exc
    return _build_truth(rows)


def summarize_rejections(rejections: Sequence[Rejection]) -> list[tuple[str, str, int]]:
    """(topic, reason, count), most frequent first; per-sample numbers in reasons are merged.

    Reasons of one class (the same text but for its numbers, :func:`reason_class`) count together,
    under the first text seen: a bag of 10^5 distinct quaternions is one line, not 10^5.
    """
    counts: Counter[tuple[str, str]] = Counter()
    first: dict[tuple[str, str], str] = {}
    for rejection in rejections:
        reason = checks.SUMMARY_LABELS.get(rejection.kind, rejection.reason)
        if reason.startswith("|") and "beyond max_steering" in reason:
            reason = "beyond max_steering" + reason.split("beyond max_steering", 1)[1]
        key = (rejection.topic, reason_class(reason))
        first.setdefault(key, reason)
        counts[key] += 1
    return [(topic, first[(topic, cls)], n) for (topic, cls), n in counts.most_common()]
