"""Outputs a controller can trust (issue #11): the validity flag is honest, not always off, and catches set-ups.

Offline over seeds 0-9 on the project's simulator (test/drives.py), with the default parameters; the
node makes the same decision online (test_node.py::test_online_equals_offline checks the flag).
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import pytest
from drives import TRUE_CF, TRUE_CR, Run, exact_claim, judged_run, run_drive, sine_drive
from helpers import sim_samples
from independent_sim import independent_drive

from transplanter_ident.config.parameters import (
    EstimatorConfig,
    ValiditySettings,
    VehicleParams,
)
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD, StepStatus
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler, assemble
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.identifiability import Identifiability
from transplanter_ident.evaluation.validity import (
    Sample,
    ValidityMonitor,
    decide_sequence,
    monitor_for,
    sample_of,
)
from transplanter_ident.sim.signals import StiffnessSchedule, sine_steering, step_steering
from transplanter_ident.sim.simulator import SensorNoise, SimResult, simulate

SEEDS = range(10)
CONFIG = EstimatorConfig()
SETTINGS = ValiditySettings()
DROP = StiffnessSchedule(times=(0.0, 60.0), front=(TRUE_CF, 0.6 * TRUE_CF), rear=(TRUE_CR, 0.6 * TRUE_CR),
                         transition=0.0)
SCENARIOS = {
    "clean": {},
    "stiffness drop": {"duration": 150.0, "stiffness": DROP},
    "paper step (1 m/s, 20 deg held)": {"speed": 1.0, "duration": 90.0,
                                        "steering": step_steering(math.radians(20.0), start=2.0, ramp=0.5)},
    "unconfigured 80 ms GNSS delay": {"gnss_delay": 0.08},
    "unconfigured 40 ms GNSS delay": {"gnss_delay": 0.04},
    "wet field (mu 0.3, tanh tire)": {"tire": "saturating", "friction": 0.3},
    "GNSS errors correlated 0.5 s": {"noise": SensorNoise(correlation_time=0.5)},
    "GNSS errors correlated 2 s": {"noise": SensorNoise(correlation_time=2.0)},
    "side slope 2 deg": {"bank_angle": math.radians(2.0)},  # the offset state takes it up: valid ~60 %
    "side slope 5 deg": {"bank_angle": math.radians(5.0)},  # the NIS shows the model's error: never valid
}


def validity(run: Run, epochs: EpochArrays) -> np.ndarray:
    return decide_sequence(CONFIG, SETTINGS, epochs, run.outputs)


def epochs_of(result: SimResult, **assembler: object) -> EpochArrays:
    return EpochArrays(assemble(EpochAssembler(AssemblerSettings(**assembler)), sim_samples(result)))


@functools.cache
def scenario_runs(name: str) -> tuple[tuple[Run, np.ndarray], ...]:
    out = []
    for seed in SEEDS:
        result = simulate(sine_drive(seed, **SCENARIOS[name]))
        epochs = epochs_of(result)
        run = run_drive(result)
        out.append((run, validity(run, epochs)))
    return tuple(out)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_when_valid_the_band_covers_the_truth(name: str) -> None:
    """Whenever valid is 1 (from 30 s on), +-2 sigma covers the truth in >= 90 % of epochs, Cf and Cr."""
    front, rear = [], []
    for run, valid in scenario_runs(name):
        keep = valid & (run.t >= 30.0)
        cf, cr = run.covered()
        front.extend(cf[keep])
        rear.extend(cr[keep])
    if front:
        assert np.mean(front) >= 0.90 and np.mean(rear) >= 0.90, (np.mean(front), np.mean(rear), len(front))


def test_clean_drives_are_valid_most_of_the_time() -> None:
    """Clean 2 m/s drives: valid in >= 70 % of the epochs after 30 s (the flag is not simply always off)."""
    fractions = [float(np.mean(valid[run.t >= 30.0])) for run, valid in scenario_runs("clean")]
    assert np.mean(fractions) >= 0.70, fractions


#: the filter without the allowances (the Cf, Cr std holding the bias of a tire at ekf.min_friction, of 1 ms of timing
#: and of 0.3 % of steering gain)
NO_ALLOWANCE = EstimatorConfig(options=replace(exact_claim(), min_friction=0.0))


@functools.cache
def clean_runs(config: EstimatorConfig) -> tuple[tuple[Run, np.ndarray], ...]:
    """The clean drives (seeds 0-9) filtered and decided with ``config``."""
    if config == CONFIG:
        return scenario_runs("clean")
    return tuple(judged_run(simulate(sine_drive(seed)), config, epochs_of, SETTINGS) for seed in SEEDS)


def pooled_error_sd(runs: tuple[tuple[Run, np.ndarray], ...]) -> tuple[float, float]:
    """The sd of (estimate - truth) / std, of Cf and of Cr, over the valid epochs after 30 s, pooled."""
    def sd(value: int, std: int, truth: str) -> float:
        return float(np.std(np.concatenate([
            ((run.outputs[:, value] - getattr(run, truth)) / run.outputs[:, std])[valid & (run.t >= 30.0)]
            for run, valid in runs])))

    return sd(O_CF, O_CF_STD, "true_cf"), sd(O_CR, O_CR_STD, "true_cr")


def test_the_band_is_as_wide_as_the_error_and_the_tire_allowance() -> None:
    """Clean drives, seeds 0-9: the std claims neither too little nor more than its allowances explain.

    The errors over the reported std, pooled over the valid epochs after 30 s (20 seeds, ad hoc, in brackets):
    - without the allowances (``ekf.min_friction`` 0, no timing or steering gain error held) their sd is 0.6-1.2,
      the statistical std about right (measured 0.87 / 0.79 [0.82 / 0.79]; 6.4 % of the valid epochs outside
      +-2 sigma);
    - with them (the defaults) 0.3-0.75 (0.40 / 0.40; the tire allowance alone 0.48 / 0.52 [0.45 / 0.52]; none
      outside): the std also holds the bias a tire at min_friction (a wet field) would cause, which the data of
      a dry one cannot rule out, and that of 1 ms of timing and 0.3 % of steering gain, so the band is two to
      two and a half times the error there; ``tanh tire, mu 0.3`` in bench/robustness_sweep.py is the field the
      tire allowance is for.
    """
    bare, defaults = pooled_error_sd(clean_runs(NO_ALLOWANCE)), pooled_error_sd(clean_runs(CONFIG))
    assert all(0.6 <= sd <= 1.2 for sd in bare), bare
    assert all(0.3 <= sd <= 0.75 for sd in defaults), defaults
    assert all(d < b for d, b in zip(defaults, bare, strict=True)), (defaults, bare)


def test_the_weakly_identifiable_and_the_delayed_drives_are_flagged() -> None:
    """The paper's held step and an unconfigured 80 ms delay: never valid after 30 s on any seed."""
    for name in ("paper step (1 m/s, 20 deg held)", "unconfigured 80 ms GNSS delay"):
        for run, valid in scenario_runs(name):
            assert not valid[run.t >= 30.0].any(), name


