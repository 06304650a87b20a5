"""How far a GNSS delay left out of gnss.delay moves the stiffness, and ekf.delay_uncertainty's band.

At farm speeds the stiffness is read off a lateral lag of tens of milliseconds, so a GNSS stamped a
few ms late moves it by percents, and no drive of this kind tells the two apart (the change looks like
a stiffer or softer tire). The filter propagates, through its own F and K, the first-order error per
second of such a delay: published as ``delay_sensitivity`` (/diagnostics "convergence", per ms), and
with ``ekf.delay_uncertainty`` (1-sigma, s) added to the Cf, Cr std.

Measured over seeds 0-9 on the project's simulator (test/drives.py) with defaults.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest
from drives import pooled_coverage, run_drive, sine_drive

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions
from transplanter_ident.ekf.joint_ekf import Estimate
from transplanter_ident.ekf.layout import O_DELAY_SENS_F, O_DELAY_SENS_R
from transplanter_ident.evaluation.convergence_report import convergence_report
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
