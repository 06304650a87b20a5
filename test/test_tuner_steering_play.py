"""``tuner --estimate-steering-play``: the steering linkage's play found on simulated drives.

A play of 0.1 deg left out moves Cf by about 10 % while the estimate stays valid (test_steering_play.py),
so the tuner searches ``vehicle.steering_play`` like ``gnss.delay``: each candidate re-assembles the bags'
decoded samples, scored by the NLL at the starting Q/R, pooled over the bags (tuning/steering_play.py).
Measured on two identification drives (seeds 0-1): 0.005 rad (0.29 deg) -> 0.0055 +- 0.00043 rad,
-0.004 -> -0.0038 +- 0.00049, none -> 0.0002 +- 0.0005; required within 3 std, and the std within
0.0001-0.002 rad. A std of 0.0005 rad (0.03 deg) still leaves ~3 % of Cf: tune on several drives.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from drives import sine_drive
from helpers import final_errors, sim_samples

from transplanter_ident.cli import replay, tuner
from transplanter_ident.config.params_file import load_params
from transplanter_ident.sim.simulator import simulate
from transplanter_ident.tuning.steering_play import estimate_steering_play, play_objective


def _scores(curve):  # noqa: ANN001, ANN202
    return lambda plays: [[(curve(p), 500)] for p in plays]


def test_the_search_finds_the_minimum_of_a_known_curve_and_its_curvature() -> None:
    """A parabola 500 x (p - 0.0037)^2 / (2 s^2) per epoch with s = 0.001: the play within the fine step, std s."""
    s = 0.001
    estimate = estimate_steering_play(_scores(lambda p: (p - 0.0037) ** 2 / (2.0 * 500 * s * s)), "nll")
    assert estimate.play == pytest.approx(0.0037, abs=1e-4) and not estimate.at_edge
    assert estimate.std == pytest.approx(s, rel=0.05)
    assert estimate_steering_play(_scores(lambda p: 1.0), "mae").play == 0.0  # ties: no play


def test_a_minimum_at_the_edge_of_the_search_pins_nothing_and_says_so() -> None:
    estimate = estimate_steering_play(_scores(lambda p: (p - 0.05) ** 2), "nll")
    assert estimate.at_edge and estimate.play == pytest.approx(0.02) and estimate.std == math.inf
    assert "at the edge of the plays searched" in estimate.format("nll")


@pytest.mark.parametrize("play", [0.005, -0.004, 0.0])
def test_the_play_is_found_on_two_drives(play: float) -> None:
    params = load_params([])
    bags = [sim_samples(simulate(sine_drive(seed, steering_play=play))) for seed in (0, 1)]
    estimate = estimate_steering_play(lambda plays: [[play_objective(b, params, p, "nll") for b in bags]
                                                     for p in plays], "nll")
    assert 0.0001 <= estimate.std <= 0.002 and abs(estimate.play - play) <= 3.0 * estimate.std, estimate.format("nll")


def test_cli_writes_the_play_and_replay_loads_it(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """Two drives through 0.3 deg of play: OUT.yaml holds the play, and replay with it is right."""
    from transplanter_ident.bags import write_sim_bag

    play = 0.005
    bags = []
    for seed in (0, 1):
        bags.append(tmp_path / f"play{seed}")
        write_sim_bag(simulate(sine_drive(seed, steering_play=play)), bags[-1])
    out = tmp_path / "tuned.yaml"
    assert tuner.main([*map(str, bags), "-o", str(out), "--estimate-steering-play", "--particles", "4",
                       "--iterations", "1", "--seed", "3", "--jobs", "1", "--no-epoch-cache",
                       "--no-leave-one-out"]) == 0
    printed = capsys.readouterr()
    assert "vehicle.steering_play:" in printed.err and "# estimated vehicle.steering_play:" in out.read_text()
    assert abs(load_params([str(out)]).config.vehicle.steering_play - play) <= 0.0015

    assert replay.main([str(bags[0])]) == 0
    unset = final_errors(capsys.readouterr().out)
    assert replay.main([str(bags[0]), "--params-file", str(out)]) == 0
    calibrated = final_errors(capsys.readouterr().out)
    assert max(map(abs, calibrated)) < 0.3 * max(map(abs, unset)), (calibrated, unset)
