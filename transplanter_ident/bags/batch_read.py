"""One pass over a bag's input and truth connections, decoded in batches (replay's fast path).

:func:`read_batch` reads every wanted message's bytes once, decodes each connection's messages in
groups (:mod:`.batch_decode`) and sends the rest through :func:`message_samples`, the per-message
decoding that :meth:`~.reader._Scan.samples` streams. It fills the scan's counts, rejections (in
message order) and ground truth exactly as the streaming pass does, and returns the input samples
as :class:`~transplanter_ident.epochs.batch.SampleStream` columns keyed by arrival order.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from transplanter_ident.bags.batch_decode import decode_connection, width_of
from transplanter_ident.bags.messages import _DECODE_ERRORS, TYPESTORE, _Unusable, seconds
from transplanter_ident.epochs import checks
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler
from transplanter_ident.epochs.batch import BatchResult, SampleStream, assemble_batch, stream_samples
from transplanter_ident.epochs.counted import assemble_counting
from transplanter_ident.epochs.epoch import EpochArrays, Rejection
from transplanter_ident.files import Progress

#: messages decoded together (bounds the memory of the bytes held at once)
CHUNK = 1 << 18
#: (entry position, role, assembler input, stamp, values) of one decoded message
Sample = tuple[int, str, str, float, tuple[float, ...]]


def message_samples(entries: list, conn: Any, log_ns: int, data: bytes, joint: str,
                    rejections: list[Rejection]) -> Iterator[Sample]:
    """Decode one message for each of its connection's entries, yielding each sample as it is made.

    What cannot be used is appended to ``rejections`` when it is met (before the samples of later entries).
    """
    try:
        msg = TYPESTORE.deserialize_cdr(data, entries[0][2])
    except _DECODE_ERRORS:
        reason = f"undecodable {conn.msgtype} message"
        for role, *_ in entries:
            rejections.append(Rejection(role.removeprefix("truth_"), seconds(log_ns), reason, checks.UNDECODABLE))
        return
    for position, (role, name, _msgtype, extract) in enumerate(entries):
        try:
            stamp, values = extract(msg, log_ns, joint)
        except _Unusable as exc:
            rejections.append(Rejection(role.removeprefix("truth_"), seconds(log_ns), str(exc), exc.kind))
            continue
        yield position, role, name, stamp, values


def _chunks(scan: Any, reader: Any, connections: list) -> Iterator[tuple[int, np.ndarray, np.ndarray, list[bytes]]]:
    """(number of the first message, connection ids, log ns, bytes) of every CHUNK messages, in log-time order.

    Raises OverflowError when a log time does not fit an int64.
    """
    ids, logs, datas = [], [], []
    first = 0
    progress = Progress(sum(c.msgcount for c in connections), f"reading {scan.path}") if scan.progress else None
    next_report = progress.next_at if progress is not None else math.inf
    for n, (conn, log_ns, data) in enumerate(reader.messages(connections=connections), 1):
        if n >= next_report:
            progress.update(n)
            next_report = progress.next_at
        ids.append(conn.id)
        logs.append(log_ns)
        datas.append(data)
        if len(ids) == CHUNK:
            yield first, np.array(ids, dtype=np.int64), np.array(logs, dtype=np.int64), datas
            first, ids, logs, datas = first + CHUNK, [], [], []
    if progress is not None:
        progress.done()
    yield first, np.array(ids, dtype=np.int64), np.array(logs, dtype=np.int64), datas


def read_batch(scan: Any, reader: Any, table: dict) -> list[SampleStream] | None:
    """Fill ``scan`` (counts, rejections, truth rows) and return the input samples; None: use the stream instead."""
    connections = [c for c in reader.connections if c.id in table]
    scan.connections = connections
    scan.release_keys = []  # per scan rejection: the key of the first sample the streaming pass reads after it
    columns: dict[tuple[str, str, int], list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {}
    try:
        for first, ids, logs, datas in _chunks(scan, reader, connections):
            _decode_chunk(scan, table, first, ids, logs, datas, columns)
    except OverflowError:
        return None
    streams = []
    for (role, name, width), parts in columns.items():
        keys = np.concatenate([p[0] for p in parts])
        stamps = np.concatenate([p[1] for p in parts])
        values = np.concatenate([p[2].reshape(-1, width) for p in parts])
        order = np.argsort(keys, kind="stable")
        scan.counts[role] += len(keys)
        if role in scan.truth_rows:
            scan.truth_rows[role] = (stamps[order], values[order])
        else:
            streams.append(SampleStream(name, keys[order], stamps[order], values[order]))
    return streams


def _decode_chunk(scan: Any, table: dict, first: int, ids: np.ndarray, logs: np.ndarray, datas: list[bytes],
                  columns: dict) -> None:
    """Decode one chunk (messages ``first``...) into ``columns``: in groups, then the rest one by one in order."""
    joint = scan.params.steering.joint_name
    slow_messages: list[np.ndarray] = [np.zeros(0, dtype=np.int64)]
    for conn in scan.connections:
        local = np.flatnonzero(ids == conn.id)
        if not len(local):
            continue
        scan.read_per_connection[conn.id] += len(local)
        entries = table[conn.id]
        subset = [datas[i] for i in local.tolist()]
        decoded = [decode_connection(msgtype, role, extract, joint, local + first, logs[local], subset,
                                     width_of(msgtype, role))
                   for role, _name, msgtype, extract in entries]
        slow = np.unique(np.concatenate([d.slow for d in decoded]))
        slow_messages.append(slow)
        for position, ((role, name, _msgtype, _extract), d) in enumerate(zip(entries, decoded, strict=True)):
            keep = ~np.isin(d.index, slow)
            columns.setdefault((role, name, d.values.shape[1]), []).append(
                (d.index[keep] * 2 + position, d.stamps[keep], d.values[keep]))
    by_conn = {c.id: c for c in scan.connections}
    for number in np.sort(np.concatenate(slow_messages)).tolist():  # the streaming pass's decoding, in order
        i = number - first
        conn = by_conn[int(ids[i])]
        made = len(scan.rejections)
        for position, role, name, stamp, values in message_samples(table[conn.id], conn, int(logs[i]), datas[i],
                                                                   joint, scan.rejections):
            _release(scan, made, number * 2 + position)
            made = len(scan.rejections)
            row = np.array([values], dtype=np.float64).reshape(1, len(values))
            columns.setdefault((role, name, len(values)), []).append(
                (np.array([number * 2 + position], dtype=np.int64), np.array([stamp], dtype=np.float64), row))
        _release(scan, made, number * 2 + 2)


def _release(scan: Any, made: int, key: int) -> None:
    """The rejections appended since ``made`` reach the streaming pass before the sample keyed ``key``."""
    scan.release_keys.extend([key] * (len(scan.rejections) - made))


def assemble_scan(new_scan: Callable[[], Any], settings: AssemblerSettings, *,
                  batch: bool) -> tuple[EpochAssembler | BatchResult, EpochArrays, list[int], list[Rejection], Any]:
    """(assembler or batch result, epochs, rejections per epoch, the assembler's rejections, the scan) of a bag.

    The rejections per epoch are those since the previous epoch, as epochs.counted.assemble_counting counts them.
    In batches where :func:`~transplanter_ident.epochs.batch.assemble_batch` applies; otherwise the
    same samples go through the streaming assembler (read again message by message when the batch
    pass could not hold them).
    """
    scan = new_scan()
    streams = scan.batch() if batch else None
    result = assemble_batch(settings, streams, scan.release_keys) if streams is not None else None
    if result is not None:
        return result, result.epochs, result.rejected, result.drain_rejections(), scan
    assembler = EpochAssembler(settings)
    if streams is None:
        scan = new_scan() if batch else scan
        epochs, rejected, drained = assemble_counting(assembler, scan.samples(), scan.rejections)
    else:
        source: list[Rejection] = []
        samples = _released(stream_samples(streams, keys=True), scan.release_keys, scan.rejections, source)
        epochs, rejected, drained = assemble_counting(assembler, samples, source)
    return assembler, EpochArrays(epochs), rejected, drained, scan


def _released(samples: list, release_keys: list[int], rejections: list[Rejection],
              source: list[Rejection]) -> Iterator[tuple[str, float, tuple[float, ...]]]:
    """The samples, appending each scan rejection to ``source`` when the streaming pass would have made it."""
    j = 0
    for key, name, stamp, values in samples:
        while j < len(release_keys) and release_keys[j] <= key:
            source.append(rejections[j])
            j += 1
        yield name, stamp, values
