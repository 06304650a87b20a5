"""The replay fast path (issue #13 item 8) gives exactly what the streaming path gives.

``read_bag(batch=True)`` decodes messages in groups (bags/batch_decode.py) and assembles epochs with
epochs/batch.py where that applies; ``batch=False`` decodes message by message and feeds the
node's streaming EpochAssembler. Compared bit for bit (epochs, rejections in order, counts, notes,
truth, errors) on the sample bags, driver-shaped bags, gapped bags, bags with future stamps and a
clock step, and seeded fuzz mutants (test/fuzz_bags.py); and, at the assembler level, on
hundreds of randomly perturbed sample streams. Clean and driver-shaped bags must take the fast path,
so that the comparison covers it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import random
import shutil
from pathlib import Path

import fuzz_bags
import numpy as np
import pytest
from helpers import NO_NOISE

from transplanter_ident.bags import BagError, read_bag
from transplanter_ident.bags.messages import yaw_quaternion
from transplanter_ident.bags.reader import _Scan
from transplanter_ident.cli import simulate
from transplanter_ident.config.params_file import EstimatorParams, load_params
from transplanter_ident.config.params_writer import write_params_yaml
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler
from transplanter_ident.epochs.batch import ROW_FIELDS, SampleStream, assemble_batch
from transplanter_ident.epochs.counted import assemble_counting
from transplanter_ident.epochs.epoch import Epoch, EpochArrays, Rejection
from transplanter_ident.epochs.steering_line import interval_line, interval_line_kernel
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.simulator import simulate as run_simulation

ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAGS = ("sine", "step20-ccw", "step30-cw", "surface-change")
DRIVERS = ("nmea", "odometry", "septentrio", "swiftnav", "ublox")
#: (name, simulate arguments, whether the batch assembler must apply)
SIMULATED = (
    *((f"driver-{d}", ["--driver", d], d != "swiftnav") for d in DRIVERS),  # swiftnav: markers leave partners unpaired
    ("gnss10-first", ["--gnss-rate", "10", "--gnss-first"], True),
    ("ned-20hz", ["--gnss-rate", "20", "--velocity-frame", "ned", "--heading-frame", "ned"], True),
    ("delay", ["--gnss-delay", "0.08"], True),
    ("float64-jitter", ["--steering-type", "float64", "--heading-lag", "0.01", "--heading-lag-jitter", "0.005"], True),
    ("float32", ["--steering-type", "float32"], True),
    ("odometry-imu", ["--velocity-type", "odometry", "--heading-type", "imu"], True),
    ("pose-cov-late-start", ["--heading-type", "pose-cov", "--start-time", "1000"], True),
    ("antenna-offset", ["--antenna-x", "0.6", "--antenna-y", "0.2", "--steering-offset", "0.01"], True),
    ("step-2hz", ["--scenario", "step20-ccw", "--gnss-rate", "2", "--steering-rate", "7"], True),
    ("reported-noise-imu", ["--report-noise", "--velocity-type", "twist-cov", "--heading-type", "imu",
                            "--gnss-degraded", "10", "20", "3"], True),
    ("reported-noise-septentrio", ["--driver", "septentrio", "--report-noise"], True),
    ("reported-noise-pose-ned", ["--report-noise", "--velocity-type", "twist-cov", "--heading-type", "pose-cov",
                                 "--velocity-frame", "ned", "--heading-frame", "ned"], True),
)


def _bits(x: float) -> bytes:
    return np.float64(x).tobytes()


def _rejections(rejections: list[Rejection]) -> list[tuple]:
    return [(r.topic, _bits(r.stamp), r.reason, r.kind) for r in rejections]


def _epochs(epochs: EpochArrays) -> dict[str, bytes]:
    return {f.name: epochs.column(f.name).tobytes() for f in dataclasses.fields(Epoch)}


def _read(path: Path, params: EstimatorParams, batch: bool) -> tuple:
    try:
        data = read_bag(path, params, truth=True, batch=batch)
    except BagError as exc:
        return ("error", str(exc))
    truth = None if data.truth is None else [getattr(data.truth, f.name).tobytes()
                                             for f in dataclasses.fields(data.truth)]
    return (_epochs(data.epochs), _rejections(data.rejections), data.counts, data.notes, truth,
            [int(n) for n in data.rejected])


def fast_path_applies(path: Path, params: EstimatorParams) -> bool:
    """Whether the batch assembler (not the streaming fallback) makes this bag's epochs."""
    streams = _Scan(path, params, truth=False, progress=False).batch()
    return streams is not None and assemble_batch(AssemblerSettings.from_params(params), streams) is not None


