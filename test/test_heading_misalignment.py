"""A dual-antenna heading misaligned with the vehicle beyond ``vehicle.heading_offset``.

The filter estimates the misalignment h as a state (``ekf.estimate_heading_offset``, default on,
ekf/measurement_row.py); with the state off, it measures it from its innovations
(ekf/heading_signature.py) and names it where the noise check fails. Also ``tuner
--estimate-heading-offset`` (tuning/heading_offset.py), which writes the offset either finds.

The identification drive (2 m/s, +-15 deg sine, 120 s) with every heading sample turned by delta: the
body-frame vy the assembler forms then carries -vx delta. The stiffness hardly moves with it (~0.2 % per
degree); what a misalignment left out cost was the validity: the steady vy looked like GNSS noise.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from drives import judged_figures, run_drive, sine_drive
from helpers import epochs_from_result
from independent_sim import independent_drive
from test_validity import SETTINGS, epochs_of

from transplanter_ident.bags import write_sim_bag
from transplanter_ident.cli import replay, tuner
from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, VehicleParams
from transplanter_ident.config.params_file import load_params
from transplanter_ident.ekf.layout import (
    O_HEADING_ESTIMATE,
    O_HEADING_ESTIMATE_STD,
    O_HEADING_OFFSET,
    O_HEADING_OFFSET_STD,
    O_HEADING_SENS_F,
    O_HEADING_SENS_R,
)
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.validity import decide_sequence, monitor_for, sample_of
from transplanter_ident.sim.simulator import SimResult, simulate

SEEDS = range(6)
#: the filter with the misalignment left out of its state: the innovations' measure of it (heading_signature.py)
MEASURED = EstimatorConfig(options=replace(FilterOptions(), estimate_heading_offset=False))


def misaligned(seed: int, degrees: float) -> SimResult:
    """The identification drive whose heading samples read ``degrees`` more than the vehicle's yaw."""
    result = simulate(sine_drive(seed))
    turned = result.heading + math.radians(degrees)
    return replace(result, heading=np.remainder(turned + math.pi, 2.0 * math.pi) - math.pi)


@pytest.mark.parametrize("degrees", [0.0, 0.5, -1.0, 2.0, 5.0])
def test_the_filter_estimates_a_misaligned_heading_and_stays_valid_and_right(degrees: float) -> None:
    """The state h, seeds 0-5: final h within 3 std of delta; valid, and right, from 60 s on.

    The std <= 0.1 deg; valid in >= 90 % of the epochs, and +-2 sigma of Cf and Cr covering the truth in
    >= 95 % of the valid ones.
    Measured: std 0.04 deg at every delta; valid 97 % at 0, 1 and 2 deg (with the state off: 97, 0, 0 %),
    median final error 1.1-1.3 %.
    """
    judged = []
    for seed in SEEDS:
        result = misaligned(seed, degrees)
        run = run_drive(result)
        last = run.outputs[-1]
        value, std = math.degrees(last[O_HEADING_OFFSET]), math.degrees(last[O_HEADING_OFFSET_STD])
        assert 0.0 < std <= 0.1 and abs(value - degrees) <= 3.0 * std, (seed, value, std)
        assert last[O_HEADING_ESTIMATE_STD] == 0.0  # the measure is off while h is a state
        judged.append((run, decide_sequence(EstimatorConfig(), SETTINGS, epochs_of(result), run.outputs)))
    figures = judged_figures(judged, start=60.0)
    assert figures.valid >= 0.9 and figures.missed <= 0.05, figures


@pytest.mark.parametrize("degrees", [0.0, 0.5, -1.0, 2.0])
def test_with_the_state_off_the_filter_measures_a_misaligned_heading(degrees: float) -> None:
    """``ekf.estimate_heading_offset`` false, seeds 0-5: the final measure within 3 std of delta.

    Its std <= 0.1 deg + 0.25 deg per degree.
    Measured: 0 deg 0.00-0.01 +- 0.03; 0.5 deg 0.50 +- 0.05; -1 deg -1.00 +- 0.10-0.13; 2 deg 1.99-2.09 +- 0.3-0.4
    (the std grows with delta: the noise measure takes the steady vy for noise and widens S).
    The stiffness's sensitivity is small (|O_HEADING_SENS| <= 0.7 per radian: <= 1.2 % per degree). It follows
    the R the noise measure learns, which in this set-up takes the misalignment for noise (heading x1.5-88):
    0.25 at most before session 31 restarted that measure once the model is near, 0.64 since (2 deg, seed 4).
    """
    for seed in SEEDS:
        last = run_drive(misaligned(seed, degrees), MEASURED).outputs[-1]
        value, std = math.degrees(last[O_HEADING_ESTIMATE]), math.degrees(last[O_HEADING_ESTIMATE_STD])
        assert 0.0 < std <= 0.1 + 0.25 * abs(degrees), (seed, value, std)
        assert abs(value - degrees) <= 3.0 * std, (seed, value, std)
        assert max(abs(last[O_HEADING_SENS_F]), abs(last[O_HEADING_SENS_R])) <= 0.7, last[[O_HEADING_SENS_F,
                                                                                          O_HEADING_SENS_R]]


