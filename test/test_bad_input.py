"""Regression tests of issue #14, items 4-7: one per defect, each failing on the code before the fix.

Bounded memory (log throttle keyed by reason class; the steering buffer capped at any rate), no
traceback (an optional output disabled on an I/O error; parameter files checked before rcl),
ranges from the schema (Q of 1e300, ``initial_stiffness: 1e300``; a sealed tuner file cut
mid-number), and offline (message counts against the bag's metadata, out-of-range stamps, a YAML
alias bomb, a tuner whose every candidate diverged, outputs that fail half-way: no partial files).
The node's process-level cases (parameter files, /dev/full, SIGTERM under a flood) are in
test_fuzz.py and test_fuzz_node.py.
"""

from __future__ import annotations

import contextlib
import io
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import fuzz_bags
import pytest
import yaml
from ros_harness import ROOT

from transplanter_ident.cli import replay, tuner
from transplanter_ident.config.params_file import ParamsError, load_params, read_params_file
from transplanter_ident.config.params_writer import write_params_yaml
from transplanter_ident.config.safe_yaml import SEALED_LAST_LINE
from transplanter_ident.epochs.assembler import MAX_STEERING_SAMPLES, AssemblerSettings, EpochAssembler
from transplanter_ident.evaluation.windows import Throttle, reason_class
from transplanter_ident.files import OptionalOutput
from transplanter_ident.ros.startup import check_params_files

CONFIG = ROOT / "config" / "estimator.yaml"


def _yaml(path: Path, body: str) -> Path:
    path.write_text("estimator:\n  ros__parameters:\n" + textwrap.indent(textwrap.dedent(body), "    "))
    return path


def _run(main, argv: list[str]) -> tuple[int, str, str]:  # noqa: ANN001 - a CLI main()
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> fuzz_bags.Base:
    return fuzz_bags.make_base(tmp_path_factory.mktemp("bad_input_base"))


# --------------------------------------------------------------------------- 4: bounded memory


def test_log_throttle_is_keyed_by_the_reason_class_and_bounded() -> None:
    """Rejections that quote their values are one throttle entry, not one per text (101 MB/h before)."""
    throttle = Throttle(5.0)
    lines = 0
    for i in range(10_000):
        reason = f"|{0.7 + i * 1e-5:.5f}| rad beyond max_steering 0.700"
        allowed, _ = throttle.allow(("steering", reason_class(reason)), now=i * 1e-3)
        lines += allowed
    assert len(throttle) == 1 and lines == 2  # one line, and one more after the 5 s period
    for i in range(10_000):  # whatever the keys, the throttle keeps a bounded number of them
        throttle.allow(("free text", str(i)), now=100.0)
    assert len(throttle) <= throttle.max_keys


def test_steering_buffer_is_bounded_at_any_rate() -> None:
    """Steering with no GNSS: trimmed by time, and capped in count (100 kHz for 3 s held 300 000 before)."""
    assembler = EpochAssembler(AssemblerSettings())
    for k in range(300_000):
        assembler.add_steering(1000.0 + k * 1e-5, 0.1)
    assert len(assembler._steering) <= MAX_STEERING_SAMPLES
    assert assembler.drain_rejections() == []


# --------------------------------------------------------------------------- 5: no traceback, no death


def test_optional_output_is_disabled_by_an_io_error() -> None:
    """A full disk under the latency log: the output turns itself off with the reason; the writer never raises."""
    log = OptionalOutput("/dev/full")
    log.write("1.0 0.001\n" * 10_000)
    log.flush()
    log.write("more\n")
    assert not log.active and log.error == "No space left on device"
    log.close()


@pytest.mark.parametrize(("body", "key"), [
    ("ekf: [1.0, 2.0]\n", "ekf"),
    ("ekf: {process_noise: [1, 1.0e-4, 1.0e-6, 1.0e-6]}\n", "ekf.process_noise"),
    ("topics: {velocity: 'gnss vel//'}\n", "topics.velocity"),
])
def test_node_checks_params_files_before_rcl(tmp_path: Path, body: str, key: str) -> None:
    """What rcl would refuse with a traceback (or name neither file nor key) is one ParamsError naming both."""
    path = _yaml(tmp_path / "p.yaml", body)
    with pytest.raises(ParamsError) as info:
        check_params_files(["--params-file", str(CONFIG), "--params-file", str(path)], "estimator")
    assert str(path) in str(info.value) and key in str(info.value)
    missing = tmp_path / "missing.yaml"
    with pytest.raises(ParamsError, match="missing.yaml: cannot read"):
        check_params_files(["--params-file", str(missing)], "estimator")
    non_utf8 = tmp_path / "latin1.yaml"
    non_utf8.write_bytes(b"estimator:\n  ros__parameters:\n    steering: {joint_name: \"\xe9\"}\n")
    with pytest.raises(ParamsError, match=r"latin1.yaml: not UTF-8 text \(byte 0xe9 on line 3\)"):
        check_params_files(["--params-file", str(non_utf8)], "estimator")


