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

import numpy as np
import pytest
from drives import sine_drive
from helpers import QUICK_TUNE, replayed_errors, sim_samples

from transplanter_ident.cli import tuner
from transplanter_ident.config.params_file import load_params
from transplanter_ident.sim.simulator import simulate
from transplanter_ident.tuning.delay import delay_objective, estimate_delay
from transplanter_ident.tuning.steering_play import (
    estimate_delay_and_play,
    estimate_steering_play,
    pair_objective,
    play_objective,
)


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
    """Two drives through 0.3 deg of play: OUT.yaml holds the play and its std, and replay with it is right."""
    from transplanter_ident.bags import write_sim_bag

    play = 0.005
    bags = []
    for seed in (0, 1):
        bags.append(tmp_path / f"play{seed}")
        write_sim_bag(simulate(sine_drive(seed, steering_play=play)), bags[-1])
    out = tmp_path / "tuned.yaml"
    assert tuner.main([*map(str, bags), "-o", str(out), "--estimate-steering-play", *QUICK_TUNE]) == 0
    printed = capsys.readouterr()
    assert "vehicle.steering_play:" in printed.err and "# estimated vehicle.steering_play:" in out.read_text()
    tuned = load_params([str(out)]).config
    assert abs(tuned.vehicle.steering_play - play) <= 0.0015
    # its std goes into the band: ekf.steering_play_uncertainty, and the error is within 3 of it
    assert 0.0001 <= tuned.options.steering_play_uncertainty <= 0.002
    assert abs(tuned.vehicle.steering_play - play) <= 3.0 * tuned.options.steering_play_uncertainty

    calibrated, unset = replayed_errors(bags[0], out, capsys)
    assert max(map(abs, calibrated)) < 0.3 * max(map(abs, unset)), (calibrated, unset)


def test_the_joint_search_follows_a_valley_and_its_stds_are_the_inverse_hessians() -> None:
    """A correlated quadratic -ln L (correlation -0.95, as a play and a delay's).

    The minimum within 2 % of a std, and each std the inverse Hessian's within 10 %.
    """
    truth, std, rho = np.array([0.03, 0.004]), np.array([0.003, 0.001]), -0.95
    covariance = np.array([[std[0] ** 2, rho * std[0] * std[1]], [rho * std[0] * std[1], std[1] ** 2]])
    information = np.linalg.inv(covariance)
    epochs = 1000

    def scores(pairs):  # noqa: ANN001, ANN202
        return [[(0.5 * float((np.array(p) - truth) @ information @ (np.array(p) - truth)) / epochs, epochs)]
                for p in pairs]

    delay, play = estimate_delay_and_play(scores, "nll")
    assert abs(delay.delay - truth[0]) <= 0.02 * std[0] and abs(play.play - truth[1]) <= 0.02 * std[1], (delay, play)
    assert delay.std == pytest.approx(std[0], rel=0.1) and play.std == pytest.approx(std[1], rel=0.1)


def test_a_play_and_a_delay_are_found_jointly_where_one_after_the_other_fails() -> None:
    """0.29 deg of play and a 20 ms delay on two drives (seeds 0-1).

    One after the other, the delay takes up the play (measured 32 ms, then a play of 0.3 mrad); jointly both
    within 3 std (measured 5.66 +- 0.90 mrad, 19.7 +- 2.3 ms).
    """
    params = load_params([])
    bags = [sim_samples(simulate(sine_drive(seed, steering_play=0.005, gnss_delay=0.02))) for seed in (0, 1)]
    delay, play = estimate_delay_and_play(lambda pairs: [[pair_objective(b, params, p, "nll") for b in bags]
                                                         for p in pairs], "nll")
    assert abs(delay.delay - 0.02) <= 3.0 * delay.std and delay.std <= 0.005, delay.format("nll")
    assert abs(play.play - 0.005) <= 3.0 * play.std and play.std <= 0.002, play.format("nll")
    alone = estimate_delay(lambda delays: [[delay_objective(b, params, d, "nll") for b in bags] for d in delays], "nll")
    assert alone.delay >= 0.028, alone.format("nll")  # the play taken for a delay: why the search is joint


def test_cli_searches_both_jointly_and_writes_them(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """--estimate-delay with --estimate-steering-play: one joint search.

    OUT.yaml holds the delay, its uncertainty and the play; replay with it is closer to the truth than without.
    """
    from transplanter_ident.bags import write_sim_bag

    bags = []
    for seed in (0, 1):
        bags.append(tmp_path / f"both{seed}")
        write_sim_bag(simulate(sine_drive(seed, duration=60.0, steering_play=0.005, gnss_delay=0.02)), bags[-1])
    out = tmp_path / "tuned.yaml"
    assert tuner.main([*map(str, bags), "-o", str(out), "--estimate-delay", "--estimate-steering-play",
                       *QUICK_TUNE]) == 0
    printed = capsys.readouterr().err
    assert "(jointly)" in printed and "input samples decoded for the joint delay and steering play search" in printed
    written = out.read_text()
    for key in ("gnss.delay", "ekf.delay_uncertainty", "vehicle.steering_play", "ekf.steering_play_uncertainty"):
        assert f"# estimated {key}:" in written, written
    tuned = load_params([str(out)])
    assert tuned.config.vehicle.steering_play > 0.0 and tuned.gnss.delay > 0.0
    calibrated, unset = replayed_errors(bags[0], out, capsys)
    assert max(map(abs, calibrated)) < 0.5 * max(map(abs, unset)), (calibrated, unset)