def test_with_the_state_off_the_noise_reason_names_a_misaligned_heading_and_setting_it_makes_it_valid() -> None:
    """State off, 1 deg off, seeds 0-2, from 60 s on: never valid; the reason names vehicle.heading_offset.

    In every epoch.
    With vehicle.heading_offset set to the measure's value the same drives are valid in >= 90 % of those
    epochs (measured 100 %), as the aligned drive.
    """
    for seed in SEEDS[:3]:
        result = misaligned(seed, 1.0)
        run = run_drive(result, MEASURED)
        epochs = epochs_of(result)
        monitor = monitor_for(MEASURED, SETTINGS)
        after = run.t >= 60.0
        reasons = [monitor.step(sample_of(epochs[i], run.outputs[i])).reasons for i in range(len(epochs))]
        named = [any("vehicle.heading_offset" in r for r in reasons[i]) for i in np.flatnonzero(after)]
        assert all(named), (seed, [r for r, a in zip(reasons, after, strict=True) if a][0])
        assert not decide_sequence(MEASURED, SETTINGS, epochs, run.outputs)[after].any()

        measured = float(run.outputs[-1, O_HEADING_ESTIMATE])
        config = replace(MEASURED, vehicle=VehicleParams(heading_offset=measured))
        fixed = run_drive(result, config)
        valid = decide_sequence(config, SETTINGS, epochs_of(result, heading_offset=measured), fixed.outputs)
        assert np.mean(valid[fixed.t >= 60.0]) >= 0.9, (seed, math.degrees(measured))


@pytest.mark.parametrize("config", [EstimatorConfig(), MEASURED], ids=["state", "measure"])
def test_an_aligned_heading_is_never_named(config: EstimatorConfig) -> None:
    """Seeds 0-5 aligned: the estimate never 3 std from zero from 30 s on, so no reason names the heading."""
    columns = [O_HEADING_OFFSET, O_HEADING_OFFSET_STD] if config.options.estimate_heading_offset else \
        [O_HEADING_ESTIMATE, O_HEADING_ESTIMATE_STD]
    for seed in SEEDS:
        run = run_drive(simulate(sine_drive(seed)), config)
        after = run.t >= 30.0
        value, std = run.outputs[after, columns[0]], run.outputs[after, columns[1]]
        assert np.all(np.abs(value) <= 3.0 * std), (seed, np.max(np.abs(value) / std))