# --------------------------------------------------------------------------- 6: ranges from the schema


@pytest.mark.parametrize(("body", "key"), [
    ("ekf: {process_noise: [1.0e300, 1.0e-4, 1.0e-6, 1.0e-6]}\n", "ekf.process_noise"),
    ("ekf: {measurement_noise: [4.0e-4, 1.0e300]}\n", "ekf.measurement_noise"),
    ("ekf: {initial_stiffness: [1.0e300, 1000.0]}\n", "ekf.initial_stiffness"),
    ("ekf: {initial_stiffness: [20.0, 1000.0]}\n", "ekf.initial_stiffness"),  # below ekf.stiffness_bounds
    ("ekf: {heading_process_noise: 1.0e300}\n", "ekf.heading_process_noise"),
    ("ekf: {initial_covariance: [1.0e-2, 1.0e-2, 1.0e300, 4.0]}\n", "ekf.initial_covariance"),
])
def test_absurd_values_are_refused_by_the_schema(tmp_path: Path, body: str, key: str) -> None:
    with pytest.raises(ParamsError) as info:
        load_params([CONFIG, _yaml(tmp_path / "p.yaml", body)])
    assert info.value.key == key, str(info.value)


def test_absurd_values_are_refused_at_run_time() -> None:
    """The node's on-set validation (the same schema): a run-time Q of 1e300 never reaches the filter."""
    from transplanter_ident.ros.parameters import validate

    with pytest.raises(ParamsError, match="ekf.process_noise"):
        validate({"ekf.process_noise": [1.0e300, 1.0e-4, 1.0e-6, 1.0e-6]})
    with pytest.raises(ParamsError, match="ekf.initial_stiffness"):
        validate({"ekf.initial_stiffness": [1.0e300, 1000.0]})


def test_a_tuned_file_cut_mid_number_is_refused(tmp_path: Path) -> None:
    """``1.0e-08`` cut to ``1.`` loaded as 1.0 before; now a sealed file without its last line is refused."""
    path = tmp_path / "tuned.yaml"
    write_params_yaml(path, {"ekf.process_noise": [1.0e-4, 1.0e-4, 1.0e-6, 1.0e-6],
                             "ekf.heading_process_noise": 1.0e-8}, "tuned")  # as the tuner writes them
    assert load_params([path]).config.noise.heading_process_noise == 1.0e-8
    text = path.read_text()
    cut = tmp_path / "cut.yaml"
    cut.write_text(text[:text.index("1.0e-08") + 2])
    assert yaml.safe_load(cut.read_text())["estimator"]["ros__parameters"]["ekf"]["heading_process_noise"] == 1.0
    with pytest.raises(ParamsError, match="cut.yaml: incomplete"):
        load_params([cut])
    assert text.rstrip().endswith(SEALED_LAST_LINE)
    edited = tmp_path / "edited.yaml"  # editing a sealed file by hand is fine while its last line is there
    edited.write_text(text.replace("1.0e-08", "2.0e-08"))
    assert load_params([edited]).config.noise.heading_process_noise == 2.0e-8
    hand = tmp_path / "hand.yaml"  # a hand-written file (no seal) is read as it is
    hand.write_text("estimator:\n  ros__parameters:\n    ekf: {heading_process_noise: 1.}\n")
    assert load_params([hand]).config.noise.heading_process_noise == 1.0


# --------------------------------------------------------------------------- 7: offline


def test_replay_compares_the_messages_read_with_the_metadata(base: fuzz_bags.Base, tmp_path: Path) -> None:
    """A corrupt chunk that rosbags skips (82 of 601 read, exit 0 before) is an error, or a note with --allow-partial."""
    compressed = tmp_path / "compressed"
    from transplanter_ident.bags import BagWriter

    with BagWriter(compressed, compress=True) as bag:
        for m in base.messages:
            bag.write(m.topic, m.msgtype, m.msg, m.log_ns)
    mcap = next(compressed.glob("*.mcap"))
    data = mcap.read_bytes()
    chunk = next(r for r in fuzz_bags._records(data) if r[0] == fuzz_bags.CHUNK_OPCODE)
    partial = 0
    for pos in range(chunk[1] + 200, chunk[2] - 16, 1200):
        damaged = bytearray(data)
        damaged[pos:pos + 16] = bytes(b ^ 0xFF for b in damaged[pos:pos + 16])
        bag = tmp_path / f"flip{pos}"
        shutil.copytree(compressed, bag)
        next(bag.glob("*.mcap")).write_bytes(bytes(damaged))
        code, out, err = _run(replay.main, [str(bag), "--quiet"])
        assert code in (0, 1) and "Traceback" not in err and "internal error" not in err, err
        if "messages read differ" in err:
            partial += 1
            assert code == 1 and "of 101" in err and "--allow-partial" in err, err
            code, out, err = _run(replay.main, [str(bag), "--quiet", "--allow-partial"])
            assert code == 0 and "Note: partial bag" in out, err
        elif code == 0:
            assert "Note: partial" not in out  # every message was read (damaged contents are rejected)
    assert partial >= 1