def assert_same(path: Path, params: EstimatorParams | None = None) -> None:
    params = params or EstimatorParams()
    fast, slow = _read(path, params, True), _read(path, params, False)
    assert fast == slow, f"{path}: the batch path differs from the streaming path"


def _params_file(directory: Path, params: dict) -> Path:
    flat = {f"{ns}.{key}": value for ns, values in params.items() for key, value in values.items()}
    path = directory / "params.yaml"
    write_params_yaml(path, flat, "batch replay test")
    return path


@pytest.mark.parametrize("name", SAMPLE_BAGS)
def test_sample_bags(name: str) -> None:
    path = ROOT / "bags" / name
    assert fast_path_applies(path, EstimatorParams())
    assert_same(path)


@pytest.mark.parametrize(("name", "args", "fast"), SIMULATED, ids=[s[0] for s in SIMULATED])
def test_simulated_drives(tmp_path: Path, name: str, args: list[str], fast: bool) -> None:
    bag, params_file = tmp_path / "bag", tmp_path / "params.yaml"
    assert simulate.main(["-o", str(bag), "--duration", "30", "--seed", "3", "--params-out", str(params_file),
                          *args]) == 0
    params = load_params([str(params_file)])
    if fast:
        assert fast_path_applies(bag, params), f"{name}: the fast path should apply"
    assert_same(bag, params)


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> fuzz_bags.Base:
    return fuzz_bags.make_base(tmp_path_factory.mktemp("batch_base"))


@pytest.mark.parametrize(("kind", "count", "seed"), [("message", 56, 14), ("byte", 24, 15)])
def test_fuzz_mutants(base: fuzz_bags.Base, tmp_path: Path, kind: str, count: int, seed: int) -> None:
    mutations = fuzz_bags.MESSAGE_MUTATIONS if kind == "message" else fuzz_bags.BYTE_MUTATIONS
    rng = random.Random(seed)
    for i in range(count):
        mutant = mutations[i % len(mutations)](rng, base)
        bag = tmp_path / f"bag{i}"
        mutant.write(bag)
        params = EstimatorParams()
        if mutant.params:
            (tmp_path / f"p{i}").mkdir()
            params = load_params([str(_params_file(tmp_path / f"p{i}", mutant.params))])
        assert_same(bag, params)


def _edited(base: fuzz_bags.Base, path: Path, keep=None, shift=None) -> Path:  # noqa: ANN001 - predicates
    t0 = base.messages[0].log_ns
    messages = [m for m in base.copy_messages() if keep is None or keep(m, (m.log_ns - t0) / 1e9)]
    for i, m in enumerate(messages):
        seconds = shift(m, i, (m.log_ns - t0) / 1e9) if shift else 0.0
        if seconds:
            fuzz_bags._shift_stamp(m.msg, seconds)
    fuzz_bags.write_messages(messages, path)
    return path


def test_gaps_future_stamps_and_a_clock_step(base: fuzz_bags.Base, tmp_path: Path) -> None:
    assert fast_path_applies(base.path, EstimatorParams())
    cases = {
        "steering gap": dict(keep=lambda m, t: not (m.topic == "/steering_angle" and 5.0 < t < 8.0)),
        "gnss gap": dict(keep=lambda m, t: not (m.topic.startswith("/gnss") and 10.0 < t < 12.5)),
        "all gap": dict(keep=lambda m, t: not (m.topic in fuzz_bags.INPUTS and 4.0 < t < 6.0)),
        "short steering gap": dict(keep=lambda m, t: not (m.topic == "/steering_angle" and 5.0 < t < 5.6)),
        "clock step": dict(shift=lambda m, i, t: 30.0 if t > 9.0 else 0.0),
    }
    for topic in fuzz_bags.INPUTS:
        for seconds in (0.03, 0.7, 2.0, 100.0):
            cases[f"{topic} +{seconds}"] = dict(
                shift=lambda m, i, t, topic=topic, seconds=seconds: seconds if m.topic == topic and 4.0 < t < 4.5
                else 0.0)
    for n, (name, edit) in enumerate(cases.items()):
        path = _edited(base, tmp_path / f"bag{n}", **edit)
        assert_same(path), name
    for n, params in enumerate(({"vehicle": {"max_yaw_rate": 0.2, "max_lateral_speed": 0.05, "max_speed": 2.05}},
                                {"gnss": {"pairing_tolerance": 0.001, "delay": 0.05}},
                                {"vehicle": {"max_lateral_speed": 0.08}})):
        (tmp_path / f"p{n}").mkdir()
        assert_same(base.path, load_params([str(_params_file(tmp_path / f"p{n}", params))]))


