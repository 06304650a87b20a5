"""A body that rolls in turns moves a high GNSS antenna sideways, which the bicycle model leaves out unless told.

An agricultural vehicle rolls outward with its lateral acceleration a_y; an antenna H m above the
roll axis then moves sideways at H x the roll rate (drives.with_body_roll: quasi-static roll,
gain x a_y). Left out (the default), the filter's innovations read the roll's velocity as a GNSS delay, a
steering gain or a tire relaxation left out (evaluation/model_errors.py), so the estimate is seldom
valid. What must hold is that it is never confidently wrong. Measured (session 34, seeds 0-9,
``python bench/robustness_sweep.py --seeds 10 "body roll ..."``): 0.25 deg per m/s^2 at 1.5 m valid in
14 % of the epochs from 30 s on, 0.5 and 1 deg never, none of the valid ones outside +-2 sigma; the
final error a median 1.4-1.5 %, worst 3.6 %. With ``vehicle.antenna_height`` and ``vehicle.roll_gradient``
set, the filter predicts the roll's velocity (measurement_row.roll_velocity) and the estimate is valid again.
"""

from __future__ import annotations

import math

import numpy as np
from drives import run_drive, sine_drive, with_body_roll
from test_validity import CONFIG, SETTINGS, epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, VehicleParams
from transplanter_ident.evaluation.validity import decide_sequence
from transplanter_ident.sim.simulator import simulate

SEEDS = range(6)
HEIGHT = 1.5  # m, a cab-roof antenna above the roll axis


def rolled_runs(gain_deg: float, config: EstimatorConfig) -> tuple[int, int, int, list[float]]:
    """Over SEEDS, from 30 s on: (epochs judged, valid, valid and outside +-2 sigma, final |errors| of Cf and Cr)."""
    judged = valid_count = missed = 0
    finals = []
    for seed in SEEDS:
        result = with_body_roll(simulate(sine_drive(seed)), math.radians(gain_deg), HEIGHT)
        run = run_drive(result, config)
        after = run.t >= 30.0
        valid = decide_sequence(config, SETTINGS, epochs_of(result), run.outputs) & after
        front, rear = run.covered()
        judged += int(after.sum())
        valid_count += int(valid.sum())
        missed += int((valid & ~(front & rear)).sum())
        finals.extend(abs(e) for e in run.final_errors())
    return judged, valid_count, missed, finals


def test_a_rolling_body_is_never_confidently_wrong() -> None:
    """Roll gradients 0.25 and 0.5 deg per m/s^2 left out: <= 5 % of the valid epochs (pooled) outside +-2 sigma.

    And the estimate itself stays near the truth (median final |error| <= 3 %, worst <= 6 %): it is the
    flag, not the number, that the roll costs.
    """
    for gain_deg in (0.25, 0.5):
        _, valid_count, missed, finals = rolled_runs(gain_deg, CONFIG)
        assert missed <= 0.05 * max(valid_count, 1), (gain_deg, missed, valid_count)
        assert np.median(finals) <= 0.03 and max(finals) <= 0.06, (gain_deg, finals)


def test_with_the_roll_set_the_estimate_is_valid_and_right() -> None:
    """vehicle.antenna_height and vehicle.roll_gradient set to the truth (the filter predicts the roll's velocity).

    0.25 and 0.5 deg per m/s^2, seeds 0-5, from 30 s on: valid in >= 75 % of the epochs, <= 5 % of those outside
    +-2 sigma, median final |error| <= 3 %. Measured (seeds 0-9, the sweep's "..., set" rows): valid 95 / 89 %,
    0.5 / 1.2 % of those outside; at 1 deg the kinematic rate leaves more: valid 32 %, 7.6 % outside.
    """
    for gain_deg in (0.25, 0.5):
        config = EstimatorConfig(vehicle=VehicleParams(antenna_height=HEIGHT, roll_gradient=math.radians(gain_deg)))
        judged, valid_count, missed, finals = rolled_runs(gain_deg, config)
        assert valid_count >= 0.75 * judged, (gain_deg, valid_count, judged)
        assert missed <= 0.05 * valid_count, (gain_deg, missed, valid_count)
        assert np.median(finals) <= 0.03, (gain_deg, finals)


def test_the_roll_reaches_the_antenna_velocity() -> None:
    """The perturbation is there: 0.5 deg per m/s^2 at 1.5 m moves the antenna by ~1 cm/s rms on this drive."""
    result = simulate(sine_drive(0))
    rolled = with_body_roll(result, math.radians(0.5), HEIGHT)
    moved = np.linalg.norm(rolled.velocity_enu - result.velocity_enu, axis=1)
    assert 0.005 <= float(np.sqrt(np.mean(moved ** 2))) <= 0.03
    assert np.array_equal(rolled.heading, result.heading)
