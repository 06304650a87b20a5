"""``ekf.yaw_inertia_uncertainty``: the Cf, Cr std hold the bias a yaw inertia left out of vehicle.iz causes.

Iz scales the yaw equation alone (paper eq. 1), so the filter carries the first-order bias per unit
of ln Iz (adaptation.propagate_inertia_bias, from a difference quotient of the prediction); the std
holds it times the declared 1-sigma. Checked against the obvious version, a second run with Iz
changed, and for coverage: on the identification drive (2 m/s, +-15 deg, 120 s), seeds 0-2.
"""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest
from drives import Run, exact_claim, run_drive, sine_drive

from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions, VehicleParams
from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD
from transplanter_ident.sim.simulator import SimResult, simulate

SEEDS = (0, 1, 2)
VEHICLE = VehicleParams()


@functools.cache
def drive(seed: int) -> SimResult:
    return simulate(sine_drive(seed))


def run_with(seed: int, iz_factor: float, uncertainty: float, options: FilterOptions | None = None) -> Run:
    """The drive filtered with vehicle.iz = iz_factor x the true Iz and ekf.yaw_inertia_uncertainty."""
    config = EstimatorConfig(vehicle=replace(VEHICLE, iz=iz_factor * VEHICLE.yaw_inertia),
                             options=replace(options or FilterOptions(), yaw_inertia_uncertainty=uncertainty))
    return run_drive(drive(seed), config)


@pytest.mark.parametrize("seed", SEEDS)
def test_the_held_bias_is_what_an_inertia_error_does(seed: int) -> None:
    """|d ln C / d ln Iz| from the std's growth matches a run with Iz 2 % high within 15 % (measured 2-4 %)."""
    right, declared, high = run_with(seed, 1.0, 0.1), run_with(seed, 1.0, 0.0), run_with(seed, 1.02, 0.0)
    for value, std in ((O_CF, O_CF_STD), (O_CR, O_CR_STD)):
        held = np.sqrt(right.outputs[-1, std] ** 2 - declared.outputs[-1, std] ** 2) / 0.1 / right.outputs[-1, value]
        actual = abs(high.outputs[-1, value] / right.outputs[-1, value] - 1.0) / np.log(1.02)
        assert held == pytest.approx(actual, rel=0.15), (value, held, actual)
        assert actual > 0.3  # Iz matters: about 0.6-0.9 % of stiffness per % (measured 0.62, 0.95)


@pytest.mark.parametrize("iz_factor", [0.85, 1.15])
def test_a_declared_inertia_uncertainty_widens_the_band_to_cover_the_truth(iz_factor: float) -> None:
    """Iz configured 15 % off: with the declared 15 %, +-2 sigma covers Cf and Cr in >= 90 % of the epochs after 30 s.

    Without it, and with the exact claim's band (config/exact_calibration.yaml: the defaults' band also holds
    1 ms of timing and 0.3 % of steering gain), one of them is covered in <= 10 % on every seed (measured
    0-5 %; Cr at 1.15 x: 39-94 %).
    """
    for seed in SEEDS:
        declared, unset = run_with(seed, iz_factor, 0.15), run_with(seed, iz_factor, 0.0, exact_claim())
        assert all(np.mean(c[declared.t >= 30.0]) >= 0.9 for c in declared.covered()), seed
        assert min(np.mean(c[unset.t >= 30.0]) for c in unset.covered()) <= 0.1, seed
