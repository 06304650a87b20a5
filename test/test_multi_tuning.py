"""Tests of multi-bag tuning (eqs. 21-22 over several bags), the leave-one-bag-out table, --jobs and --dask."""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from helpers import simulate_epochs

import transplanter_ident.cli.tuner as tuner
from transplanter_ident.bags.reader import Truth
from transplanter_ident.config.params_file import EstimatorParams, read_params_file
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.simulator import SensorNoise
from transplanter_ident.tuning.multi import (
    HoldOut,
    LeaveOneOut,
    MultiBagProblem,
    final_errors,
    fold_seed,
    leave_one_out,
)
from transplanter_ident.tuning.parallel import ProcessBackend, SerialBackend, plan_chunks
from transplanter_ident.tuning.problem import TuningProblem, noise_to_vector
from transplanter_ident.tuning.tune import tune_problem

#: short simulated drives of different kinds (30 s, 150 epochs each at 5 Hz)
SCENARIOS = (("sine", 11), ("step20-ccw", 12), ("step30-cw", 13))


@pytest.fixture(scope="module")
def sim_bags(tmp_path_factory) -> list[Path]:  # noqa: ANN001
    """Three 30 s simulated bags with ground truth."""
    from transplanter_ident.bags import write_sim_bag
    from transplanter_ident.sim.scenarios import build_config
    from transplanter_ident.sim.simulator import simulate

    root = tmp_path_factory.mktemp("multi_bags")
    paths = []
    for name, seed in SCENARIOS:
        path = root / name
        write_sim_bag(simulate(build_config(name, duration=30.0, seed=seed)), path)
        paths.append(path)
    return paths


@pytest.fixture(scope="module")
def sim_epochs(sim_bags) -> list:  # noqa: ANN001
    params = EstimatorParams()
    return [tuner.load_bag(str(bag), params)[0] for bag in sim_bags]


