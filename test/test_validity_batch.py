"""decide_sequence's batch kernel (evaluation/validity_batch.py) makes ValidityMonitor's decisions, epoch for epoch.

Compared on the drives of test_validity.py (clean, stiffness drop, the paper's step, unconfigured
delays, course-over-ground heading, ENU declared NED), a drifting stiffness, and on outputs perturbed
at random (statuses, NaN NIS, spread, bounds, stiffness updates and alarms, measured model errors)
under random validity settings, so every check and the hysteresis switch.
The window checks themselves are one set of kernels that both call (evaluation/window_checks.py,
held against slow versions in test_window_checks.py); what this compares is the rest: the per-epoch
checks, the windows' bounds, when the checks run, and the hysteresis.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from drives import drift, run_drive, sine_drive
from test_validity import CONFIG, LEVER, SCENARIOS, SETTINGS, epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, ValiditySettings
from transplanter_ident.ekf.layout import (
    O_CF,
    O_CF_STD,
    O_CHANGE,
    O_CHANGE_EVIDENCE,
    O_CR_STD,
    O_NIS,
    O_NIS_CONFIGURED,
    O_NOISE_SCALE_SECOND,
    O_NOISE_SCALE_VY,
    O_STATUS,
    O_UPDATE_F,
    O_UPDATE_R,
    StepStatus,
)
from transplanter_ident.evaluation.model_errors import MODEL_ERRORS
from transplanter_ident.evaluation.validity import (
    DISTRUSTED,
    RECHECK,
    decide_sequence,
    monitor_for,
    sample_of,
)
from transplanter_ident.evaluation.validity_batch import decide_batch
from transplanter_ident.sim.simulator import SimResult, simulate


def monitor_decisions(settings: ValiditySettings, epochs, outputs, rejected=None) -> np.ndarray:  # noqa: ANN001
    monitor = monitor_for(CONFIG, settings)
    counts = [0] * len(epochs) if rejected is None else rejected
    return np.array([monitor.step(sample_of(epochs[i], outputs[i], counts[i])).valid for i in range(len(epochs))],
                    dtype=bool)


def _drive(name: str, seed: int):  # noqa: ANN202
    if name in SCENARIOS:
        result = simulate(sine_drive(seed, **SCENARIOS[name]))
        return epochs_of(result), run_drive(result).outputs
    result = simulate(sine_drive(seed))
    if name == "course over ground":
        course = np.arctan2(result.velocity_enu[:, 1], result.velocity_enu[:, 0])
        epochs = epochs_of(SimResult(**{**result.__dict__, "heading": course}))
    else:
        epochs = epochs_of(result, velocity_frame="ned")
    from transplanter_ident.ekf.joint_ekf import run_sequence

    return epochs, run_sequence(CONFIG, epochs)


@pytest.mark.parametrize("name", [*SCENARIOS, "course over ground", "ENU declared NED"])
def test_same_decisions_on_the_validity_drives(name: str) -> None:
    for seed in (0, 1):
        epochs, outputs = _drive(name, seed)
        expected = monitor_decisions(SETTINGS, epochs, outputs)
        assert np.array_equal(decide_sequence(CONFIG, SETTINGS, epochs, outputs), expected), (name, seed)


def test_same_decisions_on_a_drifting_stiffness() -> None:
    """Both stiffnesses drifting 40 % down over 4 min (test_drift.py): the drift test fires, and the same decisions."""
    for seed in (0, 1):
        result = simulate(sine_drive(seed, duration=240.0, stiffness=drift(-0.4, 1.0, 240.0)))
        epochs, outputs = epochs_of(result), run_drive(result).outputs
        expected = monitor_decisions(SETTINGS, epochs, outputs)
        assert np.array_equal(decide_sequence(CONFIG, SETTINGS, epochs, outputs), expected), seed
        off = dataclasses.replace(SETTINGS, drift_window=0.0)
        assert not np.array_equal(decide_sequence(CONFIG, off, epochs, outputs), expected)  # the test decided


def test_same_decisions_with_an_antenna_ahead_of_the_cg() -> None:
    """An antenna 1.2 m ahead of the CG (+-15 deg, 2 m/s; |vy / vx| ~0.2 there, ~0.02 at the CG): the same decisions.

    ENU velocity as ENU and as NED, max_sideslip 0.015 / 0.03 / 0.35: the sideslip check at the CG
    fires on some and not on others, and the right frame at 0.35 is valid about half the time.
    """
    from transplanter_ident.ekf.joint_ekf import run_sequence

    config = EstimatorConfig(vehicle=LEVER)
    result = simulate(sine_drive(0, duration=60.0, vehicle=LEVER))
    shares = []
    for frame in ("enu", "ned"):
        epochs = epochs_of(result, antenna_x=LEVER.antenna_x, velocity_frame=frame)
        outputs = run_sequence(config, epochs)
        for max_sideslip in (0.015, 0.03, 0.35):
            settings = dataclasses.replace(SETTINGS, max_sideslip=max_sideslip)
            monitor = monitor_for(config, settings)
            expected = np.array([monitor.step(sample_of(epochs[i], outputs[i])).valid for i in range(len(epochs))])
            assert np.array_equal(decide_sequence(config, settings, epochs, outputs), expected), (frame, max_sideslip)
            shares.append(float(np.mean(expected)))
    assert max(shares) >= 0.3 and min(shares) == 0.0, shares  # not one constant answer


def test_same_decisions_on_perturbed_outputs_and_settings() -> None:
    rng = np.random.default_rng(11)
    epochs, clean = _drive("clean", 2)
    statuses = np.array([int(s) for s in StepStatus])
    flips = drifts = measured = noisier = suspected = 0
    for case in range(100):
        outputs = clean.copy()
        n = len(outputs)
        for _ in range(int(rng.integers(0, 6))):
            start = int(rng.integers(0, n))
            stop = min(n, start + int(rng.integers(1, 300)))
            what = int(rng.integers(0, 8))
            if what == 0:
                outputs[start:stop, O_STATUS] = rng.choice(statuses, stop - start)
            elif what == 1:
                outputs[start:stop, O_NIS_CONFIGURED] = np.where(rng.random(stop - start) < 0.5, math.nan, 40.0)
            elif what == 2:
                outputs[start:stop, [O_CF_STD, O_CR_STD]] *= 5.0
            elif what == 3:  # stiffness updates pushing one way, some rows without an update, an alarm
                outputs[start:stop, [O_UPDATE_F, O_UPDATE_R]] = rng.normal(rng.choice((-1.0, 1.0)), 1.0, (stop - start, 2))
                outputs[start:stop, O_UPDATE_R] *= rng.random(stop - start) < 0.8
                outputs[start:stop, O_UPDATE_F] *= rng.random(stop - start) < 0.8
                outputs[int(rng.integers(start, stop)), O_CHANGE] = 1.0
            elif what == 4:
                outputs[start:stop, O_CF] = CONFIG.options.stiffness_bounds[1]
            elif what == 5:  # a measured model error of either sign, some rows not measured yet
                value, std, sens_f, sens_r = MODEL_ERRORS[int(rng.integers(0, len(MODEL_ERRORS)))].columns
                outputs[start:stop, value] = rng.normal(rng.choice((-0.2, 0.2)), 0.1, stop - start)
                outputs[start:stop, std] = rng.uniform(0.03, 0.15, stop - start) * (rng.random(stop - start) < 0.9)
                outputs[start:stop, [sens_f, sens_r]] = rng.normal(0.0, 0.5, (stop - start, 2))
            elif what == 6:  # sensors noisier than R: the factors the innovations show, and the NIS against them
                factors = rng.uniform(1.0, 4.0, (stop - start, 2))
                outputs[start:stop, [O_NOISE_SCALE_VY, O_NOISE_SCALE_SECOND]] = np.where(
                    rng.random((stop - start, 2)) < 0.05, math.nan, factors)  # NaN: as the batch takes it
                outputs[start:stop, O_NIS_CONFIGURED] *= 3.0
                outputs[start:stop, O_NIS] = np.where(rng.random(stop - start) < 0.1, math.nan, 2.0)
            elif what == 7:  # the directional change test gathering evidence (a NaN: as the batch takes it)
                outputs[start:stop, O_CHANGE_EVIDENCE] = np.where(rng.random(stop - start) < 0.05, math.nan,
                                                                  rng.uniform(0.0, 1.0, stop - start))
        settings = dataclasses.replace(
            SETTINGS, window=float(rng.choice((2.0, 5.0, 10.0))), hold_on=float(rng.choice((0.2, 1.0, 3.0))),
            hold_off=float(rng.choice((0.1, 0.5, 1.0))), max_autocorrelation=float(rng.choice((0.05, 0.3))),
            max_nonlinear_fraction=float(rng.choice((0.01, 0.2))), min_steering_std=float(rng.choice((0.02, 0.2))),
            max_sideslip=float(rng.choice((0.02, 0.35))), course_ratio=float(rng.choice((0.2, 5.0))),
            max_suspect_fraction=float(rng.choice((0.05, 0.5))), max_delay_sigmas=float(rng.choice((1.0, 3.0))),
            max_delay_shift=float(rng.choice((0.3, 1.5, 100.0))), drift_window=float(rng.choice((0.0, 20.0, 90.0))),
            max_drift_sigmas=float(rng.choice((1.0, 2.5))), max_relaxation_sigmas=float(rng.choice((1.0, 3.0))),
            max_relaxation_shift=float(rng.choice((0.3, 1.0, 100.0))),
            max_steering_gain_sigmas=float(rng.choice((1.0, 3.0))),
            max_steering_gain_shift=float(rng.choice((0.3, 1.0, 100.0))),
            max_noise_factor=float(rng.choice((1.0, 2.25, 100.0))),
            max_change_evidence=float(rng.choice((0.3, 0.5, 1.0))))
        rejected = [0] * n
        for _ in range(int(rng.integers(0, 4))):
            start = int(rng.integers(0, n))
            for i in range(start, min(n, start + int(rng.integers(1, 200)))):
                rejected[i] = int(rng.integers(0, 3))
        expected = monitor_decisions(settings, epochs, outputs, rejected)
        monitor = monitor_for(CONFIG, settings)
        got = decide_batch(settings, monitor.bounds, monitor.lever, RECHECK, epochs, outputs, rejected, DISTRUSTED,
                           monitor.antenna_x, monitor.rear_slip_gain)
        assert got is not None and np.array_equal(got, expected), f"case {case}"
        flips += int(np.count_nonzero(np.diff(expected.astype(int))))
        drifts += not np.array_equal(expected, monitor_decisions(dataclasses.replace(settings, drift_window=0.0), epochs,
                                                                 outputs, rejected))
        unmeasured = dataclasses.replace(settings, **{f"max_{e.name}_{test}": 100.0 for e in MODEL_ERRORS
                                                      for test in ("sigmas", "shift")})
        measured += not np.array_equal(expected, monitor_decisions(unmeasured, epochs, outputs, rejected))
        noisier += not np.array_equal(expected, monitor_decisions(dataclasses.replace(settings, max_noise_factor=1.0e4),
                                                                  epochs, outputs, rejected))
        suspected += not np.array_equal(expected, monitor_decisions(
            dataclasses.replace(settings, max_change_evidence=1.0), epochs, outputs, rejected))
    assert flips > 50  # the cases switch valid on and off, not one constant answer
    assert drifts >= 3 and measured >= 3 and noisier >= 3 and suspected >= 3  # these tests decided some


def test_times_that_go_back_use_the_monitor() -> None:
    epochs, outputs = _drive("clean", 3)
    t = epochs.t.copy()
    t[len(t) // 2:] -= 30.0
    epochs.t[:] = t
    assert decide_batch(SETTINGS, CONFIG.options.stiffness_bounds, 0.4, RECHECK, epochs, outputs, [0] * len(t),
                        DISTRUSTED) is None
    assert np.array_equal(decide_sequence(CONFIG, SETTINGS, epochs, outputs),
                          monitor_decisions(SETTINGS, epochs, outputs))
