"""Simulated drives for the accuracy tests: scenario -> epochs -> default filter -> errors against the truth.

Every accuracy claim of the real-sensor tests is measured here over seeds, against the
simulator's ground truth: final error, the fraction of epochs whose +-2 sigma band covers the
truth, and the time to get back within a tolerance after a change.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from helpers import course_epochs, epochs_from_result, sim_samples

from transplanter_ident.config.parameters import (
    EstimatorConfig,
    FilterOptions,
    NoiseParams,
    ValiditySettings,
    VehicleParams,
)
from transplanter_ident.config.params_file import load_params
from transplanter_ident.ekf.joint_ekf import run_sequence
from transplanter_ident.ekf.layout import (
    O_CF,
    O_CF_STD,
    O_CHANGE,
    O_CR,
    O_CR_STD,
    O_OFFSET,
    O_STATUS,
    O_TIRE_BIAS_F,
    O_TIRE_BIAS_R,
)
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler, assemble
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.validity import decide_sequence
from transplanter_ident.sim.signals import StiffnessSchedule, multisine_steering, sine_steering
from transplanter_ident.sim.simulator import SensorNoise, SimConfig, SimResult, simulate

CONFIG_DIR = Path(__file__).resolve().parents[1] / "config"
#: config/exact_calibration.yaml over config/estimator.yaml: no timing or steering gain error held, the narrower
#: band (the defaults until session 38)
EXACT = load_params([CONFIG_DIR / "estimator.yaml", CONFIG_DIR / "exact_calibration.yaml"])
EXACT_VALIDITY = EXACT.validity


def exact_claim(options: FilterOptions | None = None) -> FilterOptions:
    """``options`` (the defaults') with the exact claim's timing and steering gain uncertainties.

    The tests that show what a mechanism catches compare with this claim: the defaults' band already holds part
    of what those mechanisms are for.
    """
    exact = EXACT.config.options
    return replace(options or FilterOptions(), delay_uncertainty=exact.delay_uncertainty,
                   steering_scale_uncertainty=exact.steering_scale_uncertainty)

TRUE_CF, TRUE_CR = 8000.0, 10000.0
#: a 40 % drop of both stiffnesses at 75 s (a wet patch; 150 s drives)
LATE_DROP = StiffnessSchedule(times=(0.0, 75.0), front=(TRUE_CF, 0.6 * TRUE_CF), rear=(TRUE_CR, 0.6 * TRUE_CR))


def step_change(change: float, at: float) -> StiffnessSchedule:
    """Both stiffnesses stepping to (1 + change) x at ``at`` s (a new surface: -0.4 a wet patch, +0.3 firmer ground)."""
    return StiffnessSchedule(times=(0.0, at), front=(TRUE_CF, (1.0 + change) * TRUE_CF),
                             rear=(TRUE_CR, (1.0 + change) * TRUE_CR))


def drift(change: float, start: float, end: float) -> StiffnessSchedule:
    """Both stiffnesses drifting linearly to (1 + change) x from ``start`` to ``end`` s (a changing surface or load)."""
    return StiffnessSchedule(times=(0.0, start), front=(TRUE_CF, (1.0 + change) * TRUE_CF),
                             rear=(TRUE_CR, (1.0 + change) * TRUE_CR), transition=end - start)


def varying_speed(t: np.ndarray) -> np.ndarray:
    """1-3 m/s, a 30 s sine: the understeer, ~vx^2, sets the stiffness apart from a steering gain or a delay."""
    return 2.0 + np.sin(2.0 * np.pi * t / 30.0)


#: the drive of 180 s at that speed (sine_drive overrides)
VARYING_SPEED = {"speed_profile": varying_speed, "duration": 180.0}


def with_body_roll(result: SimResult, gain: float, height: float) -> SimResult:
    """``result`` with the body rolling outward in turns, gain rad per m/s^2 of lateral acceleration (quasi-static).

    The model has no roll: an antenna ``height`` m above the roll axis moves sideways at -height x the roll
    rate, gain x d(a_y)/dt with a_y = dvy/dt + vx r at the CG (finite differences of the truth at the GNSS
    samples), added to the antenna's measured velocity. The heading (a dual antenna along x) stays.
    """
    t = result.gnss_time
    lateral_acceleration = np.gradient(result.truth_vy, t) + result.truth_vx * result.truth_yaw_rate
    sideways = -height * gain * np.gradient(lateral_acceleration, t)
    psi = result.truth_heading
    velocity = result.velocity_enu + np.column_stack((-np.sin(psi) * sideways, np.cos(psi) * sideways))
    return replace(result, velocity_enu=velocity)


def with_steering_drift(result: SimResult, amount: float, start: float, end: float) -> SimResult:
    """``result`` with the steering sensor's offset moving by ``amount`` rad from ``start`` to ``end`` s.

    Linearly in between (a sensor warming up), at once when ``end`` is ``start`` (a knock); the wheels do not move.
    """
    t = result.steering_time
    share = (t >= start).astype(float) if end <= start else np.clip((t - start) / (end - start), 0.0, 1.0)
    return replace(result, steering=result.steering + amount * share)


#: GNSS velocity and heading 2x noisier than the default, and the R that describes them (a tuned noisier receiver)
NOISY_GNSS = SensorNoise(velocity=2.0 * SensorNoise().velocity, heading=2.0 * SensorNoise().heading)
NOISY_GNSS_R = NoiseParams(measurement_noise=tuple(4.0 * r for r in NoiseParams().measurement_noise))


def sine_drive(seed: int, **overrides: object) -> SimConfig:
    """The identification drive: 2 m/s, +-15 deg sine steer of 6 s, linear tires, 5 Hz GNSS, 120 s."""
    base = SimConfig(duration=120.0, speed=2.0, steering=sine_steering(math.radians(15.0), 6.0),
                     stiffness=StiffnessSchedule(front=(TRUE_CF,), rear=(TRUE_CR,)), tire="linear",
                     gnss_rate=5.0, steering_rate=50.0, noise=SensorNoise(), seed=seed)
    return replace(base, **overrides)


def noisy_late_drop(seed: int) -> SimConfig:
    """The identification drive, 150 s, with LATE_DROP seen through NOISY_GNSS (filter it with NOISY_GNSS_R)."""
    return sine_drive(seed, duration=150.0, stiffness=LATE_DROP, noise=NOISY_GNSS)


@dataclass(frozen=True)
class Run:
    """One drive through the filter: per-epoch outputs and the truth at each epoch."""

    t: np.ndarray
    outputs: np.ndarray
    true_cf: np.ndarray
    true_cr: np.ndarray

    @property
    def cf(self) -> np.ndarray:
        return self.outputs[:, O_CF]

    @property
    def cr(self) -> np.ndarray:
        return self.outputs[:, O_CR]

    def final_errors(self) -> tuple[float, float]:
        """Relative error of the last estimate of Cf and Cr."""
        return self.cf[-1] / self.true_cf[-1] - 1.0, self.cr[-1] / self.true_cr[-1] - 1.0

    def final_rel_std(self) -> tuple[float, float]:
        """Relative std of the last estimate of Cf and Cr."""
        return self.outputs[-1, O_CF_STD] / self.cf[-1], self.outputs[-1, O_CR_STD] / self.cr[-1]

    def final_tire_bias(self) -> tuple[float, float]:
        """The last relative bias of Cf and Cr a tire saturating at ekf.min_friction would cause."""
        return self.outputs[-1, O_TIRE_BIAS_F], self.outputs[-1, O_TIRE_BIAS_R]

    def covered(self) -> tuple[np.ndarray, np.ndarray]:
        """Per epoch: Cf, and Cr, within +-2 sigma of the truth."""
        o = self.outputs
        return (np.abs(o[:, O_CF] - self.true_cf) <= 2.0 * o[:, O_CF_STD],
                np.abs(o[:, O_CR] - self.true_cr) <= 2.0 * o[:, O_CR_STD])

    def coverage_after(self, start: float) -> float:
        """The smaller of the Cf and Cr fractions of epochs from ``start`` (s) on that +-2 sigma covers."""
        return min(float(np.mean(c[self.t >= start])) for c in self.covered())

    def worst_error_between(self, start: float, end: float) -> float:
        """Largest relative error of Cf or Cr over epochs in [start, end)."""
        window = (self.t >= start) & (self.t < end)
        return float(max(np.max(np.abs(self.cf[window] / self.true_cf[window] - 1.0)),
                         np.max(np.abs(self.cr[window] / self.true_cr[window] - 1.0))))

    def recovery_time(self, change: float, tolerance: float) -> float:
        """Seconds after ``change`` until both estimates stay within ``tolerance`` of the truth (inf: never)."""
        error = np.maximum(np.abs(self.cf / self.true_cf - 1.0), np.abs(self.cr / self.true_cr - 1.0))
        after = self.t >= change
        outside = np.nonzero(after & (error > tolerance))[0]
        if len(outside) == 0:
            return 0.0
        last = outside[-1]
        return math.inf if last == len(self.t) - 1 else float(self.t[last + 1] - change)

    def alarms_between(self, start: float, end: float) -> int:
        window = (self.t >= start) & (self.t < end)
        return int(np.sum(self.outputs[window, O_CHANGE] > 0.5))

    @property
    def offset(self) -> float:
        return float(self.outputs[-1, O_OFFSET])

    @property
    def statuses(self) -> np.ndarray:
        return self.outputs[:, O_STATUS].astype(int)


def run_drive(sim: SimConfig | SimResult, config: EstimatorConfig | None = None, *, gnss_delay: float = 0.0,
              gnss_first: bool = False) -> Run:
    """Simulate (unless given a result), assemble with the filter's vehicle and ``gnss_delay``, filter."""
    result = simulate(sim) if isinstance(sim, SimConfig) else sim
    config = config or EstimatorConfig()
    vehicle = config.vehicle
    if gnss_delay == 0.0 and not gnss_first:
        epochs = EpochArrays(epochs_from_result(result, vehicle))
    else:
        settings = AssemblerSettings(antenna_x=vehicle.antenna_x, antenna_y=vehicle.antenna_y,
                                     max_steering=vehicle.max_steering, gnss_delay=gnss_delay)
        epochs = EpochArrays(assemble(EpochAssembler(settings), sim_samples(result, gnss_first=gnss_first)))
    outputs = run_sequence(config, epochs)
    true_cf = np.interp(epochs.t, result.gnss_time, result.truth_cf)
    true_cr = np.interp(epochs.t, result.gnss_time, result.truth_cr)
    return Run(np.asarray(epochs.t), outputs, true_cf, true_cr)


def run_course(result: SimResult, config: EstimatorConfig) -> tuple[Run, EpochArrays]:
    """One antenna (``ekf.measurement: course``): the velocity and steering streams through the filter; and the epochs."""
    epochs = course_epochs(result, config.vehicle)
    outputs = run_sequence(config, epochs)
    t = np.asarray(epochs.t)
    return Run(t, outputs, np.interp(t, result.gnss_time, result.truth_cf),
               np.interp(t, result.gnss_time, result.truth_cr)), epochs


def median_and_worst(values: list[float]) -> tuple[float, float]:
    magnitudes = np.abs(np.asarray(values))
    return float(np.median(magnitudes)), float(np.max(magnitudes))


def pooled_coverage(runs: list[Run], start: float) -> tuple[float, float]:
    """Fractions of all epochs from ``start`` on, over all runs, whose +-2 sigma covers Cf, and Cr."""
    front = np.concatenate([r.covered()[0][r.t >= start] for r in runs])
    rear = np.concatenate([r.covered()[1][r.t >= start] for r in runs])
    return float(np.mean(front)), float(np.mean(rear))


@dataclass(frozen=True)
class ValidityFigures:
    """What a set of drives says about trust: availability, the worst output, and accuracy."""

    valid: float  # mean share of the epochs from the start time on flagged valid
    missed: float  # share of those valid epochs whose +-2 sigma misses Cf or Cr (0 when none is valid)
    finals: tuple[float, ...]  # |final relative error| of Cf and Cr of every drive
    kept: int = 0  # how many valid epochs ``missed`` is over

    @property
    def median(self) -> float:
        return float(np.median(self.finals))


def validity_figures(results: Iterable[SimResult], config: EstimatorConfig,
                     epochs_for: Callable[[SimResult], EpochArrays], start: float = 30.0) -> ValidityFigures:
    """Filter each drive with ``config`` and decide its validity on ``epochs_for(result)``, from ``start`` s on."""
    return pooled_validity_figures(((result, config) for result in results), epochs_for, start)


def pooled_validity_figures(drives: Iterable[tuple[SimResult, EstimatorConfig]],
                            epochs_for: Callable[[SimResult], EpochArrays], start: float = 30.0,
                            settings: ValiditySettings | None = None) -> ValidityFigures:
    """:func:`validity_figures` of drives each filtered with its own configuration (validity: the defaults)."""
    return judged_figures((judged_run(result, config, epochs_for, settings) for result, config in drives), start)


def judged_run(result: SimResult, config: EstimatorConfig, epochs_for: Callable[[SimResult], EpochArrays],
               settings: ValiditySettings | None = None) -> tuple[Run, np.ndarray]:
    """``result`` filtered with ``config``, and its valid flag per epoch decided on ``epochs_for(result)``."""
    run = run_drive(result, config)
    return run, decide_sequence(config, settings or ValiditySettings(), epochs_for(result), run.outputs)


def judged_figures(judged: Iterable[tuple[Run, np.ndarray]], start: float = 30.0) -> ValidityFigures:
    """The figures of runs already judged: each run with its valid flag per epoch, from ``start`` s on."""
    shares, missed, finals = [], [], []
    for run, valid in judged:
        after = run.t >= start
        kept = valid & after
        front, rear = run.covered()
        shares.append(float(np.mean(kept[after])))
        missed.extend((~(front & rear))[kept].tolist())
        finals.extend(abs(e) for e in run.final_errors())
    return ValidityFigures(float(np.mean(shares)), float(np.mean(missed)) if missed else 0.0, tuple(finals),
                           len(missed))


def random_drive(rng: np.random.Generator, seed: int) -> tuple[SimConfig, str]:
    """A drive with its conditions drawn from ``rng`` (bench/random_drives.py says which), and a line saying what it is."""
    speed = rng.uniform(1.0, 3.0)
    if rng.random() < 0.5:
        amplitude, period = rng.uniform(5.0, 25.0), rng.uniform(3.0, 14.0)
        steering, steer = sine_steering(math.radians(amplitude), period), f"sine +-{amplitude:.0f} deg/{period:.1f} s"
    else:
        amplitude, periods = rng.uniform(5.0, 20.0), tuple(float(p) for p in np.sort(rng.uniform(2.0, 16.0, 4)))
        steering = multisine_steering(math.radians(amplitude), periods, seed=seed)
        steer = f"multisine +-{amplitude:.0f} deg"
    tire, friction = ("linear", 0.8) if rng.random() < 0.4 else ("saturating", rng.uniform(0.3, 0.9))
    cf = rng.uniform(5000.0, 15000.0)
    cr = cf * rng.uniform(1.0, 1.6)
    vehicle = VehicleParams(mass=rng.uniform(600.0, 1200.0), lf=rng.uniform(0.5, 0.9), lr=rng.uniform(0.3, 0.7))
    rate = float(rng.choice([5.0, 10.0]))
    noise_factor = rng.uniform(0.5, 1.5)
    base = SensorNoise()
    noise = replace(base, velocity=noise_factor * base.velocity, heading=noise_factor * base.heading)
    offset = rng.uniform(-2.0, 2.0)
    sim = sine_drive(seed, duration=180.0, speed=speed, steering=steering, tire=tire, friction=friction,
                     stiffness=StiffnessSchedule(front=(cf,), rear=(cr,)), vehicle=vehicle, gnss_rate=rate,
                     noise=noise, steering_offset=math.radians(offset))
    tires = "linear" if tire == "linear" else f"tanh mu {friction:.2f}"
    return sim, (f"{speed:.1f} m/s, {steer}, {tires}, Cf {cf:.0f} Cr {cr:.0f}, m {vehicle.mass:.0f} lf {vehicle.lf:.2f} "
                 f"lr {vehicle.lr:.2f}, {rate:.0f} Hz, noise x{noise_factor:.1f}, offset {offset:+.1f} deg")