@pytest.mark.parametrize("name", ["GNSS errors correlated 0.5 s", "GNSS errors correlated 2 s"])
def test_correlated_gnss_errors_are_flagged_and_named(name: str) -> None:
    """GNSS errors correlated in time (Gauss-Markov, the white case's 1-sigma) narrow the band below the error.

    Taken as white, without the innovations' autocorrelation check, they were valid in 47 % / 35 % of
    the epochs after 30 s, with the truth outside +-2 sigma in 9 % / 23 % of those
    (``bench/robustness_sweep.py --option noise_correlation=0 --validity max_autocorrelation=1``). With
    R widened by their correlation (ekf.noise_correlation) and the check at 0.6, over 10 seeds: the 0.5 s
    drives are valid in 13 % of the epochs, none of those outside +-2 sigma; the 2 s ones never.
    Required: valid epochs outside +-2 sigma <= 5 % (pooled), the online reason names the correlation,
    and the estimate is still close (final error median <= 4 %: 1.5 % / 2.0 % measured).
    """
    runs = scenario_runs(name)
    missed = [m for run, valid in runs for m in (~np.logical_and(*run.covered()))[valid & (run.t >= 30.0)]]
    assert not missed or np.mean(missed) <= 0.05, (np.mean(missed), len(missed))
    assert np.median([abs(e) for run, _ in runs for e in run.final_errors()]) <= 0.04
    result = simulate(sine_drive(0, **SCENARIOS[name]))
    epochs = epochs_of(result)
    outputs = run_sequence(CONFIG, epochs)
    monitor = monitor_for(CONFIG, SETTINGS)
    reasons = [r for i in range(len(epochs)) for r in monitor.step(sample_of(epochs[i], outputs[i])).reasons
               if epochs[i].t >= 30.0]
    assert any("correlated in time" in r and "receiver smoothing" in r for r in reasons)