@pytest.mark.parametrize("estimated", [True, False], ids=["state", "measure"])
@pytest.mark.parametrize("degrees", [0.0, 1.0])
def test_the_independent_simulator_with_a_lever_arm_reads_the_same(degrees: float, estimated: bool) -> None:
    """The independent simulator, antenna 0.8 m ahead and 0.3 m left, 1.5 m/s, 150 s, seeds 0-7: as above.

    The final estimate within 3 std of delta, std <= 0.3 deg (measure: 0.96-1.02 +- 0.10-0.17 deg; aligned:
    within 1.4 std; state: 0.94-1.03 +- 0.05 deg). With the state, from 60 s on and over seeds 0-23: valid in
    >= 50 % of the epochs, and each stiffness within +-2 sigma in >= 85 % of the valid ones (the band's promise
    is 95 %). Measured on seeds 0-7: aligned 82 % valid, Cf 100 % and Cr 97 % covered; 1 deg 66 % valid (0 with
    the state off), Cf 99.6 % and Cr 90 % covered. At 1.5 m/s the band is about as wide as the error
    (docs/robustness.md), and seed 5 sits 1.7-2 sigma high at 0 and 1 deg alike; it alone decided 8 seeds'
    share (session 31, R's measure restarted once the model is near: seed 5 valid 66 -> 83 %, Cr covered in
    58 -> 31 % of those, seeds 0-7 Cr 90 -> 84 %). Over seeds 0-23 at 1 deg: valid 64 %, Cf 99.9 %, Cr 94.6 %
    (96.5 % before that change).
    """
    vehicle = VehicleParams(antenna_x=0.8, antenna_y=0.3)
    config = EstimatorConfig(vehicle=vehicle, options=replace(FilterOptions(), estimate_heading_offset=estimated))
    columns = [O_HEADING_OFFSET, O_HEADING_OFFSET_STD] if estimated else [O_HEADING_ESTIMATE, O_HEADING_ESTIMATE_STD]
    valid, front, rear = [], [], []
    for seed in range(24 if estimated else 8):
        result = independent_drive(seed, vehicle=vehicle, speed=1.5, duration=150.0)
        turned = result.heading + math.radians(degrees)
        result = replace(result, heading=np.remainder(turned + math.pi, 2.0 * math.pi) - math.pi)
        run = run_drive(result, config)
        value, std = map(math.degrees, run.outputs[-1, columns])
        if seed < 8:
            assert 0.0 < std <= 0.3 and abs(value - degrees) <= 3.0 * std, (seed, value, std)
        after = run.t >= 60.0
        kept = decide_sequence(config, SETTINGS, EpochArrays(epochs_from_result(result, vehicle)), run.outputs)[after]
        covered_f, covered_r = (c[after] for c in run.covered())
        valid.append(kept)
        front.append(covered_f[kept])
        rear.append(covered_r[kept])
    if estimated:
        share, front_share, rear_share = (float(np.mean(np.concatenate(a))) for a in (valid, front, rear))
        assert share >= 0.5 and front_share >= 0.85 and rear_share >= 0.85, (share, front_share, rear_share)


def test_tuner_writes_the_heading_offset_and_replay_with_it_is_valid(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """``tuner --estimate-heading-offset`` on two drives 1.5 deg off, then replay of a third.

    OUT.yaml's vehicle.heading_offset within 3 of its std and 0.2 deg of the truth (measured 1.51 +- 0.03 deg,
    2 passes, from the state h; 1.50 +- 0.02 deg, 3 passes, from the measure in session 26). The third drive, from 60 s on, with ``ekf.estimate_heading_offset`` false: valid in >= 90 % of
    the epochs with OUT.yaml (measured 100 %), never without it; with the state and no offset, >= 90 %.
    """
    paths = []
    for seed in (0, 1, 2):
        paths.append(tmp_path / f"drive{seed}")
        write_sim_bag(misaligned(seed, 1.5), paths[-1])
    out = tmp_path / "tuned.yaml"
    assert tuner.main([str(paths[0]), str(paths[1]), "-o", str(out), "--estimate-heading-offset", "--particles", "4",
                       "--iterations", "1", "--seed", "3", "--jobs", "1", "--no-epoch-cache",
                       "--no-leave-one-out"]) == 0
    printed = capsys.readouterr().err
    line = next(line for line in printed.splitlines() if line.startswith("tuner: vehicle.heading_offset: "))
    offset = load_params([str(out)]).config.vehicle.heading_offset
    std = math.radians(float(line.split("+- ")[1].split(" deg")[0]))
    print(f"\n{line}")
    assert "# estimated vehicle.heading_offset:" in out.read_text()
    assert abs(offset - math.radians(1.5)) <= min(3.0 * std, math.radians(0.2)), (offset, std)

    state_off = tmp_path / "state_off.yaml"
    state_off.write_text("/**:\n  ros__parameters:\n    ekf:\n      estimate_heading_offset: false\n")
    valid = {}
    for name, extra in (("unset, state off", ["--params-file", str(state_off)]),
                        ("set, state off", ["--params-file", str(state_off), "--params-file", str(out)]),
                        ("unset, state", [])):
        csv = tmp_path / f"{name}.csv"
        assert replay.main([str(paths[2]), "--csv", str(csv), *extra]) == 0
        rows = np.genfromtxt(csv, delimiter=",", names=True)
        valid[name] = float(np.mean(rows["valid"][rows["t"] - rows["t"][0] >= 60.0]))
    capsys.readouterr()
    assert valid["unset, state off"] == 0.0 and valid["set, state off"] >= 0.9 and valid["unset, state"] >= 0.9, valid
