"""Tests of the `tuner` command (IPSO/PSO over Q and R, eqs. 15-22; Table 2) and its bad-input handling."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

import transplanter_ident.cli.tuner as tuner
from transplanter_ident.bags.samples import ensure_bag
from transplanter_ident.config.params_file import EstimatorParams, load_params, read_params_file
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.evaluation.metrics import stiffness_error
from transplanter_ident.tuning.tune import compare

ROOT = Path(__file__).resolve().parents[1]
DEFAULTS = ROOT / "config" / "estimator.yaml"


@pytest.fixture(scope="module")
def sample_bags(tmp_path_factory) -> dict[str, Path]:  # noqa: ANN001
    """The committed sample bags (simulated with `make bags`' seeds if this checkout lacks them)."""
    fallback = tmp_path_factory.mktemp("bags")
    return {name: ensure_bag(name, ROOT / "bags", fallback) for name in ("step20-ccw", "sine")}


@pytest.fixture(scope="module")
def short_bag(tmp_path_factory) -> Path:  # noqa: ANN001
    """A 5 s bag: about 25 epochs, too short to tune."""
    from transplanter_ident.bags import write_sim_bag
    from transplanter_ident.sim.scenarios import build_config
    from transplanter_ident.sim.simulator import simulate

    path = tmp_path_factory.mktemp("short") / "short"
    write_sim_bag(simulate(build_config("sine", duration=5.0, seed=0)), path)
    return path


@pytest.fixture(scope="module")
def tuned_run(sample_bags, tmp_path_factory) -> tuple[Path, str, Path]:  # noqa: ANN001
    """One full CLI run (paper settings) on step20-ccw with --report; (yaml, stdout, report dir)."""
    out = tmp_path_factory.mktemp("tuned")
    yaml_path, report = out / "tuned.yaml", out / "report"
    result = subprocess.run(
        [sys.executable, "-m", "transplanter_ident.cli.tuner", str(sample_bags["step20-ccw"]), "-o", str(yaml_path),
         "--params-file", str(DEFAULTS), "--seed", "3", "--objective", "mae", "--report", str(report)],
        capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=300)
    assert result.returncode == 0, result.stderr
    progress = [line for line in result.stderr.splitlines() if line.startswith("iteration")]
    assert len(progress) == 41 and "best" in progress[-1]  # the initial swarm plus one line per iteration
    return yaml_path, result.stdout, report


def _one_line_error(capsys, code: int) -> str:  # noqa: ANN001
    assert code != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("tuner: ")
    return err[0]


def _leftovers(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp") or p.name.startswith("."))


# --------------------------------------------------------------------------- tuning works


def test_tuned_objective_not_worse_and_table2_printed(sample_bags) -> None:  # noqa: ANN001
    params = EstimatorParams()
    epochs, _ = tuner.load_bag(str(sample_bags["step20-ccw"]), params)
    outcome = tuner.tune(params.config, epochs, seed=1)
    assert outcome.result.fitness <= outcome.start_fitness
    chaotic = sum(record.chaotic_particles for record in outcome.result.history)
    assert outcome.result.evaluations >= 20 * 41 and (outcome.result.evaluations > 20 * 41) == (chaotic > 0)
    assert outcome.problem.evaluate_noise(outcome.tuned_config.noise) == pytest.approx(outcome.result.fitness)
    comparison = compare(outcome, epochs)
    for row in (comparison.start, comparison.tuned):
        assert row.epochs > 400 and all(math.isfinite(v) for v in (row.mean_error_vy, row.mean_error_r))
    text = comparison.format("Table 2")
    assert "EKF (start Q/R)" in text and "IPSO-EKF (tuned)" in text and "ratio tuned/start" in text
    assert 0.5 < comparison.ratio("mean_error_vy") < 1.5 and 0.5 < comparison.ratio("mean_error_r") < 1.5


def test_cli_writes_a_layerable_yaml_with_header(tuned_run) -> None:  # noqa: ANN001
    yaml_path, stdout, _ = tuned_run
    text = yaml_path.read_text()
    header = [line for line in text.splitlines() if line.startswith("#")]
    for word in ("bag:", "objective: mae", "fitness:", "seed: 3", "algorithm: ipso", "evaluations:",
                 "Q searched within 1 decade of the start (tuner --q-span)"):
        assert any(word in line for line in header), word
    flat = read_params_file(yaml_path)
    assert set(flat) == {"ekf.discretization", "ekf.stiffness_state", "ekf.measurement", "ekf.process_noise",
                         "ekf.measurement_noise", "ekf.heading_process_noise", "ekf.process_noise_units"}
    assert flat["ekf.process_noise_units"] == "per_second"  # the units the Q was tuned in travel with it
    assert (flat["ekf.discretization"], flat["ekf.stiffness_state"], flat["ekf.measurement"]) == (
        "exact", "log", "heading")
    assert all(isinstance(v, float) for v in [*flat["ekf.process_noise"], *flat["ekf.measurement_noise"]])
    layered = load_params([DEFAULTS, yaml_path])
    assert layered.config.noise.process_noise == tuple(flat["ekf.process_noise"])
    assert layered.config.vehicle == load_params([DEFAULTS]).config.vehicle
    assert "Table 2" in stdout and "ratio tuned/start" in stdout and "IPSO-EKF (tuned)" in stdout
    assert not _leftovers(yaml_path.parent)


def test_cli_is_reproducible_with_a_seed(tuned_run, sample_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    yaml_path, _, _ = tuned_run
    again = tmp_path / "again.yaml"
    assert tuner.main([str(sample_bags["step20-ccw"]), "-o", str(again), "--params-file", str(DEFAULTS),
                       "--seed", "3", "--objective", "mae"]) == 0
    strip = lambda p: [line for line in p.read_text().splitlines() if not line.startswith("# bag:")]  # noqa: E731
    assert strip(again) == strip(yaml_path)


def test_report_writes_the_figures(tuned_run) -> None:  # noqa: ANN001
    _, stdout, report = tuned_run
    names = {p.name for p in report.iterdir()}
    assert {"fig4_objective.png", "fig5_stiffness_tuned.png", "fig6_model_output_tuned.png",
            "fig7_model_output_start.png", "report.txt"} <= names
    for name in names:
        if name.endswith(".png"):
            assert (report / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "report:" in stdout


def test_pso_and_nll_and_small_swarm(sample_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "pso.yaml"
    assert tuner.main([str(sample_bags["step20-ccw"]), "-o", str(out), "--algorithm", "pso", "--objective", "nll",
                       "--particles", "4", "--iterations", "3", "--seed", "0"]) == 0
    captured = capsys.readouterr()
    assert "pso: nll" in captured.out
    bound = next(line for line in captured.out.splitlines() if "Cramér-Rao bound" in line)  # issue #11 item 2
    assert "of it" in bound and "weakest along" in bound, bound
    assert sum(line.startswith("iteration") for line in captured.err.splitlines()) == 4
    assert "algorithm: pso, objective: nll" in out.read_text()


def test_both_objectives_run_on_the_sine_bag_with_truth(sample_bags) -> None:  # noqa: ANN001
    """Both objectives (mae, nll) give finite results; the comparison itself is bench/objectives.py and the demo."""
    params = EstimatorParams()
    epochs, truth = tuner.load_bag(str(sample_bags["sine"]), params, truth=True)
    assert truth is not None
    true_f, true_r = truth.at(epochs.t)
    for objective in ("mae", "nll"):
        outcome = tuner.tune(params.config, epochs, objective=objective, particles=8, iterations=5, seed=0)
        assert math.isfinite(outcome.result.fitness) and outcome.result.fitness <= outcome.start_fitness
        err = stiffness_error(run_sequence(outcome.tuned_config, epochs), true_f, true_r)
        assert all(math.isfinite(v) for v in (err.final_front, err.final_rear))
        assert abs(err.final_front) < 0.5 and abs(err.final_rear) < 0.5


# --------------------------------------------------------------------------- bad input


def test_missing_bag_is_one_line(tmp_path, capsys) -> None:  # noqa: ANN001
    line = _one_line_error(capsys, tuner.main([str(tmp_path / "nope"), "-o", str(tmp_path / "o.yaml")]))
    assert "nope" in line
    assert not (tmp_path / "o.yaml").exists()


def test_corrupt_bag_is_one_line(tmp_path, capsys) -> None:  # noqa: ANN001
    bag = tmp_path / "junk.mcap"
    bag.write_bytes(b"\x89MCAP0\r\n" + os.urandom(200))
    line = _one_line_error(capsys, tuner.main([str(bag), "-o", str(tmp_path / "o.yaml")]))
    assert "junk.mcap" in line
    assert not (tmp_path / "o.yaml").exists()


def test_too_short_bag_says_how_many_epochs(short_bag, tmp_path, capsys) -> None:  # noqa: ANN001
    from transplanter_ident.bags import read_epochs

    count = len(read_epochs(short_bag, EstimatorParams())[0])
    line = _one_line_error(capsys, tuner.main([str(short_bag), "-o", str(tmp_path / "o.yaml")]))
    assert "too short to tune" in line and f"only {count} epochs" in line and f"at least {tuner.MIN_EPOCHS}" in line
    assert not (tmp_path / "o.yaml").exists()


def test_output_path_is_a_directory(sample_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    target = tmp_path / "out.yaml"
    target.mkdir()
    line = _one_line_error(capsys, tuner.main([str(sample_bags["step20-ccw"]), "-o", str(target)]))
    assert "is a directory" in line
    assert list(target.iterdir()) == [] and _leftovers(tmp_path) == []


def test_output_directory_missing(sample_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    line = _one_line_error(capsys, tuner.main([str(sample_bags["step20-ccw"]), "-o", str(tmp_path / "no" / "o.yaml")]))
    assert "does not exist" in line


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write into a read-only directory")
def test_output_directory_read_only(sample_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        line = _one_line_error(capsys, tuner.main([str(sample_bags["step20-ccw"]), "-o", str(locked / "o.yaml")]))
        assert "not writable" in line
        assert list(locked.iterdir()) == []
    finally:
        locked.chmod(0o755)


def test_unwritable_output_at_write_time_is_one_line(sample_bags, tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    """As root the read-only test above is skipped: make the temp file creation fail instead."""

    def refuse(*args, dir=None, **kwargs):  # noqa: ANN002, ANN003, ANN202, A002
        raise PermissionError(13, "Permission denied", str(dir))

    monkeypatch.setattr("transplanter_ident.files.tempfile.mkstemp", refuse)
    target = tmp_path / "o.yaml"
    assert tuner.main([str(sample_bags["step20-ccw"]), "-o", str(target), "--particles", "2", "--iterations", "1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert [line for line in err if "error" in line] == [err[-1]] and "Permission denied" in err[-1]
    assert list(tmp_path.iterdir()) == []


def test_failed_write_leaves_no_half_written_yaml(sample_bags, tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    """A failure at the rename (after the temp file is written) keeps the old file and removes the temp."""
    target = tmp_path / "tuned.yaml"
    target.write_text("old\n")

    def broken_replace(src, dst) -> None:  # noqa: ANN001
        raise OSError(28, "No space left on device", str(dst))

    monkeypatch.setattr("transplanter_ident.files.os.replace", broken_replace)
    assert tuner.main([str(sample_bags["step20-ccw"]), "-o", str(target), "--particles", "2", "--iterations", "1"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if "error" in line]
    assert len(errors) == 1 and errors[0] == err[-1] and "No space left" in errors[0]  # after the progress lines
    assert target.read_text() == "old\n"
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("flags", [["--particles", "0"], ["--iterations", "-3"], ["--particles", "x"],
                                   ["--algorithm", "foo"], ["--objective", "rmse"], ["--seed", "-1"]])
def test_invalid_flags_are_one_line(flags: list[str], tmp_path, capsys) -> None:  # noqa: ANN001
    with pytest.raises(SystemExit) as exc:
        tuner.main(["bag", "-o", str(tmp_path / "o.yaml"), *flags])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tuner: error: argument") and flags[0] in err[0], err


def test_bad_params_file_is_one_line(sample_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    bad = tmp_path / "bad.yaml"
    bad.write_text("estimator:\n  ros__parameters:\n    ekf: {process_noise: [1.0, 2.0]}\n")
    line = _one_line_error(capsys, tuner.main([str(sample_bags["step20-ccw"]), "-o", str(tmp_path / "o.yaml"),
                                               "--params-file", str(bad)]))
    assert "process_noise" in line


def test_console_script_bad_flag_subprocess(tmp_path) -> None:  # noqa: ANN001
    result = subprocess.run([sys.executable, "-m", "transplanter_ident.cli.tuner", "x", "-o", str(tmp_path / "o.yaml"),
                             "--particles", "0"], capture_output=True, text=True, cwd=ROOT,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "--particles" in result.stderr


def test_the_demo_reads_the_checkouts_bags_and_parameters() -> None:
    """`make demo` runs on bags/ and config/estimator.yaml of this checkout (not simulated stand-ins)."""
    from transplanter_ident.cli import demo

    assert (demo.ROOT / "bags" / demo.TUNE_BAG / "metadata.yaml").is_file()
    files, _ = demo.base_parameters()
    assert files == [demo.ROOT / "config" / "estimator.yaml"]