def plausibility_runs(kind: str) -> list[tuple[Run, list]]:
    out = []
    for seed in SEEDS:
        result = simulate(sine_drive(seed, duration=60.0))
        assembler: dict[str, object] = {}
        if kind == "course over ground":  # a single-antenna receiver: the heading is the velocity's direction
            course = np.arctan2(result.velocity_enu[:, 1], result.velocity_enu[:, 0])
            result = SimResult(**{**result.__dict__, "heading": course})
        else:  # ENU velocity declared NED
            assembler = {"velocity_frame": "ned"}
        epochs = epochs_of(result, **assembler)
        outputs = run_sequence(CONFIG, epochs)
        monitor = monitor_for(CONFIG, SETTINGS)
        decisions = [monitor.step(sample_of(epochs[i], outputs[i])) for i in range(len(epochs))]
        out.append((Run(np.asarray(epochs.t), outputs, np.full(len(epochs), TRUE_CF), np.full(len(epochs), TRUE_CR)),
                    decisions))
    return out


@pytest.mark.parametrize(("kind", "cause"), [("course over ground", "course over ground"),
                                             ("ENU velocity declared NED", "frames.velocity")])
def test_a_wrong_setup_is_invalid_and_named(kind: str, cause: str) -> None:
    """Course-over-ground heading, ENU/NED mix-up: valid is 0 in >= 95 % of epochs after 20 s, cause named."""
    for run, decisions in plausibility_runs(kind):
        after = run.t >= 20.0
        valid = np.array([d.valid for d in decisions])
        assert np.mean(~valid[after]) >= 0.95
        named = [d for d, a in zip(decisions, after, strict=True) if a and any(cause in r for r in d.reasons)]
        assert len(named) >= 0.95 * np.sum(after)
        assert all(d.hard for d in named)  # an ERROR in /diagnostics


#: a GNSS antenna 1.2 m ahead of the CG: in a +-30 deg sine at 2 m/s its vy holds antenna_x r, up to 0.6 m/s
LEVER = VehicleParams(antenna_x=1.2)


def lever_arm_decisions(velocity_frame: str, monitor_of: str = "config") -> list[tuple[np.ndarray, list]]:
    """Seeds 0-3, 60 s: (epoch times, decisions), the estimator told the lever arm.

    ``monitor_of`` "antenna only": the sideslip check before it took vy at the CG (no antenna_x).
    """
    config = EstimatorConfig(vehicle=LEVER)
    out = []
    for seed in range(4):
        result = simulate(sine_drive(seed, duration=60.0, vehicle=LEVER, steering=sine_steering(math.radians(30.0),
                                                                                                  6.0)))
        epochs = epochs_of(result, antenna_x=LEVER.antenna_x, velocity_frame=velocity_frame)
        outputs = run_sequence(config, epochs)
        monitor = monitor_for(config, SETTINGS) if monitor_of == "config" else ValidityMonitor(
            SETTINGS, config.options.stiffness_bounds, LEVER.lr + LEVER.antenna_x)
        out.append((np.asarray(epochs.t), [monitor.step(sample_of(epochs[i], outputs[i])) for i in range(len(epochs))]))
    return out


def named_share(runs: list[tuple[np.ndarray, list]], cause: str) -> float:
    """The share of the epochs from 20 s on whose reasons name ``cause`` as a hard (ERROR) failure."""
    named = [d.hard and any(cause in r for r in d.reasons) for t, decisions in runs
             for time, d in zip(t, decisions, strict=True) if time >= 20.0]
    return float(np.mean(named))


def test_an_antenna_ahead_of_the_cg_is_no_implausible_sideslip() -> None:
    """The sideslip check takes vy at the CG: an antenna 1.2 m ahead in tight turns raises no frame ERROR.

    Its vy holds antenna_x r (median |vy / vx| ~0.4 here, above validity.max_sideslip 0.35): the check on
    the antenna's vy, as before, named "implausible sideslip" in every epoch (asserted >= 95 %, so this test
    can fail); at the CG none. The same drive with the ENU velocity declared NED is still named in >= 95 %.
    """
    assert named_share(lever_arm_decisions("enu"), "implausible sideslip") == 0.0
    assert named_share(lever_arm_decisions("enu", "antenna only"), "implausible sideslip") >= 0.95
    assert named_share(lever_arm_decisions("ned"), "frames.velocity") >= 0.95


#: an antenna 0.30 m behind the CG, 0.20 m ahead of the rear axle: at 1.9 m/s the rear tires' slip
#: (m lf vx^2 r / (2 L Cr) = 0.20 r) cancels the kinematic (lr + antenna_x) r, so its vy is ~0 with a true heading
NEUTRAL = VehicleParams(mass=1121.0, lf=0.75, lr=0.50, antenna_x=-0.30, antenna_y=0.21)


