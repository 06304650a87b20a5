"""A GNSS delay left out of gnss.delay: how far it moves the stiffness, and how the filter measures it.

At farm speeds the stiffness is read off a lateral lag of tens of milliseconds, so a GNSS stamped a
few ms late moves it by percents (the change looks like a stiffer or softer tire). The filter
propagates, through its own F and K, the first-order error per second of such a delay: published as
``delay_sensitivity`` (/diagnostics "convergence", per ms), and with ``ekf.delay_uncertainty``
(1-sigma, s) added to the Cf, Cr std. The same propagation gives the innovation a delay would leave,
and a least-squares fit of the innovations to it measures the delay (``delay_estimate``, with its std);
one ``validity.max_delay_sigmas`` (3) std from zero makes the estimate invalid, and so does one that is
not yet significant but moves Cf or Cr (its lower 1-sigma bound) beyond ``validity.max_delay_shift`` (1.5)
of their reported std.

Measured over seeds 0-9 on the project's simulator (test/drives.py) with defaults.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from drives import pooled_coverage, run_drive, sine_drive
from test_validity import epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, ValiditySettings
from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.ekf.layout import (
    O_DELAY_ESTIMATE,
    O_DELAY_ESTIMATE_STD,
    O_DELAY_SENS_F,
    O_DELAY_SENS_R,
)
from transplanter_ident.evaluation.convergence_report import convergence_report
from transplanter_ident.evaluation.validity import decide_sequence, monitor_for, sample_of
from transplanter_ident.sim.signals import multisine_steering
from transplanter_ident.sim.simulator import simulate

SEEDS = range(10)


@functools.cache
def delayed_runs(delay: float, uncertainty: float = 0.0) -> tuple:
    config = EstimatorConfig(options=FilterOptions(delay_uncertainty=uncertainty))
    return tuple(run_drive(sine_drive(seed, gnss_delay=delay), config) for seed in SEEDS)


@pytest.mark.parametrize("delay", [0.005, 0.010])
def test_the_published_sensitivity_predicts_what_a_delay_does(delay: float) -> None:
    """GNSS 5 or 10 ms late, unconfigured: the mean error is the published sensitivity x delay within 2 points.

    Means of the final Cf and Cr errors over the seeds (measured: -10.6 / -9.1 % against -10.7 / -7.9 % at
    5 ms); the shift is many times the seeds' spread (the test's teeth).
    """
    runs = delayed_runs(delay)
    errors = np.array([r.final_errors() for r in runs])
    predicted = np.array([r.outputs[-1, [O_DELAY_SENS_F, O_DELAY_SENS_R]] * delay for r in runs])
    np.testing.assert_allclose(errors.mean(axis=0), predicted.mean(axis=0), atol=0.02)
    assert np.all(np.abs(errors.mean(axis=0)) > 3.0 * errors.std(axis=0))


@pytest.mark.parametrize("delay", [0.010, 0.020])
def test_a_declared_delay_uncertainty_widens_the_band_to_cover_the_truth(delay: float) -> None:
    """ekf.delay_uncertainty = the delay left out: +-2 sigma covers >= 90 % of epochs after 30 s (else < 10 %).

    The estimate itself is bit-identical.
    """
    plain, declared = delayed_runs(delay), delayed_runs(delay, uncertainty=delay)
    front, rear = pooled_coverage(list(declared), 30.0)
    assert front >= 0.90 and rear >= 0.90, (front, rear)
    assert max(pooled_coverage(list(plain), 30.0)) < 0.10
    for a, b in zip(plain, declared, strict=True):
        np.testing.assert_array_equal(a.cf, b.cf)
        np.testing.assert_array_equal(a.cr, b.cr)


def test_the_convergence_status_shows_the_sensitivity_per_ms() -> None:
    run = run_drive(simulate(sine_drive(0)))
    estimate = Estimate.from_row(float(run.t[-1]), run.outputs[-1])
    values = dict(convergence_report("estimator", estimate, 100, 0.05).values)
    front, rear = (float(v) for v in values["delay_sensitivity_per_ms"].split())
    assert front == pytest.approx(1.0e-3 * run.outputs[-1, O_DELAY_SENS_F], abs=1e-4)
    assert rear == pytest.approx(1.0e-3 * run.outputs[-1, O_DELAY_SENS_R], abs=1e-4)
    assert front < -0.005 and rear < -0.005  # at 2 m/s, more than half a percent per ms


@pytest.mark.parametrize("delay", [-0.010, 0.0, 0.010, 0.020])
def test_the_filter_measures_a_delay_left_out(delay: float) -> None:
    """GNSS -10, 0, 10, 20 ms late, unconfigured: every seed's final measure within 3 std of the delay.

    Their mean within 2 ms; the std is about 3 ms (120 s at 2 m/s).
    """
    last = np.array([r.outputs[-1, [O_DELAY_ESTIMATE, O_DELAY_ESTIMATE_STD]] for r in delayed_runs(delay)])
    estimate, std = last[:, 0], last[:, 1]
    assert np.all(std > 0.0) and np.all(std < 0.005), std
    assert np.all(np.abs(estimate - delay) <= 3.0 * std), (estimate, std)
    assert abs(np.mean(estimate) - delay) <= 0.002, estimate


def test_a_measured_delay_makes_the_estimate_invalid_and_says_so() -> None:
    """20 ms late, unconfigured (stiffness ~30 % off): valid in <= 2 % of epochs after 60 s, seeds 0-9.

    The reason names gnss.delay; on the same drives without the delay, valid in at least 90 %.
    """
    late, clean = [], []
    for seed in SEEDS:
        for delay, shares in ((0.02, late), (0.0, clean)):
            result = simulate(sine_drive(seed, gnss_delay=delay))
            run, epochs = run_drive(result), epochs_of(result)
            valid = decide_sequence(EstimatorConfig(), ValiditySettings(), epochs, run.outputs)
            shares.append(np.mean(valid[run.t >= 60.0]))
    assert np.mean(late) <= 0.02 and np.mean(clean) >= 0.90, (np.mean(late), np.mean(clean))
    result = simulate(sine_drive(0, gnss_delay=0.02))
    run, monitor = run_drive(result), monitor_for(EstimatorConfig(), ValiditySettings())
    reasons = [r for k, epoch in enumerate(epochs_of(result)) for r in monitor.step(sample_of(epoch, run.outputs[k])).reasons]
    assert any("GNSS delay of +" in r and "gnss.delay" in r for r in reasons)


def test_a_delay_that_moves_the_stiffness_beyond_its_band_is_not_valid() -> None:
    """10 ms late, unconfigured (Cf ~ -18 %): valid in <= 8 % of the epochs from 30 s on, seeds 0-9.

    Measured 4.1 % (11 % when the measure started after 20 s of data instead of 10); 29 % without the
    shift check (validity.max_delay_shift 100). The reason says by how much the delay moves the
    stiffness. The same drives without the delay lose <= 3 points (measured 92.7 -> 92.5 %). The other
    model errors' checks (model_errors.py) are off here: a delay looks like a relaxation length or a
    steering gain to them, and they alone leave 4.0 % valid.
    """
    others_off = {f"max_{name}_{test}": 100.0 for name in ("relaxation", "steering_gain") for test in ("sigmas", "shift")}
    checked = ValiditySettings(**others_off)
    without = ValiditySettings(max_delay_shift=100.0, **others_off)
    shares: dict[tuple[float, bool], list[float]] = {}
    for seed in SEEDS:
        for delay in (0.01, 0.0):
            result = simulate(sine_drive(seed, gnss_delay=delay))
            run, epochs = run_drive(result), epochs_of(result)
            for shifts, settings in ((True, checked), (False, without)):
                valid = decide_sequence(EstimatorConfig(), settings, epochs, run.outputs)
                shares.setdefault((delay, shifts), []).append(np.mean(valid[run.t >= 30.0]))
    late, late_unchecked = np.mean(shares[0.01, True]), np.mean(shares[0.01, False])
    clean, clean_unchecked = np.mean(shares[0.0, True]), np.mean(shares[0.0, False])
    assert late <= 0.08 and late_unchecked >= 2.0 * late, (late, late_unchecked)
    assert clean >= clean_unchecked - 0.03, (clean, clean_unchecked)
    result = simulate(sine_drive(1, gnss_delay=0.01))
    run, monitor = run_drive(result), monitor_for(EstimatorConfig(), checked)
    reasons = [r for k, epoch in enumerate(epochs_of(result)) for r in monitor.step(sample_of(epoch, run.outputs[k])).reasons]
    assert any("moves the stiffness by" in r and "gnss.delay" in r for r in reasons)


def test_long_clean_drives_rarely_show_a_delay() -> None:
    """10 seeds x 10 min without a delay: the measure is beyond 3 std in <= 0.5 % of epochs, never beyond 4.

    Measured: 0 on the sine and on the multisine drive (largest 2.4 and 2.2 std).
    """
    multisine = multisine_steering(math.radians(10.0), (3.0, 5.0, 9.0, 14.0), seed=3)
    for overrides in ({}, {"steering": multisine}):
        z = []
        for seed in SEEDS:
            run = run_drive(sine_drive(seed, duration=600.0, **overrides))
            o = run.outputs[run.t >= 30.0]
            z.append(np.abs(o[:, O_DELAY_ESTIMATE]) / o[:, O_DELAY_ESTIMATE_STD])
        z = np.concatenate(z)
        assert np.mean(z > 3.0) <= 0.005 and z.max() < 4.0, (np.mean(z > 3.0), z.max())
