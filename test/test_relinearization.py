"""Re-linearised passes over the start (ekf/relinearization.py): ``ekf.relinearization_window``.

Started at the configured 1000 N/rad (8-10x below the simulator's tire), the EKF linearises its
first steps far from the truth; on gentle steering with the steering offset as a state the
estimate then creeps towards the truth for minutes under a band that says ~5 %. A new pass over
the epochs since the start, from the estimate held at a check, replaces the pass in force when
its innovations are more likely.

Figures are measured on the project's simulator (test/drives.py: 2 m/s, 5 Hz, 120 s) with the
defaults (``ekf.relinearization_window: 60``) against its
truth Cf = 8000, Cr = 10000 N/rad; "one pass" is ``ekf.relinearization_window: 0``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import pytest
from drives import Run, median_and_worst, pooled_coverage, run_drive, sine_drive
from helpers import epochs_from_result
from scipy.optimize import minimize

from transplanter_ident.config.parameters import EstimatorConfig, NoiseParams
from transplanter_ident.ekf import relinearization
from transplanter_ident.ekf.entries import objective_kernel, run_kernel
from transplanter_ident.ekf.joint_ekf import (
    FilterArrays,
    JointEKF,
    identifiability_guard,
    kernel_input,
    run_sequence,
)
from transplanter_ident.ekf.layout import (
    DIVERGENCE_PENALTY,
    N_MEMO,
    N_MODEL,
    N_OUTPUTS,
    NLL,
    O_CF,
    O_CF_STD,
    O_CR,
    O_CR_STD,
    O_DT,
    O_NIS,
    O_S00,
    O_S11,
    O_STATUS,
    X_THETA_F,
    X_THETA_R,
    StepStatus,
)
from transplanter_ident.ekf.relinearization import (
    CHECK_PERIOD,
    FilterState,
    epoch_nll,
    mean_nll,
    schedule_for,
)
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.signals import sine_steering
from transplanter_ident.sim.simulator import SensorNoise, simulate

SEEDS = range(10)
NOISE_FREE = SensorNoise(velocity=0.0, heading=0.0, steering=0.0)
#: one pass, R white (test_noise_correlation.py tests its widening; the tuner's NLL scores R white)
ONE_PASS = replace(EstimatorConfig().options, relinearization_window=0.0, noise_correlation=False)
RELINEARIZED = EstimatorConfig()  # the defaults: ekf.relinearization_window 60 s


def gentle(seed: int, offset_deg: float, noise: SensorNoise | None = None):  # noqa: ANN201 - a SimConfig
    """+-5 deg sine of 6 s at 2 m/s (path-tracking-like steering), with a steering-sensor offset."""
    drive = sine_drive(seed, steering=sine_steering(math.radians(5.0), 6.0), steering_offset=math.radians(offset_deg))
    return drive if noise is None else replace(drive, noise=noise)


def error_at(run: Run, t: float) -> float:
    """The larger relative error of Cf and Cr at the first epoch at or after ``t``."""
    k = int(np.searchsorted(run.t, t))
    return float(max(abs(run.cf[k] / run.true_cf[k] - 1.0), abs(run.cr[k] / run.true_cr[k] - 1.0)))


@functools.cache
def noisy_runs(offset_deg: float, relinearized: bool) -> tuple[Run, ...]:
    config = RELINEARIZED if relinearized else EstimatorConfig(options=ONE_PASS)
    return tuple(run_drive(gentle(seed, offset_deg), config) for seed in SEEDS)


@pytest.mark.parametrize("offset_deg", [0.0, 1.0])
def test_gentle_steering_converges_at_once_without_noise(offset_deg: float) -> None:
    """Noise-free +-5 deg: one pass is still 10.9 % (0 deg) / 4.8 % (1 deg) off at 30 s; re-linearised < 1 %.

    (-11 % and -31 % with the change test of before, ekf.change_scale 4, and 6.6 % with 1 deg before
    the directional change test: their alarms at the start raise the stiffness random walk, which
    speeds one pass up.) Asserted: one pass > 3 % off, the premise. R white: without noise the
    innovations are the linearisation's own error, correlated throughout, and ekf.noise_correlation
    widens R by it (2.7 % off at 30 s with it; with noise the widening is a few percent). The offset is
    kept at those alarms (ekf.change_offset_variance 0): re-opening it speeds one pass up too (1 deg:
    2.7 % off at 30 s).
    """
    result = simulate(gentle(0, offset_deg, NOISE_FREE))
    kept_offset = replace(ONE_PASS, change_offset_variance=0.0)
    one = run_drive(result, EstimatorConfig(options=kept_offset))
    relinearized = run_drive(result, EstimatorConfig(options=replace(kept_offset, relinearization_window=60.0)))
    assert error_at(one, 30.0) > 0.03, "the one-pass filter converged: this drive no longer shows the effect"
    for t in (30.0, 60.0, 120.0):
        assert error_at(relinearized, t) < 0.01, f"{error_at(relinearized, t):.3%} off at {t} s"


@pytest.mark.parametrize("offset_deg", [0.0, 1.0])
def test_gentle_steering_band_covers_the_truth(offset_deg: float) -> None:
    """+-5 deg with the simulator's noise, seeds 0-9: pooled coverage, the errors at 60 s and at the end.

    +-2 sigma covers the truth in >= 90 % of the epochs from 30 s on, for Cf and Cr, and with the 1 deg
    offset more often than with one pass (R white). The median |error| at 60 s within a point of one
    pass's, and the worst at the end within 2 points. Measured since the heading's misalignment is a
    filter state (session 27), re-linearised vs one pass: coverage 0 deg 0.94 / 0.97 vs 0.98 / 0.99,
    1 deg 0.95 / 0.98 vs 0.87 / 0.98; median at 60 s 3.5 % vs 4.6 %, 3.4 % vs 3.4 %; worst at the end
    7.4 % vs 6.0 %, 7.0 % vs 12.2 %. Before it: coverage 1.00 / 1.00 vs 0.95 / 0.99 and 0.95 / 0.99 vs
    0.86 / 0.94; worst 5.9 % vs 6.4 %, 7.1 % vs 6.8 % (an unknown more in vy costs where the steering
    excites little). The directional change test's alarms at the start speed one pass up (without it,
    one pass: 4.4 % and 5.7 % at 60 s, 0.90 / 0.99 and 0.76 / 0.89 covered). The worst at 60 s is not
    compared: a new pass's bounded prior can put one seed where the maximum likelihood of those 60 s is
    (with 1 deg, seed 7 was 15.9 % off there, one pass 10.3 %, the likelihood's maximum 14.0 %).
    """
    relinearized, one = noisy_runs(offset_deg, True), noisy_runs(offset_deg, False)
    covered = pooled_coverage(list(relinearized), 30.0)
    covered_one = pooled_coverage(list(one), 30.0)
    assert min(covered) >= 0.9, f"coverage {covered} (one pass {covered_one})"
    assert offset_deg == 0.0 or min(covered) > min(covered_one), f"coverage {covered} vs one pass {covered_one}"
    at_60 = median_and_worst([error_at(r, 60.0) for r in relinearized])[0]
    at_60_one = median_and_worst([error_at(r, 60.0) for r in one])[0]
    assert at_60 < at_60_one + 0.01, f"median error at 60 s {at_60:.1%} vs one pass {at_60_one:.1%}"
    worst = median_and_worst([abs(e) for r in relinearized for e in r.final_errors()])[1]
    worst_one = median_and_worst([abs(e) for r in one for e in r.final_errors()])[1]
    assert worst < worst_one + 0.02, f"worst final error {worst:.1%} vs one pass {worst_one:.1%}"


def test_the_identification_drive_keeps_its_accuracy() -> None:
    """+-15 deg, seeds 0-9: median final |error| within 0.3 points of one pass, worst <= 4 %, coverage >= 0.9."""
    runs = [run_drive(sine_drive(seed), RELINEARIZED) for seed in SEEDS]
    one = [run_drive(sine_drive(seed), EstimatorConfig(options=ONE_PASS)) for seed in SEEDS]
    median, worst = median_and_worst([e for r in runs for e in r.final_errors()])
    median_one, _ = median_and_worst([e for r in one for e in r.final_errors()])
    assert median <= median_one + 0.003, f"median {median:.2%} vs one pass {median_one:.2%}"
    assert worst <= 0.04, f"worst final error {worst:.2%}"
    assert min(pooled_coverage(runs, 30.0)) >= 0.9


def test_the_node_takes_the_passes_replay_takes() -> None:
    """JointEKF.step epoch by epoch gives the same output rows, bit for bit, as run_sequence, with a pass kept."""
    config = RELINEARIZED
    epochs = epochs_from_result(simulate(gentle(3, 1.0)), config.vehicle)
    ekf = JointEKF(config)
    online = np.array([ekf.step(epoch).row for epoch in epochs])
    offline = run_sequence(config, EpochArrays(epochs))
    tried, kept = ekf.relinearized_passes
    assert kept >= 1 and tried >= kept
    assert np.array_equal(online, offline)


def test_window_zero_is_the_one_pass_filter() -> None:
    """ekf.relinearization_window: 0 runs the compiled filter once over the sequence, as before this change."""
    config = EstimatorConfig(options=ONE_PASS)
    epochs = EpochArrays(epochs_from_result(simulate(gentle(1, 1.0)), config.vehicle))
    a = FilterArrays.from_config(config)
    rows = kernel_input(epochs)
    plain = np.zeros((len(rows), N_OUTPUTS))
    run_kernel(rows, a.initial_state.copy(), a.initial_covariance.copy(), np.zeros(N_MODEL), np.zeros(N_MEMO),
               a.vehicle, a.settings, a.process_noise, a.measurement_noise, plain)
    identifiability_guard(config, a).run(rows, plain)
    assert np.array_equal(run_sequence(config, epochs), plain)


# --------------------------------------------------------------------------- the schedule on its own


def updated(dt: float = 0.2) -> np.ndarray:
    out = np.zeros(N_OUTPUTS)
    out[O_STATUS], out[O_DT] = StepStatus.UPDATED, dt
    return out


def state_at(cf: float, cr: float, variance: float = 1.0e-4) -> FilterState:
    x, p = np.zeros(6), np.eye(6) * variance
    x[X_THETA_F], x[X_THETA_R] = math.log(cf), math.log(cr)
    return FilterState(x, p)


def test_checks_come_every_period_of_stiffness_updates_and_end_with_the_window() -> None:
    schedule = schedule_for(12.0, 0.1, True, state_at(1000.0, 1000.0).x)
    held = np.zeros(N_OUTPUTS)
    held[O_STATUS], held[O_DT] = StepStatus.LOW_SPEED, 0.2
    assert not any(schedule.due(held, 1) for _ in range(100))  # standing still counts nothing
    checks = [k for k in range(1, 101) if schedule.due(updated(0.25), k)]  # 0.25 s: sums without rounding
    assert [0.25 * k for k in checks] == [CHECK_PERIOD, 2 * CHECK_PERIOD]
    assert not schedule.open


@pytest.mark.parametrize(("cf", "variance", "moved"), [(1050.0, 1.0e-4, False),  # under the threshold
                                                       (1300.0, 1.0e-4, True),
                                                       (1300.0, 0.01, False)])  # within 3 std
def test_a_new_pass_needs_a_move_beyond_threshold_and_noise(cf: float, variance: float, moved: bool) -> None:
    schedule = schedule_for(60.0, 0.1, True, state_at(1000.0, 1000.0).x)
    assert schedule.moved(state_at(cf, 1000.0, variance)) is moved


def scored(nis: float) -> np.ndarray:
    """An UPDATED output row whose innovation has this NIS (S = I, so its NLL is nis / 2 + ln 2 pi)."""
    out = updated()
    out[O_S00] = out[O_S11] = 1.0
    out[O_NIS] = nis
    return out


@pytest.mark.parametrize(("tried", "kept"), [(1.0, True), (3.0, False), (math.nan, False)])
def test_a_new_pass_is_kept_only_when_its_innovations_are_more_likely(tried: float, kept: bool) -> None:
    """The pass in force has NIS 2 at every epoch; the new one (``run``) has ``tried``."""
    x0 = state_at(1000.0, 1000.0).x
    schedule = schedule_for(60.0, 0.1, True, x0)
    state = state_at(8000.0, 10000.0)

    def run(rows, x, p, model, memo, outputs) -> None:  # noqa: ANN001
        outputs[:] = scored(tried)

    result = state
    for k in range(1, round(CHECK_PERIOD / 0.2) + 1):
        result = schedule.step(np.zeros((k, 3)), scored(2.0), result, x0, np.eye(6), run)
    assert (result is not state) is kept
    assert schedule.passes == 2 and schedule.kept == int(kept)
    if kept:  # from P0, but for ln Cf, ln Cr: at most PRIOR_SIGMAS of the held std (1e-2 here) wide
        assert result.x[X_THETA_F] == pytest.approx(math.log(8000.0))
        prior = np.eye(6)
        prior[X_THETA_F, X_THETA_F] = prior[X_THETA_R, X_THETA_R] = relinearization.PRIOR_SIGMAS ** 2 * 1.0e-4
        assert np.array_equal(result.p, prior)


@pytest.mark.parametrize("offset_deg", [0.0, 1.0])
def test_the_pass_score_is_the_tuners_nll(offset_deg: float) -> None:
    """mean_nll(epoch_nll(outputs)) of a run equals objective_kernel's NLL of the same pass (the compiled sum)."""
    config = EstimatorConfig(options=ONE_PASS)
    epochs = EpochArrays(epochs_from_result(simulate(gentle(2, offset_deg)), config.vehicle))
    a = FilterArrays.from_config(config)
    rows = kernel_input(epochs)
    outputs = np.zeros((len(rows), N_OUTPUTS))
    run_kernel(rows, a.initial_state.copy(), a.initial_covariance.copy(), np.zeros(N_MODEL), np.zeros(N_MEMO),
               a.vehicle, a.settings, a.process_noise, a.measurement_noise, outputs)
    compiled = objective_kernel(rows, a.initial_state.copy(), a.initial_covariance.copy(), np.zeros(N_MODEL),
                                np.zeros(N_MEMO), a.vehicle, a.settings, a.process_noise, a.measurement_noise, NLL)
    assert mean_nll(epoch_nll(outputs)) == pytest.approx(compiled, rel=1e-12)


def test_a_failed_epoch_fails_the_pass() -> None:
    rows = np.array([scored(1.0), scored(1.0)])
    rows[1, O_STATUS] = StepStatus.DIVERGED
    assert mean_nll(epoch_nll(rows)) == DIVERGENCE_PENALTY
    rows[1, O_STATUS] = StepStatus.LOW_SPEED  # not counted
    assert mean_nll(epoch_nll(rows)) == pytest.approx(0.5 + math.log(2.0 * math.pi))


#: the filter with the stiffness fixed (its Q and P0 zero): its innovations' likelihood is the data's
FIXED_STIFFNESS = replace(EstimatorConfig().options, change_detection=False, relinearization_window=0.0,
                          noise_adaptation=False)


def maximum_likelihood(epochs: EpochArrays, start: np.ndarray) -> np.ndarray:
    """(ln Cf, ln Cr) that minimise the innovations' NLL of the fixed-stiffness filter (Nelder-Mead from ``start``)."""
    def nll(theta: np.ndarray) -> float:
        noise = NoiseParams(process_noise=(1.0e-4, 1.0e-4, 0.0, 0.0), initial_stiffness=tuple(np.exp(theta)),
                            initial_covariance=(1.0e-2, 1.0e-2, 0.0, 0.0))
        return float(np.nansum(epoch_nll(run_sequence(EstimatorConfig(options=FIXED_STIFFNESS, noise=noise),
                                                      epochs))))
    simplex = [start, start + [0.1, 0.0], start + [0.0, 0.1]]
    return minimize(nll, start, method="Nelder-Mead",
                    options={"xatol": 1.0e-3, "fatol": 1.0e-3, "initial_simplex": simplex}).x


def distance_to_maximum_likelihood(seed: int) -> np.ndarray:
    """Field work's first row and U-turn (52 s): |EKF - ML| of ln Cf, ln Cr in the EKF's std."""
    epochs = EpochArrays(epochs_from_result(simulate(build_config("field-work", seed=seed, duration=52.0)),
                                            EstimatorConfig().vehicle))
    last = run_sequence(RELINEARIZED, epochs)[-1]
    estimate = np.log([last[O_CF], last[O_CR]])
    std = np.array([last[O_CF_STD] / last[O_CF], last[O_CR_STD] / last[O_CR]])
    return np.abs(estimate - maximum_likelihood(epochs, estimate)) / std


def test_a_straight_start_leaves_the_estimate_where_the_data_put_it() -> None:
    """Field work (a 40 s row with +-2 deg corrections, then a U-turn), seeds 0-11: the EKF at the ML.

    The first seconds of a straight start carry next to nothing, yet P0's std of 2 in ln C let them
    throw Cf from the truth to a 14th of it; every new pass, from P0 again, went the same way, and
    (with the change test of before, ekf.change_scale 4) the U-turn left seed 9 at -41 % with a std
    of 4.9 % (the ML: -3 %). A new pass's prior of ln C is now at most PRIOR_SIGMAS of its std wide.
    |EKF - ML| / std after the turn, measured: mean 0.18 / 0.16, worst 1.0 / 0.9; with an unbounded
    prior 0.51 / 0.53 and 1.05 / 1.55 (the change test of before: 0.73 / 0.61 and 7.8 / 3.9 over
    seeds 0-19). Asserted: every seed <= 1.5, mean <= 0.35. The ML: Nelder-Mead over the
    fixed-stiffness filter's NLL.
    """
    distances = np.array([distance_to_maximum_likelihood(seed) for seed in range(12)])
    assert np.max(distances) <= 1.5 and np.all(np.mean(distances, axis=0) <= 0.35), distances


def test_with_an_unbounded_prior_a_new_pass_falls_as_the_first(monkeypatch: pytest.MonkeyPatch) -> None:
    """The failure the bound fixes, so the test above can fail: the mean over seeds 0-11 > 0.35 (measured 0.51 / 0.53)."""
    monkeypatch.setattr(relinearization, "PRIOR_SIGMAS", math.inf)
    distances = np.array([distance_to_maximum_likelihood(seed) for seed in range(12)])
    assert np.any(np.mean(distances, axis=0) > 0.35), distances