def neutral_point_decisions(heading: str, monitor_of: str = "config") -> list[tuple[np.ndarray, list]]:
    """Seeds 0-3, 60 s of the independent simulator (nearly linear tires), the estimator told the vehicle.

    ``heading`` "course": a single antenna's course over ground; ``monitor_of`` "lever only": the
    course-over-ground check before it took the rear axle's slip into account.
    """
    config = EstimatorConfig(vehicle=NEUTRAL)
    out = []
    for seed in range(4):
        result = independent_drive(seed, speed=1.9, amplitude_deg=23.0, period=11.4, duration=60.0, friction=5.0,
                                   cf=5736.0, cr=5978.0, vehicle=NEUTRAL)
        if heading == "course":
            course = np.arctan2(result.velocity_enu[:, 1], result.velocity_enu[:, 0])
            result = SimResult(**{**result.__dict__, "heading": course})
        epochs = epochs_of(result, antenna_x=NEUTRAL.antenna_x, antenna_y=NEUTRAL.antenna_y)
        outputs = run_sequence(config, epochs)
        monitor = monitor_for(config, SETTINGS) if monitor_of == "config" else ValidityMonitor(
            SETTINGS, config.options.stiffness_bounds, NEUTRAL.lr + NEUTRAL.antenna_x, NEUTRAL.antenna_x)
        out.append((np.asarray(epochs.t), [monitor.step(sample_of(epochs[i], outputs[i])) for i in range(len(epochs))]))
    return out


def test_an_antenna_near_the_neutral_point_is_no_course_over_ground() -> None:
    """The course-over-ground check expects the vy of a steady turn less the rear axle's slip: no false ERROR.

    With a true dual-antenna heading, the check on (lr + antenna_x) r alone named "course over ground"
    (a hard ERROR, invalid at once) in 11 % of the epochs from 20 s on (measured 5 / 22 / 0 / 15 % on
    seeds 0-3; asserted >= 5 %, so this test can fail); now in none. A course-over-ground heading on the
    same drives is still named in >= 95 % (measured 100 %).
    """
    assert named_share(neutral_point_decisions("dual antenna"), "course over ground") == 0.0
    assert named_share(neutral_point_decisions("dual antenna", "lever only"), "course over ground") >= 0.05
    assert named_share(neutral_point_decisions("course"), "course over ground") >= 0.95


def test_hysteresis_needs_hold_on_to_become_valid_and_hold_off_to_drop() -> None:
    """A synthetic stream: good for 10 s, one bad epoch, good again; the flag does not flicker."""
    monitor = ValidityMonitor(ValiditySettings(window=4.0, hold_on=3.0, hold_off=1.0), (50.0, 1.0e6), 0.4)
    rng = np.random.default_rng(0)
    flags = []
    for k in range(150):
        t = 0.1 * k
        bad = k == 100
        nis = float(rng.chisquare(2))
        sample = Sample(t=t, status=StepStatus.UPDATED, cf=8000.0, cr=10000.0, cf_std=80.0,
                        cr_std=900.0 if bad else 100.0, steering=0.2 * math.sin(t), yaw_rate=0.4 * math.sin(t),
                        speed=2.0, antenna_lateral_velocity=0.15 * math.sin(t), nis=nis, nis_measured=nis,
                        noise_factors=(1.0, 1.0),
                        whitened_vy=float(rng.standard_normal()))
        flags.append(monitor.step(sample).valid)
    first = flags.index(True)
    assert 2.9 <= 0.1 * first - 2.0 <= 3.1 + 0.1  # the window fills after 2 s, then hold_on
    assert flags[100]  # one bad epoch (shorter than hold_off) does not drop the flag
    assert all(flags[first:])




def test_identifiability_matches_an_eigendecomposition() -> None:
    """The weak direction and its sigma are numpy's eigendecomposition; scale and ratio sigmas propagate."""
    rel_f, rel_r, rho = 0.12, 0.10, 0.99
    known = Identifiability.of(rel_f, rel_r, rho)
    cov = np.array([[rel_f ** 2, rho * rel_f * rel_r], [rho * rel_f * rel_r, rel_r ** 2]])
    values, vectors = np.linalg.eigh(cov)
    assert known.weak_std == pytest.approx(math.sqrt(values[-1]), rel=1e-12)
    assert abs(np.dot(known.weak_direction, vectors[:, -1])) == pytest.approx(1.0, rel=1e-12)
    assert known.ratio_std == pytest.approx(math.sqrt(np.array([1, -1]) @ cov @ np.array([1, -1])), rel=1e-12)
    assert known.scale_std == pytest.approx(0.5 * math.sqrt(np.array([1, 1]) @ cov @ np.array([1, 1])), rel=1e-12)
    assert known.condition == pytest.approx(values[-1] / values[0], rel=1e-9)