def _positions(problem: MultiBagProblem | TuningProblem, count: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.vstack([problem.start, problem.box.uniform(rng, count - 1)])


# --------------------------------------------------------------------------- the objective


def test_multi_bag_objective_is_the_epoch_weighted_mean(sim_epochs) -> None:  # noqa: ANN001
    config = EstimatorParams().config
    problem = MultiBagProblem.from_epochs(config, sim_epochs, "nll")
    singles = [TuningProblem.from_epochs(config, e, "nll") for e in sim_epochs]
    x = _positions(problem, 5)
    weights = np.array([len(e) for e in sim_epochs], dtype=float)
    expected = sum(w * p(x) for w, p in zip(weights, singles, strict=True)) / weights.sum()
    np.testing.assert_allclose(problem(x), expected, rtol=1e-12)
    noise = config.noise
    expected_start = sum(w * p.evaluate_noise(noise) for w, p in zip(weights, singles, strict=True)) / weights.sum()
    assert problem.evaluate_noise(noise) == pytest.approx(expected_start, rel=1e-12)
    # one bag: exactly that bag's objective
    np.testing.assert_array_equal(problem.subset([1])(x), singles[1](x))
    assert problem.subset([2]).epochs == (len(sim_epochs[2]),)
    assert problem.box == singles[0].box and np.array_equal(problem.start, singles[0].start)


def test_bags_must_share_the_configuration(sim_epochs) -> None:  # noqa: ANN001
    config = EstimatorParams().config
    mae = TuningProblem.from_epochs(config, sim_epochs[0], "mae")
    nll = TuningProblem.from_epochs(config, sim_epochs[1], "nll")
    with pytest.raises(ValueError, match="share"):
        MultiBagProblem((mae, nll))
    with pytest.raises(ValueError, match="span"):
        MultiBagProblem((nll, TuningProblem.from_epochs(config, sim_epochs[1], "nll", q_span=2.0)))
    with pytest.raises(ValueError, match="at least one"):
        MultiBagProblem(())


@pytest.mark.parametrize(("sizes", "candidates", "slots"), [((100, 300, 50), 20, 2), ((10,), 1, 4), ((5, 5), 7, 1),
                                                            ((1000,), 3, 8), ((7, 9, 11, 13), 40, 3)])
def test_chunks_cover_every_candidate_of_every_bag_once(sizes, candidates, slots) -> None:  # noqa: ANN001
    tasks = plan_chunks(sizes, candidates, slots)
    for bag in range(len(sizes)):
        covered = sorted(i for b, first, stop in tasks if b == bag for i in range(first, stop))
        assert covered == list(range(candidates))
    if slots == 1:
        assert len(tasks) == len(sizes)
    costs = [(stop - first) * sizes[bag] for bag, first, stop in tasks]
    assert costs == sorted(costs, reverse=True)  # largest first


def test_process_pool_values_equal_serial_values_bit_for_bit(sim_epochs) -> None:  # noqa: ANN001
    config = EstimatorParams().config
    serial = MultiBagProblem.from_epochs(config, sim_epochs, "mae")
    x = _positions(serial, 9, seed=4)
    pool = ProcessBackend(2)
    try:
        pool.wait_ready()  # so that the worker computes some of the chunks
        assert pool.ready()
        parallel = MultiBagProblem.from_epochs(config, sim_epochs, "mae", pool)
        np.testing.assert_array_equal(parallel.per_bag(x), serial.per_bag(x))
        np.testing.assert_array_equal(parallel(x), serial(x))
        assert pool.map(math.hypot, [(3.0, 4.0), (5.0, 12.0)]) == [5.0, 13.0]
    finally:
        pool.close()


@pytest.mark.parametrize("algorithm", ["ipso", "cmaes"])
def test_tuning_on_a_ready_pool_equals_serial_tuning(sim_epochs, algorithm: str) -> None:  # noqa: ANN001
    config = EstimatorParams().config
    serial = tune_problem(MultiBagProblem.from_epochs(config, sim_epochs, "nll"), algorithm=algorithm,
                          particles=6, iterations=4, seed=8)
    pool = ProcessBackend(2)
    try:
        pool.wait_ready()
        parallel = tune_problem(MultiBagProblem.from_epochs(config, sim_epochs, "nll", pool), algorithm=algorithm,
                                particles=6, iterations=4, seed=8)
    finally:
        pool.close()
    assert parallel.result.fitness == serial.result.fitness
    np.testing.assert_array_equal(parallel.result.position, serial.result.position)
    assert [h.best_fitness for h in parallel.result.history] == [h.best_fitness for h in serial.result.history]


def _worker_warm_up(folder: Path, wait_for_host: Callable[[], bool]) -> None:
    """A worker's warm-up that records whether the host's warm-up had finished when the wait returned."""
    (folder / f"waiting-{os.getpid()}").touch()
    released = wait_for_host()
    (folder / f"worker-{os.getpid()}").write_text(f"{released} {(folder / 'host').exists()}")


def _host_warm_up(folder: Path) -> None:
    """The host's warm-up: done only once a worker is waiting for it (so a worker that did not wait is caught)."""
    deadline = time.monotonic() + 60.0
    while not list(folder.glob("waiting-*")) and time.monotonic() < deadline:
        time.sleep(0.01)
    (folder / "host").touch()


@pytest.mark.parametrize("host", [True, False])
def test_workers_wait_for_the_hosts_warm_up(tmp_path: Path, host: bool) -> None:
    """The workers' warm-up goes on after this process's (the compiled step is shared through the disk cache).

    Without a host warm-up the workers are released at the first parallel call, not held until the timeout.
    """
    backend = ProcessBackend(3, warm_up=partial(_worker_warm_up, tmp_path),
                             host_warm_up=partial(_host_warm_up, tmp_path) if host else None)
    try:
        if host:
            backend.start()
        assert backend.map(pow, [(i, 2) for i in range(8)]) == [i * i for i in range(8)]
        backend.wait_ready()
    finally:
        backend.close()
    records = sorted(path.read_text() for path in tmp_path.glob("worker-*"))
    assert records == [f"True {host}"] * 2


def test_process_backend_runs_calls_here_and_on_workers_in_order() -> None:
    backend = ProcessBackend(3)
    try:
        assert backend.map(pow, [(i, 2) for i in range(25)]) == [i * i for i in range(25)]
        assert backend.map(pow, [(3, 3)]) == [27] and backend.map(pow, []) == []
        with pytest.raises(ZeroDivisionError):
            backend.map(divmod, [(1, 1), (2, 1), (1, 0), (4, 2), (5, 1)])
        assert backend.map(divmod, [(7, 2), (9, 4)]) == [(3, 1), (2, 1)]  # still usable
    finally:
        backend.close()
    assert ProcessBackend(1).map(pow, [(2, 5), (2, 6)]) == [32, 64]  # one job: no pool at all
    with pytest.raises(ValueError, match="jobs"):
        ProcessBackend(0)


def test_serial_backend_restores_the_thread_count(sim_epochs) -> None:  # noqa: ANN001
    import numba

    before = numba.get_num_threads()
    problem = MultiBagProblem.from_epochs(EstimatorParams().config, sim_epochs[:1], "nll", SerialBackend())
    problem(_positions(problem, 3))
    assert numba.get_num_threads() == before


def test_wins_count_bags_where_multi_bag_is_not_worse_on_both_stiffnesses() -> None:
    rows = (HoldOut("a", 10, (0.0, 0.0, 0.0), (0.10, -0.02, 0.05), (0.01, 0.01, -0.01), (0.05, 0.02)),
            HoldOut("b", 10, (0.0, 0.0, 0.0), (0.01, 0.03, -0.02), (0.01, 0.01, 0.01), (0.01, 0.10)),
            HoldOut("c", 10, (0.0, 0.0, 0.0), None, None, None))
    table = LeaveOneOut("nll", rows)
    assert table.wins() == (2, 1, 1, 1)  # a: <= default and <= one other; b: <= single only
    text = table.format()
    assert "on 1/2 bags, <= single-bag (in-sample) on 1/2, <= single-bag tuned on one other bag (median) on 1/2" in text
    assert " 5.0% " in text and "10.0%" in text  # the 'one other' medians, unsigned


def test_fold_seeds_differ_and_repeat() -> None:
    seeds = {fold_seed(3, kind, i) for kind in (1, 2) for i in range(5)}
    assert len(seeds) == 10 and fold_seed(3, 1, 0) == fold_seed(3, 1, 0)


# --------------------------------------------------------------------------- the command


def test_leave_one_out_scores_every_single_bag_q_r_on_the_other_bags(sim_bags) -> None:  # noqa: ANN001
    """The 'one other' column is the median |final error| of the other bags' single-bag Q/R (checked by hand)."""
    params = EstimatorParams()
    loaded = [tuner.load_bag(str(bag), params, truth=True) for bag in sim_bags]
    epochs, truths = [e for e, _ in loaded], [t for _, t in loaded]
    problem = MultiBagProblem.from_epochs(params.config, epochs, "nll")

    def fake_tune(fold: MultiBagProblem, seed: int):  # noqa: ANN202 - a distinct R per fold, no search
        index = [[q is p for q in problem.problems].index(True) for p in fold.problems]
        factor = 1.0 + sum(0.5 * 3**j for j in index)  # alone 1.5, 2.5, 5.5; in pairs 3, 6, 7
        noise = params.config.noise
        return replace(params.config, noise=replace(noise, measurement_noise=tuple(factor * v for v in
                                                                                     noise.measurement_noise)))

    table = leave_one_out(problem, epochs, truths, [b.name for b in sim_bags], fake_tune, seed=3)
    singles = [fake_tune(problem.subset([j]), 0) for j in range(3)]
    for i, row in enumerate(table.rows):
        cf, cr = final_errors([singles[j] for j in range(3) if j != i], epochs[i], truths[i])
        assert row.elsewhere == pytest.approx((np.median(np.abs(cf)), np.median(np.abs(cr))), rel=1e-12)
        own_cf, own_cr = final_errors([singles[i]], epochs[i], truths[i])
        assert (row.final_cf[1], row.final_cr[1]) == pytest.approx((own_cf[0], own_cr[0]), rel=1e-12)


def _tuner(*args: object) -> int:
    return tuner.main([str(a) for a in args])


def test_cli_tunes_several_bags_with_a_leave_one_out_table(sim_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    out, report = tmp_path / "multi.yaml", tmp_path / "report"
    assert _tuner(*sim_bags, "-o", out, "--particles", "6", "--iterations", "3", "--seed", "5", "--jobs", "1",
                  "--epoch-cache", tmp_path / "cache", "--report", report) == 0
    captured = capsys.readouterr()
    header = [line for line in out.read_text().splitlines() if line.startswith("#")]
    assert sum(line.startswith("# bag: ") for line in header) == 3
    assert any("3 bags, 450 epochs" in line for line in header)
    assert set(read_params_file(out)) >= {"ekf.process_noise", "ekf.measurement_noise"}
    assert captured.out.count("Table 2 on ") == 3
    assert "Leave-one-bag-out (nll)" in captured.out
    table = captured.out.split("Leave-one-bag-out", 1)[1].splitlines()
    rows = [line for line in table if line.startswith(str(sim_bags[0].parent))]
    assert len(rows) == 3
    for row in rows:  # objective x3 and the Cf, Cr errors x4 (the bags have ground truth)
        assert row.count("%") == 8, row
    assert "held-out |error| of Cf and Cr with multi-bag Q/R" in captured.out
    assert captured.err.count("leave-one-out ") == 3
    assert sum(line.startswith("iteration") for line in captured.err.splitlines()) == 4  # the main run only
    names = {p.name for p in report.iterdir()}
    assert {"fig4_objective.png", "report.txt", "leave_one_out.txt"} <= names
    for n, bag in enumerate(sim_bags, 1):
        assert f"fig5_stiffness_tuned_{n}_{bag.name}.png" in names
        assert f"fig6_model_output_tuned_{n}_{bag.name}.png" in names
    text = (report / "report.txt").read_text()
    assert text.count("Table 2") == 3 and "Leave-one-bag-out" in text


def test_no_leave_one_out_and_cmaes(sim_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "cmaes.yaml"
    assert _tuner(*sim_bags[:2], "-o", out, "--algorithm", "cmaes", "--particles", "5", "--iterations", "2",
                  "--seed", "1", "--jobs", "1", "--no-leave-one-out", "--no-epoch-cache", "--q-span", "inf") == 0
    captured = capsys.readouterr()
    assert "# Q searched over the whole box (tuner --q-span)" in out.read_text()
    assert "Leave-one-bag-out" not in captured.out and "cmaes: nll" in captured.out
    assert "algorithm: cmaes" in out.read_text()
    assert sum(line.startswith("iteration") for line in captured.err.splitlines()) == 3
    assert "(decoded)" in captured.err  # no cache: decoded, nothing kept


def test_jobs_1_and_2_write_the_same_yaml(sim_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    texts, tables = [], []
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}.yaml"
        assert _tuner(*sim_bags, "-o", out, "--particles", "6", "--iterations", "3", "--seed", "9",
                      "--jobs", jobs, "--epoch-cache", tmp_path / f"cache{jobs}") == 0
        captured = capsys.readouterr()
        assert f"; {jobs} job" in captured.err
        texts.append(out.read_bytes())
        assert "Leave-one-bag-out" in captured.out
        # Table 2 and the bound of each bag (computed on the workers with --jobs 2) and the leave-one-out table;
        # only the line with the search's wall time differs
        tables.append([line for line in captured.out.splitlines() if not line.startswith("ipso:")])
    assert texts[0] == texts[1]
    assert tables[0] == tables[1]
    assert sum(line.startswith("Table 2 on ") for line in tables[0]) == len(sim_bags)


def test_dask_cluster_writes_the_same_yaml_as_local(sim_bags, tmp_path, capsys) -> None:  # noqa: ANN001
    """A LocalCluster (2 worker processes, 127.0.0.1 only) gives the YAML of a local run."""
    psutil = pytest.importorskip("psutil")
    from distributed import LocalCluster

    common = [*sim_bags[:2], "--particles", "6", "--iterations", "3", "--seed", "2", "--no-leave-one-out",
              "--epoch-cache", tmp_path / "cache"]
    assert _tuner("-o", tmp_path / "local.yaml", "--jobs", "1", *common) == 0
    with LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        listening = [c.laddr.ip for proc in [psutil.Process(), *psutil.Process().children(recursive=True)]
                     for c in proc.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN]
        assert listening and set(listening) == {"127.0.0.1"}, listening
        assert _tuner("-o", tmp_path / "dask.yaml", "--dask", cluster.scheduler_address, *common) == 0
    captured = capsys.readouterr()
    assert "Dask cluster tcp://127.0.0.1:" in captured.err
    assert (tmp_path / "dask.yaml").read_bytes() == (tmp_path / "local.yaml").read_bytes()


def test_unreachable_dask_scheduler_is_one_line(sim_bags, tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    import socket

    monkeypatch.setattr("transplanter_ident.tuning.parallel.DASK_CONNECT_TIMEOUT", 2.0)
    with socket.socket() as sock:  # a free port on loopback that nothing listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    code = _tuner(sim_bags[0], "-o", tmp_path / "o.yaml", "--dask", f"tcp://127.0.0.1:{port}", "--jobs", "1")
    assert code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tuner: error: --dask") and "cannot connect" in err[0], err
    assert not (tmp_path / "o.yaml").exists()


@pytest.mark.parametrize("flags", [["--jobs", "0"], ["--jobs", "x"], ["--algorithm", "cma"], ["--q-span", "0"],
                                   ["--q-span", "nan"], ["--q-span", "-1"], ["--q-span", "x"]])
def test_invalid_new_flags_are_one_line(flags: list[str], tmp_path, capsys) -> None:  # noqa: ANN001
    with pytest.raises(SystemExit) as exc:
        tuner.main(["bag", "-o", str(tmp_path / "o.yaml"), *flags])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("tuner: error: argument") and flags[0] in err[0], err


# --------------------------------------------------------------------------- the design span of Q

#: the leave-one-bag-out fold that went wrong with Q searched over the whole box (seeds 21, 22, GNSS noise
#: 2x the default R): Q/R tuned on the six other scenarios, held out on stiffness-drop
SPAN_SOURCES = ("sine", "step20-ccw", "step30-cw", "surface-change", "multisine", "wet-saturating")
SPAN_SEEDS = (21, 22)


def _noisier_drive(scenario: str, seed: int) -> tuple[EpochArrays, Truth]:
    """A scenario's drive with the GNSS noise 2x the default R: its epochs and truth."""
    base = SensorNoise()
    noise = replace(base, velocity=2.0 * base.velocity, heading=2.0 * base.heading)
    result, epochs = simulate_epochs(replace(build_config(scenario, seed=seed), noise=noise))
    nan = np.full_like(result.gnss_time, np.nan)
    return epochs, Truth(result.gnss_time, result.truth_cf, result.truth_cr, nan, nan, nan)


@functools.cache
def span_outcome(seed: int) -> tuple[dict[float, float], dict[float, float]]:
    """(excess, q_psi) by span (1 decade, the whole box), Q/R tuned on SPAN_SOURCES.

    excess: the held-out stiffness-drop drive's final error beyond the defaults' (the worse of Cf and
    Cr); q_psi: how many decades the heading's process noise rose.
    """
    config = EstimatorParams().config
    sources = [_noisier_drive(name, seed)[0] for name in SPAN_SOURCES]
    held_out, truth = _noisier_drive("stiffness-drop", seed)
    excess, q_psi = {}, {}
    for span in (1.0, math.inf):
        problem = MultiBagProblem.from_epochs(config, sources, "nll", q_span=span)
        tuned = tune_problem(problem, seed=7).tuned_config
        q_psi[span] = noise_to_vector(tuned.noise, ("q_psi",))[0] - noise_to_vector(config.noise, ("q_psi",))[0]
        (cf_default, cf_tuned), (cr_default, cr_tuned) = final_errors([config, tuned], held_out, truth)
        excess[span] = max(abs(cf_tuned) - abs(cf_default), abs(cr_tuned) - abs(cr_default))
    return excess, q_psi


@pytest.mark.parametrize("seed", SPAN_SEEDS)
def test_q_tuned_on_other_drives_within_its_span_keeps_a_held_out_change_drive_as_accurate(seed: int) -> None:
    """Issue #13: Q/R tuned on the other scenarios (model misfit included) do not cost the held-out drive accuracy.

    Searched over the whole box, the NLL on drives the linear model does not fit buys heading
    and yaw-rate process noise far above the design (measured q_psi 1e-5 vs 1e-8), and the held-out
    stiffness-drop drive ended 11 and 1.7 points further off than with the defaults (seeds 21, 22;
    with the speed's noise in Q, ekf.speed_noise: 0.06 and 1.7 points; with the linear range a
    force: 0.17 and 1.3; since the directional change test sees the drop whatever q_psi, 0.1 at
    most). Within the default span (1 decade): at most 0.5 points (0.03 and 0.16 measured);
    asserted: <= 1 point, and q_psi <= 1 decade up (+0.08 and +0.21).
    """
    excess, q_psi = span_outcome(seed)
    assert excess[1.0] <= 0.01, excess
    assert q_psi[1.0] <= 1.0 + 1e-9


def test_over_the_whole_box_the_heading_noise_runs_away() -> None:
    """The span's teeth: searched over the whole box, q_psi rises beyond the span on a seed of the two.

    Measured +1.32 decades on seed 21 and +0.26 on seed 22 (-0.26 and -0.14 within the span), since the
    heading's misalignment is a filter state (session 27: it takes up part of the misfit that q_psi took);
    before, +1.99 and +0.39 (at ekf.change_shift 0.7; +1.76 and +2.86 at 1, with the linear range a force).
    Asserted: beyond the span (1 decade) on one, and on each more than within the span.
    """
    rises = [span_outcome(seed)[1] for seed in SPAN_SEEDS]
    assert max(q_psi[math.inf] for q_psi in rises) > 1.0, rises
    assert all(q_psi[math.inf] > q_psi[1.0] for q_psi in rises), rises
