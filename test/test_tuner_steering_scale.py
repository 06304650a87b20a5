"""``tuner --estimate-steering-scale``: the steering sensor's gain found on simulated drives.

A sensor reading 1 % more than the wheel moves Cf by about -5 % and Cr by +8 % and the estimate stays
valid (test_steering_scale.py), so the tuner searches ``vehicle.steering_scale`` like ``gnss.delay``:
the objective at the starting Q/R over 0.95-1.05 x the configured scale, pooled over the bags
(tuning/steering_scale.py). Measured on three identification drives (seeds 0-2) per sensor gain:
1.02 -> 0.9820 (truth 0.9804), 0.99 -> 1.0115 (1.0101), 1.00 -> 1.0015, 1.02 with a 1 deg offset +0.16 %;
required within 0.5 %. On +-10 deg multisine drives (less excitation) +0.52 % (seeds 0-2) and -0.04 %
(seeds 3-5); required within 1 %.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from drives import sine_drive
from helpers import QUICK_TUNE, replayed_errors, sim_samples
from test_validity import epochs_of

from transplanter_ident.cli import tuner
from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions
from transplanter_ident.config.params_file import EstimatorParams, load_params
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler, assemble
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.sim.signals import multisine_steering
from transplanter_ident.sim.simulator import simulate
from transplanter_ident.tuning.steering_scale import (
    pooled_scale_objective,
    scale_objective,
    scaled_epochs,
    search_steering_scale,
    with_std,
    without_gain_state,
)

TOLERANCE = 0.005  # relative


def test_the_search_finds_the_minimum_of_a_known_curve() -> None:
    """A parabola in the factor with its minimum at 1.013: the scale is 0.8 x 1.013 within the fine step."""
    estimate = search_steering_scale(lambda factors: [(f - 1.013) ** 2 for f in factors], 0.8)
    assert estimate.value == pytest.approx(0.8 * 1.013, abs=0.8 * 0.0005)
    assert estimate.configured == 0.8 and len(estimate.points) > 20
    with pytest.raises(ValueError, match="vehicle.steering_scale search"):
        search_steering_scale(lambda factors: factors, 1.0, low=1.05, high=0.95)
    assert not estimate.at_edge and search_steering_scale(lambda fs: [1.0] * len(fs), 0.8).value == 0.8  # ties: 1


def test_a_minimum_at_the_edge_of_the_search_pins_nothing_and_says_so() -> None:
    """The sensor's gain beyond +-5 %: the search ends at 1.05, its std is +inf, and the line says to calibrate."""
    estimate = with_std(search_steering_scale(lambda factors: [(f - 1.08) ** 2 for f in factors], 1.0), 600)
    assert estimate.at_edge and estimate.value == pytest.approx(1.05) and estimate.std == math.inf
    assert "at the edge of the values searched, [0.95, 1.05]" in estimate.format("nll")
    from transplanter_ident.cli.delay_search import scale_calibration

    written = scale_calibration(estimate, EstimatorParams(), "nll")
    assert written["ekf.steering_scale_uncertainty"][0] == 0.2  # the schema's bound: never valid on it


def test_scaling_the_epochs_equals_assembling_with_the_scale() -> None:
    """scaled_epochs (the search's shortcut) matches the assembler with vehicle.steering_scale, to 1e-12."""
    samples = sim_samples(simulate(sine_drive(0, duration=20.0)))
    plain = EpochArrays(assemble(EpochAssembler(AssemblerSettings()), samples))
    assembled = EpochArrays(assemble(EpochAssembler(AssemblerSettings(steering_scale=0.97)), samples))
    shortcut = scaled_epochs(plain, 0.97)
    for name in ("steering", "steering_rate", "t", "antenna_lateral_velocity", "heading"):
        np.testing.assert_allclose(shortcut.column(name), assembled.column(name), rtol=1e-12, atol=1e-15)


MULTISINE = multisine_steering(math.radians(10.0), (3.0, 5.0, 9.0, 14.0), seed=3)


