"""GNSS noisier than the configured R (ekf.noise_adaptation): the estimate stays right and its band honest.

Measured over seeds 0-9 on the project's simulator (test/drives.py: 2 m/s, +-15 deg sine steer, 5 Hz,
120 s) with the default parameters, whose R is the simulator's own noise. The GNSS velocity and heading
noise is then raised 2x and 3x (1-sigma), as on a receiver worse than the one R was set for. Without
the adaptation the surface-change CUSUM reads the larger innovations as a stiffness change at nearly
every epoch, and the estimate wanders (median error 17 % at 2x, 39 % at 3x on seeds 0-4); with it,
1.5 % and 3.2 % (seeds 0-9).
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import pytest
from drives import median_and_worst, pooled_coverage, run_drive, sine_drive
from helpers import heading_held
from test_noise_correlation import unwidened_s
from test_validity import epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, ValiditySettings
from transplanter_ident.ekf.layout import (
    O_DT,
    O_E0,
    O_E1,
    O_NOISE_CORRELATION_SECOND,
    O_NOISE_SCALE_SECOND,
    O_NOISE_SCALE_VY,
    O_STATUS,
    StepStatus,
)
from transplanter_ident.evaluation.validity import decide_sequence, monitor_for, sample_of
from transplanter_ident.sim.simulator import SensorNoise, simulate

SEEDS = range(10)
BASE = SensorNoise()


def noisier(velocity: float, heading: float) -> SensorNoise:
    return replace(BASE, velocity=BASE.velocity * velocity, heading=BASE.heading * heading)


@functools.cache
def runs(velocity: float, heading: float, adaptation: bool = True) -> tuple:
    config = EstimatorConfig(options=FilterOptions(noise_adaptation=adaptation))
    return tuple(run_drive(sine_drive(seed, noise=noisier(velocity, heading)), config) for seed in SEEDS)


@pytest.mark.parametrize("factor", [2.0, 3.0])
def test_noisier_gnss_keeps_the_estimate_and_its_band(factor: float) -> None:
    """Median |error| <= 2 % x factor, final errors and epochs after 30 s >= 90 % within +-2 sigma, few late alarms.

    The error grows with the noise's sigma, hence the factor. At most one change alarm after 30 s over
    the 10 drives (20 min; the constant-stiffness budget of test_real_sensors). Measured: none with the
    change test of before (ekf.change_scale 4, threshold 12); one at 67 s (2x) with today's (2, 8), the
    price of seeing a 40 % drop when R is set to sensors 2x noisier (robustness sweep).

    While R is still being learned (the first seconds) the innovations are larger than the filter allows,
    and the change test may fire: that re-opens the stiffness band when it is most needed. Off, the same
    drives raise dozens of alarms and the median error exceeds 5 % (the test's teeth).
    """
    adapted = runs(factor, factor)
    median = median_and_worst([e for r in adapted for e in r.final_errors()])[0]
    assert median <= 0.02 * factor, median
    z = [abs(e) / std for r in adapted for e, std in zip(r.final_errors(), r.final_rel_std(), strict=True)]
    assert np.mean(np.asarray(z) <= 2.0) >= 0.90, z
    front, rear = pooled_coverage(list(adapted), 30.0)
    assert front >= 0.90 and rear >= 0.90, (front, rear)
    assert sum(r.alarms_between(30.0, math.inf) for r in adapted) <= 1
    fixed = runs(factor, factor, adaptation=False)
    assert sum(r.alarms_between(0.0, math.inf) for r in fixed) > 20
    assert median_and_worst([e for r in fixed for e in r.final_errors()])[0] > 0.05


def test_the_learned_factor_is_the_variance_ratio() -> None:
    """GNSS velocity noise 2x (variance 4x): the factor on R_vy ends within [3, 5.5] on every seed.

    With the simulator's noise (= R) within [1, 1.2]. The factor on the heading's R is never below 1.
    """
    for run in runs(2.0, 1.0):
        assert 3.0 <= run.outputs[-1, O_NOISE_SCALE_VY] <= 5.5
    for run in runs(1.0, 1.0):
        assert 1.0 <= run.outputs[-1, O_NOISE_SCALE_VY] <= 1.2
        assert np.all(run.outputs[:, O_NOISE_SCALE_SECOND] >= 1.0)


@pytest.mark.parametrize("widened", [False, True])
def test_the_kernel_learns_as_a_plain_loop_over_its_outputs(widened: bool) -> None:
    """The compiled covariance matching equals a plain Python loop over the published innovations and S.

    Per epoch the filter passed (UPDATED or NONLINEAR): prior = S_ii - R_i f_i (f: the factor in use, the
    previous epoch's), sample (e_i^2 - prior) / R_i of weight (R_i f_i / S_ii)^2 dt, a weighted mean over the
    first ekf.noise_memory s, then exponential; the factor is that mean clipped to [1, max_noise_scale]. vy's
    waits while the filter holds the heading misalignment h (helpers.heading_held: until the model is near);
    then both start again from nothing (noise_correlation.restart_noise_when_near).
    ``widened`` (ekf.noise_correlation): S is the one with R unwidened, rebuilt from the published S
    (test_noise_correlation.unwidened_s). One pass (``ekf.relinearization_window: 0``): a re-linearised
    pass goes on from what it learned over epochs whose outputs were published by the pass before it.
    """
    config = EstimatorConfig(options=replace(EstimatorConfig().options, relinearization_window=0.0,
                                             noise_correlation=widened))
    options, r = config.options, np.array(config.noise.measurement_noise)
    result = simulate(sine_drive(3, noise=noisier(2.0, 1.5)))
    speed = np.asarray(epochs_of(result).speed)
    out = run_drive(result, config).outputs
    mean, span = np.zeros(2), np.zeros(2)
    factors = np.ones(2)
    checked, restarted = 0, False
    for k in range(1, len(out)):
        if int(out[k, O_STATUS]) in (StepStatus.UPDATED, StepStatus.NONLINEAR):
            held = heading_held(out, k)  # the model is still far off (h is held meanwhile)
            s = unwidened_s(config, speed[k], out[k - 1], out[k])  # HPH^T + R f, f the factors in use
            if not held and not restarted:  # near now: the measure starts again, at the configured R (f = 1)
                excess = r * (factors - 1.0)
                s = s - np.array([excess[0] + speed[k] ** 2 * excess[1], excess[1]])
                mean, span, factors, restarted = np.zeros(2), np.zeros(2), np.ones(2), True
            learnt = np.array([not held, True])  # vy's R waits while h is held
            noise = r * factors
            e = out[k, [O_E0, O_E1]]
            prior = s - noise
            weight = np.where(learnt, (noise / s) ** 2 * out[k, O_DT], 0.0)
            span = np.where(learnt, np.minimum(span + weight, options.noise_memory), span)
            mean += np.where(learnt, weight / np.where(span > 0.0, span, 1.0), 0.0) * ((e * e - prior) / r - mean)
            checked += 1
        expected = np.where(span > 0.0, np.clip(mean, 1.0, options.max_noise_scale), 1.0)
        np.testing.assert_allclose(out[k, [O_NOISE_SCALE_VY, O_NOISE_SCALE_SECOND]], expected, rtol=1e-9)
        factors = expected
    assert checked > 500 and factors[0] > 2.0  # the loop saw the adaptation at work
    assert not widened or np.max(out[:, O_NOISE_CORRELATION_SECOND]) > 0.05  # and R widened (measured 0.087: +19 %)


def test_noisier_gnss_is_not_valid_and_says_why() -> None:
    """GNSS 2x noisier than R (4x its variance, beyond validity.max_noise_factor 2.25): a wrong R is a wrong set-up.

    The chi^2 test then takes the NIS against the configured R, and the reason names ekf.measurement_noise.
    """
    result = simulate(sine_drive(0, noise=noisier(2.0, 2.0)))
    run = run_drive(result)
    monitor = monitor_for(EstimatorConfig(), ValiditySettings())
    decisions = [monitor.step(sample_of(epoch, run.outputs[k])) for k, epoch in enumerate(epochs_of(result))]
    late = [d for d, t in zip(decisions, run.t, strict=True) if t >= 30.0]
    assert not any(d.valid for d in late)
    assert any("innovations inconsistent with R" in reason for d in late for reason in d.reasons)
    assert any("GNSS noisier than ekf.measurement_noise" in reason for d in late for reason in d.reasons)


@pytest.mark.parametrize("max_noise_factor", [2.25, 1.0])
def test_gnss_a_little_noisier_than_r_is_measured_not_a_fault(max_noise_factor: float) -> None:
    """GNSS 1.3x noisier than R (1-sigma; the factor the innovations show reads 1.6-2.1), seeds 0-9, from 30 s on.

    The chi^2 test takes R times that factor up to validity.max_noise_factor (2.25): valid in >= 60 % of the
    epochs (80 % measured; 18 % when the test took the configured R), <= 5 % of them outside +-2 sigma (0
    measured). With the factor held to 1 (the configured R) never valid.
    """
    kept = missed = epochs = 0
    settings = ValiditySettings(max_noise_factor=max_noise_factor)
    for seed in SEEDS:
        result = simulate(sine_drive(seed, noise=noisier(1.3, 1.3)))
        run = run_drive(result)
        after = run.t >= 30.0
        valid = decide_sequence(EstimatorConfig(), settings, epochs_of(result), run.outputs) & after
        front, rear = run.covered()
        kept, missed = kept + int(valid.sum()), missed + int((valid & ~(front & rear)).sum())
        epochs += int(after.sum())
    if max_noise_factor > 1.0:
        assert kept >= 0.6 * epochs and missed <= 0.05 * kept, (kept, missed, epochs)
    else:
        assert kept == 0, kept


@pytest.mark.parametrize("rate", [10.0, 20.0])
def test_the_start_from_the_prior_is_not_read_as_noise(rate: float) -> None:
    """GNSS at 10 / 20 Hz with the simulator's noise (= R), seeds 0-7: no factor on R above 1.5 from 30 s on.

    The filter starts far from the truth (C0 = 1000 N/rad); while it converges its errors are neither noise
    nor a misaligned heading, so the measure of R starts again once both stiffnesses are known (or 10 s of
    data are in; noise_correlation.restart_noise_when_near). Without that, seed 3 read the start as a heading 100x
    noisier than R within 3 s, kept a factor of 6.9 (10 Hz) and 3.3 (20 Hz) from 30 s on, and was valid in
    0 % and 61 % of those epochs (the other seeds <= 1.35). Measured since: <= 1.23 on seeds 0-11 (5 Hz:
    <= 1.32), seed 3 valid in 100 % (10 Hz) and 90 % (20 Hz).
    """
    for seed in range(8):
        result = simulate(replace(sine_drive(seed), gnss_rate=rate))
        run = run_drive(result)
        after = run.t >= 30.0
        largest = float(np.max(run.outputs[after][:, [O_NOISE_SCALE_VY, O_NOISE_SCALE_SECOND]]))
        assert largest <= 1.5, (seed, largest)


def test_an_offset_settling_after_the_start_is_not_read_as_noise() -> None:
    """A 2 deg steering offset, seeds 0-9: no factor on R above 1.5 from 30 s on, valid in >= 90 % of those epochs.

    The measure of R starts again once both stiffnesses are known, while the offset may still be settling. A
    first version learnt no R before then: the start went undamped and the offset still settled when the
    measure began, so its first samples set the factor (up to 32 on the heading within a second, still 3.3
    and 3.6 from 30 s on, seeds 1 and 5), and the row was valid in 87 % of those epochs (96 % before, and now).
    """
    valid = epochs = 0
    for seed in SEEDS:
        result = simulate(sine_drive(seed, steering_offset=math.radians(2.0)))
        run = run_drive(result)
        after = run.t >= 30.0
        largest = float(np.max(run.outputs[after][:, [O_NOISE_SCALE_VY, O_NOISE_SCALE_SECOND]]))
        assert largest <= 1.5, (seed, largest)
        valid += int((decide_sequence(EstimatorConfig(), ValiditySettings(), epochs_of(result), run.outputs)
                      & after).sum())
        epochs += int(after.sum())
    assert valid >= 0.9 * epochs, (valid, epochs)