def test_out_of_range_stamps_give_a_clear_error_and_no_outputs(base: fuzz_bags.Base, tmp_path: Path) -> None:
    """Stamps at the end of int32 seconds (nanosec beyond 1e9): 'internal error: OverflowError' and a CSV before."""
    import random

    mutant = fuzz_bags.stamps_out_of_range(random.Random(0), base)
    while "int32_end_nanosec" not in mutant.description:
        mutant = fuzz_bags.stamps_out_of_range(random.Random(len(mutant.description) + 1), base)
    bag = tmp_path / "bag"
    mutant.write(bag)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, _, err = _run(replay.main, [str(bag), "--quiet", "--csv", str(out_dir / "o.csv"), "-o",
                                      str(out_dir / "o_bag")])
    assert code == 1 and "cannot be written to a bag" in err and "internal error" not in err, err
    assert list(out_dir.iterdir()) == []


def _subprocess(script: str, *, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True, text=True,
                          timeout=timeout, cwd=ROOT)


def test_replay_leaves_no_csv_when_the_bag_fails(base: fuzz_bags.Base, tmp_path: Path) -> None:
    """The CSV was committed before the output bag: a failing bag (here: a file-size limit) left it behind."""
    result = _subprocess(f"""
        import resource, signal, sys
        from transplanter_ident.cli import replay
        replay.main([{str(base.path)!r}, "--quiet"])  # compiled and cached before the limit
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (30_000, 30_000))  # the CSV fits, the bag does not
        sys.exit(replay.main([{str(base.path)!r}, "--quiet", "--csv", {str(tmp_path / "o.csv")!r},
                              "-o", {str(tmp_path / "o_bag")!r}]))
        """)
    assert result.returncode == 1 and "replay: error:" in result.stderr, result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_yaml_alias_bomb_is_refused_in_little_memory(tmp_path: Path) -> None:
    """A billion-laughs params file took replay to 4.5 GB: refused now, under a 1 GB address-space limit."""
    keys = [f"k{i}" for i in range(9)]
    lines = ["l0: &l0 {" + ", ".join(f"{k}: 1.0" for k in keys) + "}"]
    lines += [f"l{n}: &l{n} {{" + ", ".join(f"{k}: *l{n - 1}" for k in keys) + "}" for n in range(1, 10)]
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(lines) + "\nestimator:\n  ros__parameters:\n    vehicle: *l9\n")
    result = _subprocess(f"""
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))
        from transplanter_ident.config.params_file import ParamsError, read_params_file
        try:
            read_params_file({str(bomb)!r})
        except ParamsError as exc:
            print("refused:", exc)
        """, timeout=120.0)
    assert result.returncode == 0 and "refused:" in result.stdout and "aliases are expanded" in result.stdout, (
        result.stdout + result.stderr[-2000:])
    with pytest.raises(ParamsError, match="bomb.yaml"):
        read_params_file(bomb)


def test_tuner_refuses_to_write_when_every_candidate_diverged(base: fuzz_bags.Base, tmp_path: Path) -> None:
    """ekf.min_speed above the drive's speed: no candidate ever updates (DIVERGENCE_PENALTY); nothing written."""
    params = _yaml(tmp_path / "slow.yaml", "ekf: {min_speed: 20.0}\n")
    out = tmp_path / "tuned.yaml"
    code, _, err = _run(tuner.main, [str(base.path), "-o", str(out), "--params-file", str(params), "--particles", "4",
                                     "--iterations", "2", "--seed", "1"])
    assert code == 1 and "finite objective" in err and "nothing written" in err, err
    assert not out.exists()


def test_tuner_report_is_all_or_nothing(base: fuzz_bags.Base, tmp_path: Path) -> None:
    """A report that fails half-way (a file-size limit stops the first plot) left a partial folder and the YAML."""
    pytest.importorskip("matplotlib")
    out = tmp_path / "out"
    out.mkdir()
    argv = [str(base.path), "-o", str(out / "tuned.yaml"), "--particles", "4", "--iterations", "2", "--seed", "1",
            "--report", str(out / "report")]
    result = _subprocess(f"""
        import resource, signal, sys
        from transplanter_ident.cli import tuner
        argv = {argv!r}
        tuner.main([argv[0], "-o", {str(tmp_path / "warm.yaml")!r}, *argv[3:9]])  # compile and cache first
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4_000, 4_000))  # the YAML fits, a plot does not
        sys.exit(tuner.main(argv))
        """)
    assert result.returncode == 1 and "tuner: error:" in result.stderr, result.stdout + result.stderr
    assert list(out.iterdir()) == [], list(out.iterdir())
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "mine.txt").write_text("not a report")
    code, _, err = _run(tuner.main, [*argv[:9], "--report", str(tmp_path / "notes")])
    assert code == 1 and "not an earlier report" in err, err
    assert (tmp_path / "notes" / "mine.txt").exists()