# --------------------------------------------------------------------------- assembler level


def _clean_samples(seed: int, gnss_rate: float, steering_rate: float) -> list[tuple[str, float, tuple[float, ...]]]:
    config = build_config("sine", duration=12.0, gnss_rate=gnss_rate, steering_rate=steering_rate, seed=seed)
    result = run_simulation(dataclasses.replace(config, noise=NO_NOISE) if seed % 3 == 0 else config)
    rows = []
    for t, (east, north), heading in zip(result.gnss_stamp, result.velocity_enu, result.heading, strict=True):
        rows.append((float(t), 1, "velocity", (float(east), float(north))))
        rows.append((float(t), 2, "heading_quaternion", yaw_quaternion(float(heading))))
    for t, angle in zip(result.steering_time, result.steering, strict=True):
        rows.append((float(t), 0, "steering", (float(angle),)))
    rows.sort(key=lambda row: (row[0], row[1]))
    return [(name, t, values) for t, _, name, values in rows]


def _perturb(rng: random.Random, samples: list) -> list:
    samples = list(samples)
    for _ in range(rng.choice((0, 1, 2, 5))):
        i = rng.randrange(len(samples))
        name, t, values = samples[i]
        what = rng.choice(("drop", "jitter", "swap", "nan", "future", "past", "big", "repeat", "rotate"))
        if what == "drop":
            del samples[i]
        elif what == "jitter":
            samples[i] = (name, t + rng.uniform(-0.08, 0.08), values)
        elif what == "swap" and i + 1 < len(samples):
            samples[i], samples[i + 1] = samples[i + 1], samples[i]
        elif what == "nan":
            samples[i] = (name, t, (math.nan, *values[1:]))
        elif what in ("future", "past"):
            samples[i] = (name, t + rng.choice((0.5, 1.5, 30.0)) * (1 if what == "future" else -1), values)
        elif what == "big":
            samples[i] = (name, t, tuple(3.0 * v for v in values))
        elif what == "repeat":
            samples.insert(i, samples[i])
        elif what == "rotate":
            samples[i] = (name, t, values[::-1])
    return samples


def _streams(samples: list) -> list[SampleStream]:
    by_name: dict[str, list] = {}
    for key, (name, t, values) in enumerate(samples):
        by_name.setdefault(name, []).append((key, t, values))
    return [SampleStream(name, np.array([r[0] for r in rows], dtype=np.int64), np.array([r[1] for r in rows]),
                         np.array([r[2] for r in rows], dtype=np.float64)) for name, rows in by_name.items()]


def test_perturbed_sample_streams() -> None:
    rng = random.Random(13)
    fast = 0
    for case in range(240):
        samples = _clean_samples(case % 7, rng.choice((2.0, 5.0, 10.0, 20.0)), rng.choice((7.0, 20.0, 50.0)))
        samples = _perturb(rng, samples) if case % 4 else samples
        settings = AssemblerSettings(max_speed=5.0, max_lateral_speed=rng.choice((1.0, 0.1)), max_yaw_rate=1.5,
                                     gnss_delay=rng.choice((0.0, 0.0, 0.04)), antenna_x=rng.choice((0.0, 0.5)))
        streaming = EpochAssembler(settings)
        listed, counts, drained = assemble_counting(streaming, samples, [])
        epochs = EpochArrays(listed)
        result = assemble_batch(settings, _streams(samples))
        if case % 4 == 0:
            assert result is not None, f"case {case}: a clean stream must take the fast path"
        if result is None:
            continue
        fast += 1
        assert _epochs(result.epochs) == _epochs(epochs), f"case {case}"
        assert _rejections(result.drain_rejections()) == _rejections(drained), f"case {case}"
        assert result.rejected == counts, f"case {case}"
        assert result.uncovered_epochs == streaming.uncovered_epochs
        assert dataclasses.asdict(result.pairing) == dataclasses.asdict(streaming.pairing)
    assert fast >= 60


