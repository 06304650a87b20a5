"""``tuner --estimate-delay`` (issue #13 item 4) and split Q (item 2): gnss.delay found on simulated drives.

Acceptance (issue #13): on simulated drives whose GNSS is 0, 40, 80 and 120 ms late, the
estimated ``gnss.delay`` is within 10 ms. Measured here on the project's identification drive
(``sine``, 2 m/s, +-15 deg, 5 Hz GNSS, 120 s) with two seeds per delay, each drive its own seed;
``bench/delay_figures.py`` runs ten seeds per delay on ``sine`` and ``multisine``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import sim_samples

from transplanter_ident.cli import replay, tuner
from transplanter_ident.config.params_file import EstimatorParams, load_params
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.simulator import simulate
from transplanter_ident.tuning.delay import delay_objective, search_delay

TOLERANCE = 0.010  # s (issue #13)
TRUE_DELAYS = (0.0, 0.04, 0.08, 0.12)
SEEDS_PER_DELAY = 2


def test_search_finds_the_minimum_of_a_known_curve() -> None:
    calls: list[list[float]] = []

    def curve(delays: list[float]) -> list[float]:
        calls.append(list(delays))
        return [(d - 0.0831) ** 2 if d < 0.25 else math.nan for d in delays]

    estimate = search_delay(curve)
    assert estimate.delay == pytest.approx(0.084) and estimate.fitness == pytest.approx(0.0009**2)
    assert len(calls) == 2 and len(calls[0]) == 16  # a coarse grid, then one fine grid, each in one batch
    assert not set(calls[0]) & set(calls[1])  # nothing evaluated twice
    assert estimate.value_at(0.3) == math.inf and estimate.value_at(0.0) == pytest.approx(0.0831**2)
    assert search_delay(lambda ds: [1.0] * len(ds)).delay == 0.0  # ties: the smallest delay
    with pytest.raises(ValueError, match="delay search"):
        search_delay(curve, 0.3, 0.1)


@pytest.mark.parametrize("index", range(len(TRUE_DELAYS)))
def test_simulated_delay_is_found_within_10_ms(index: int) -> None:
    """The search on the tuner's objective (NLL at the default Q/R) over each drive's samples."""
    true = TRUE_DELAYS[index]
    params = EstimatorParams()
    errors = []
    for seed in range(index * SEEDS_PER_DELAY, (index + 1) * SEEDS_PER_DELAY):
        samples = sim_samples(simulate(build_config("sine", duration=120.0, seed=seed, gnss_delay=true)))
        estimate = search_delay(lambda delays: [delay_objective(samples, params, d, "nll")[0] for d in delays])  # noqa: B023
        errors.append(estimate.delay - true)
    assert np.max(np.abs(errors)) <= TOLERANCE, f"true {true} s: errors {errors}"


# --------------------------------------------------------------------------- the command


@pytest.fixture(scope="module")
def late_bag(tmp_path_factory) -> Path:  # noqa: ANN001
    """The identification drive with its GNSS stamped 80 ms late (ground truth included)."""
    from transplanter_ident.bags import write_sim_bag

    path = tmp_path_factory.mktemp("delay") / "late80"
    write_sim_bag(simulate(build_config("sine", duration=120.0, seed=21, gnss_delay=0.08)), path)
    return path


def _final_errors(text: str) -> tuple[float, float]:
    match = re.search(r"final Cf ([-+\d.]+) %, Cr ([-+\d.]+) %", text)
    assert match, text
    return float(match.group(1)), float(match.group(2))


def test_cli_writes_the_delay_and_replay_loads_it(late_bag, tmp_path, capsys) -> None:  # noqa: ANN001
    out, cache = tmp_path / "tuned.yaml", tmp_path / "cache"
    args = ["--particles", "4", "--iterations", "2", "--seed", "3", "--jobs", "1", "--epoch-cache", str(cache)]
    assert tuner.main([str(late_bag), "-o", str(out), "--estimate-delay", *args]) == 0
    printed = capsys.readouterr()
    assert "estimated gnss.delay:" in printed.out and "input samples decoded" in printed.err
    tuned = load_params([str(out)])
    assert abs(tuned.gnss.delay - 0.08) <= TOLERANCE
    assert "# estimated gnss.delay:" in out.read_text()
    # split Q: the stiffness random walk is kept at its designed value
    assert tuned.config.noise.process_noise[2:] == EstimatorParams().config.noise.process_noise[2:]
    assert "kept by design" in out.read_text()

    assert replay.main([str(late_bag)]) == 0
    unset = _final_errors(capsys.readouterr().out)
    assert replay.main([str(late_bag), "--params-file", str(out)]) == 0
    with_delay = _final_errors(capsys.readouterr().out)
    assert max(map(abs, with_delay)) < 0.5 * min(map(abs, unset)), (with_delay, unset)

    # the epochs at the estimated delay were cached under it: tuning with the YAML skips decoding
    assert tuner.main([str(late_bag), "-o", str(tmp_path / "again.yaml"), "--params-file", str(out), *args]) == 0
    assert "from the epoch cache" in capsys.readouterr().err


def test_tune_stiffness_noise_searches_the_stiffness_random_walk(late_bag, tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "full.yaml"
    assert tuner.main([str(late_bag), "-o", str(out), "--tune-stiffness-noise", "--particles", "4",
                       "--iterations", "2", "--seed", "3", "--jobs", "1", "--no-epoch-cache"]) == 0
    capsys.readouterr()
    text = out.read_text()
    assert "q_cf=" in text.split("# tuned:")[1].splitlines()[0] and "kept by design" not in text
    assert "gnss" not in load_params([str(out)]).extra and "delay:" not in text


def test_delay_search_gives_the_same_yaml_for_any_jobs(late_bag, tmp_path, capsys) -> None:  # noqa: ANN001
    outputs = []
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}.yaml"
        assert tuner.main([str(late_bag), "-o", str(out), "--estimate-delay", "--particles", "4", "--iterations", "1",
                           "--seed", "5", "--jobs", str(jobs), "--no-epoch-cache"]) == 0
        outputs.append(out.read_bytes())
    capsys.readouterr()
    assert outputs[0] == outputs[1]