@pytest.mark.parametrize(("sensor_gain", "drive", "tolerance"), [
    (1.02, {}, TOLERANCE),  # measured +0.16 %
    (0.99, {}, TOLERANCE),  # +0.14 %
    (1.02, {"steering_offset": math.radians(1.0)}, TOLERANCE),  # with a 1 deg offset too: +0.16 %
    (1.02, {"steering": MULTISINE}, 2.0 * TOLERANCE),  # +-10 deg multisine, less excitation: +0.52 %, std 0.58 %
], ids=["sine-high", "sine-low", "sine-offset", "multisine"])
def test_the_scale_is_found_on_three_drives(sensor_gain: float, drive: dict, tolerance: float) -> None:
    bags = [epochs_of(simulate(sine_drive(seed, steering_scale=sensor_gain, **drive))) for seed in range(3)]
    estimate = search_steering_scale(pooled_scale_objective(bags, EstimatorConfig(), "nll"), 1.0)
    assert abs(estimate.value * sensor_gain - 1.0) <= tolerance, estimate.format("nll")
    # its std, from the NLL's curvature over the three drives' epochs
    estimate = with_std(estimate, sum(len(bag) for bag in bags))
    error = estimate.value - 1.0 / sensor_gain
    assert 0.0003 <= estimate.std <= 0.01 and abs(error) <= 3.0 * estimate.std, (error, estimate.format("nll"))


def test_cli_writes_the_scale_and_replay_loads_it(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """Two drives with the sensor 2 % high: OUT.yaml holds the scale and its std, and replay with it is right."""
    from transplanter_ident.bags import write_sim_bag

    bags = []
    for seed in (0, 1):
        bags.append(tmp_path / f"high{seed}")
        write_sim_bag(simulate(replace(sine_drive(seed), steering_scale=1.02)), bags[-1])
    out = tmp_path / "tuned.yaml"
    assert tuner.main([*map(str, bags), "-o", str(out), "--estimate-steering-scale", *QUICK_TUNE]) == 0
    printed = capsys.readouterr()
    assert "estimated vehicle.steering_scale:" in printed.out and "# estimated vehicle.steering_scale:" in out.read_text()
    assert "add --estimate-yaw-inertia" in printed.err  # vehicle.iz is m lf lr here
    tuned = load_params([str(out)]).config
    assert abs(tuned.vehicle.steering_scale * 1.02 - 1.0) <= TOLERANCE
    # its std (relative) goes into the band: ekf.steering_scale_uncertainty, and the error is within 3 of it
    uncertainty = tuned.options.steering_scale_uncertainty
    assert 0.0003 <= uncertainty <= 0.01 and "# estimated ekf.steering_scale_uncertainty:" in out.read_text()
    assert abs(tuned.vehicle.steering_scale * 1.02 - 1.0) <= 3.0 * uncertainty

    calibrated, unset = replayed_errors(bags[0], out, capsys)
    assert max(map(abs, calibrated)) < 0.5 * max(map(abs, unset)), (calibrated, unset)


def test_cli_refuses_the_search_for_a_sensor_on_one_wheel(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """Scaling the epochs is assembling with the scale only on the centre line: a clear error, nothing written."""
    from transplanter_ident.bags import write_sim_bag

    bag, out = tmp_path / "drive", tmp_path / "tuned.yaml"
    write_sim_bag(simulate(sine_drive(0, duration=30.0)), bag)
    params_file = tmp_path / "wheel.yaml"
    params_file.write_text("estimator:\n  ros__parameters:\n    vehicle:\n      steering_sensor_wheel: left\n"
                           "      track_width: 1.2\n")
    assert tuner.main([str(bag), "-o", str(out), "--params-file", str(params_file), "--estimate-steering-scale",
                       "--no-epoch-cache", "--jobs", "1"]) != 0
    assert "steering_sensor_wheel: center" in capsys.readouterr().err and not out.exists()


def test_the_search_runs_without_the_gain_state() -> None:
    """With ekf.estimate_steering_gain the objective is the one without it (the state would take up the factor)."""
    bag = epochs_of(simulate(sine_drive(0, duration=40.0, steering_scale=1.02)))
    with_state = replace(EstimatorConfig(), options=FilterOptions(estimate_steering_gain=True))
    for factor in (0.97, 1.0):
        assert scale_objective(bag, with_state, factor, "nll") == scale_objective(bag, EstimatorConfig(), factor, "nll")
    assert without_gain_state(with_state).options == FilterOptions()