def test_kernel_rows_are_the_epoch_fields() -> None:
    assert ROW_FIELDS == tuple(f.name for f in dataclasses.fields(Epoch))


def test_interval_line_kernel_is_bit_identical() -> None:
    rng = np.random.default_rng(5)
    for _ in range(2000):
        n = int(rng.integers(1, 12))
        times = np.cumsum(rng.uniform(1e-3, 0.3, n)) + rng.uniform(-1.0, 1.0) * 1e3
        values = rng.normal(0.0, 0.3, n)
        start = float(times[0] + rng.uniform(-0.3, 0.5))
        end = start + float(rng.uniform(1e-3, 1.0))
        expected = interval_line(times.tolist(), values.tolist(), start, end)
        got = interval_line_kernel(times, values, start, end)
        assert _bits(got[0]) == _bits(expected[0]) and _bits(got[1]) == _bits(expected[1])


def test_copied_sample_bag_with_a_corrupt_chunk_reports_the_same(tmp_path: Path) -> None:
    bag = tmp_path / "sine"
    shutil.copytree(ROOT / "bags" / "sine", bag)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    data[len(data) // 2: len(data) // 2 + 64] = bytes(64)
    mcap.write_bytes(bytes(data))
    assert_same(bag)


# --------------------------------------------------------------------------- group decoding


def test_group_decoding_equals_message_by_message() -> None:
    """Every type and role; frame ids and joint lists that change, big-endian, truncated and garbage messages."""
    from test_bag_io import _messages

    from transplanter_ident.bags.batch_decode import decode_connection, width_of
    from transplanter_ident.bags.messages import _DECODE_ERRORS, INPUT_TYPES, TYPESTORE, _Unusable

    rng = np.random.default_rng(3)
    joint = "front_steering"
    for role, types in INPUT_TYPES.items():
        for msgtype, (_name, extract) in types.items():
            datas = []
            for i in range(60):
                frame = ("gnss_link", "gnss", "antenna_frame_long_name")[int(rng.integers(0, 3)) if i % 7 == 0 else 0]
                names = ["rear_left", joint, "rear"] if i % 11 else [joint]
                msg = _messages(frame, rng, names)[msgtype][0]
                data = bytes(TYPESTORE.serialize_cdr(msg, msgtype, little_endian=i % 13 != 5))
                if i % 17 == 3:
                    data = data[:-3]
                elif i % 19 == 4:
                    data = bytes(rng.integers(0, 256, len(data), dtype=np.uint8))
                datas.append(data)
            index = np.arange(100, 100 + len(datas), dtype=np.int64)
            log_ns = np.arange(len(datas), dtype=np.int64) * 50_000_000 + 1_700_000_000_000_000_000
            decoded = decode_connection(msgtype, role, extract, joint, index, log_ns, datas, width_of(msgtype, role))
            assert sorted([*decoded.index.tolist(), *decoded.slow.tolist()]) == index.tolist(), msgtype
            assert len(decoded.index) >= 30, f"{msgtype}: most messages should decode in groups"
            for k, i in enumerate((decoded.index - 100).tolist()):
                stamp, values = extract(TYPESTORE.deserialize_cdr(datas[i], msgtype), int(log_ns[i]), joint)
                assert _bits(decoded.stamps[k]) == _bits(stamp)
                assert decoded.values[k].tobytes() == np.array(values, dtype=np.float64).tobytes(), (msgtype, i)
            for i in (decoded.slow - 100).tolist():  # left to the per-message path: odd, or unusable
                with contextlib.suppress(*_DECODE_ERRORS, _Unusable):
                    extract(TYPESTORE.deserialize_cdr(datas[i], msgtype), int(log_ns[i]), joint)


def test_small_chunks_give_the_same(base: fuzz_bags.Base, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Decoding in chunks of a few messages (groups and the per-message rest across chunk ends) changes nothing."""
    from transplanter_ident.bags import batch_read

    rng = random.Random(7)
    bags = [ROOT / "bags" / "sine", base.path]
    for i, mutation in enumerate((fuzz_bags.bad_fields, fuzz_bags.bad_orientation_or_joint, fuzz_bags.drop_or_repeat)):
        mutation(rng, base).write(tmp_path / f"bag{i}")
        bags.append(tmp_path / f"bag{i}")
    for chunk in (1, 37, 1000):
        monkeypatch.setattr(batch_read, "CHUNK", chunk)
        for bag in bags:
            assert_same(bag)
