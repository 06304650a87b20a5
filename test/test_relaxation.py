"""Relaxing tires (``vehicle.relaxation_length``): the slip lags in the model, and what they buy.

A real tire builds its lateral force over its relaxation length. Left out of the model, 0.3 m at
2 m/s biases Cf by about +12 %, and only the filter's measure of the lag makes the estimate invalid
(test_relaxation_measure.py; README, the robustness table). With
the length configured, the filter carries each axle's slip lag d (force C (alpha - d), d' = alpha' -
(vx / sigma) d). Checked here: the compiled discretisation against scipy's expm of the obvious
matrix (E and its derivatives), and the estimate against the truth on relaxing drives of both
simulators, over seeds, from 30 s on.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from drives import pooled_validity_figures, run_drive, sine_drive
from independent_sim import independent_drive
from scipy.linalg import expm
from test_validity import epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, ValiditySettings, VehicleParams
from transplanter_ident.ekf.joint_ekf import FilterArrays, JointEKF
from transplanter_ident.ekf.layout import (
    EXACT,
    HEADING_LAG_STATES,
    HEADING_STATES,
    W_DE_F,
    W_DE_R,
    W_DE_V,
    W_E,
    YAW_RATE_LAG_STATES,
)
from transplanter_ident.ekf.model import (
    discretize_heading_lagged,
    discretize_yaw_rate_lagged,
    vehicle_array,
    work_buffer,
)
from transplanter_ident.sim.signals import field_work
from transplanter_ident.sim.simulator import simulate

SEEDS = range(6)
_STEERING, _SPEED = field_work()  # rows at 2 m/s, +-2 deg; U-turns at 1.2 m/s, 30 deg (bench/robustness_sweep.py)
FIELD_WORK = {"duration": 300.0, "steering": _STEERING, "speed_profile": _SPEED}


def obvious_matrix(vehicle: np.ndarray, cf: float, cr: float, vx: float, sigma: float, heading: bool) -> np.ndarray:
    """M over [vy, r, (psi), d_f, d_r, delta, delta'], column by column from the right-hand side written out.

    ``sigma`` 0: eq. 4 (the forces C alpha; the lags' rows zero).
    """
    mass, lf, lr, iz = vehicle[:4]
    motion = 3 if heading else 2
    size = motion + 4

    def rhs(z: np.ndarray) -> np.ndarray:
        vy, r, lag_f, lag_r, delta, rate = z[0], z[1], z[motion], z[motion + 1], z[motion + 2], z[motion + 3]
        if sigma == 0.0:
            lag_f = lag_r = 0.0
        force_f = 2.0 * cf * (delta - (vy + lf * r) / vx - lag_f)
        force_r = 2.0 * cr * ((lr * r - vy) / vx - lag_r)
        vy_dot = -vx * r + (force_f + force_r) / mass
        r_dot = (lf * force_f - lr * force_r) / iz
        out = np.zeros(size)
        out[0], out[1] = vy_dot, r_dot
        if heading:
            out[2] = r
        if sigma > 0.0:
            out[motion] = rate - (vy_dot + lf * r_dot) / vx - vx / sigma * lag_f  # alpha_f' - (vx / sigma) d_f
            out[motion + 1] = (lr * r_dot - vy_dot) / vx - vx / sigma * lag_r
        out[motion + 2] = rate
        return out

    return np.column_stack([rhs(np.eye(size)[j]) for j in range(size)])


@pytest.mark.parametrize("heading", [False, True])
def test_the_lagged_discretisation_is_the_matrix_exponential(heading: bool) -> None:
    """E = expm(M dt) and dE/dCf, dE/dCr, dE/dvx (central differences of expm) on 12 random draws.

    Required: E within 1e-10 of its largest entry, the derivatives within 1e-6 of theirs (measured
    4e-13, and 4e-8 / 1e-8 / 5e-8: the central differences' own error).
    """
    rng = np.random.default_rng(0)
    discretize = discretize_heading_lagged if heading else discretize_yaw_rate_lagged
    rows = (3 if heading else 2) + 2
    for _ in range(12):
        cf, cr = rng.uniform(2000.0, 30000.0, 2)
        vx, sigma, dt = rng.uniform(0.5, 3.5), rng.uniform(0.05, 1.0), rng.choice([0.05, 0.1, 0.2, 0.5])
        vehicle = vehicle_array(VehicleParams(mass=rng.uniform(500.0, 1500.0), lf=rng.uniform(0.4, 1.0),
                                              lr=rng.uniform(0.3, 0.8), relaxation_length=sigma))
        ws = work_buffer()
        discretize(cf, cr, 1.0, 1.0, vx, dt, vehicle, EXACT, True, sigma, ws)
        want = expm(obvious_matrix(vehicle, cf, cr, vx, sigma, heading) * dt)[:rows]
        got = ws[W_E, :rows, :rows + 2]
        assert np.max(np.abs(got - want)) <= 1e-10 * np.max(np.abs(want))
        for slot, step in ((W_DE_F, (1.0, 0.0, 0.0)), (W_DE_R, (0.0, 1.0, 0.0)), (W_DE_V, (0.0, 0.0, 1e-4))):
            ahead = expm(obvious_matrix(vehicle, cf + step[0], cr + step[1], vx + step[2], sigma, heading) * dt)
            behind = expm(obvious_matrix(vehicle, cf - step[0], cr - step[1], vx - step[2], sigma, heading) * dt)
            derivative = (ahead - behind)[:rows] / (2.0 * max(step))
            assert np.max(np.abs(ws[slot, :rows, :rows + 2] - derivative)) <= 1e-6 * np.max(np.abs(derivative))


def test_a_short_relaxation_length_is_the_papers_model() -> None:
    """1 mm of relaxation at 2 m/s (0.5 ms): the motion block of E within 1 % of eq. 4's (measured 0.05 %)."""
    vehicle = vehicle_array(VehicleParams(relaxation_length=0.001))
    lagged = work_buffer()
    discretize_heading_lagged(8000.0, 10000.0, 1.0, 1.0, 2.0, 0.2, vehicle, EXACT, False, 0.001, lagged)
    plain = expm(obvious_matrix(vehicle, 8000.0, 10000.0, 2.0, 0.0, True) * 0.2)
    motion, steering = np.r_[0:3], np.r_[5]
    for columns in (motion, steering):
        want = plain[np.ix_(motion, columns)]
        got = lagged[W_E][np.ix_(motion, columns)]
        assert np.max(np.abs(got - want)) <= 0.01 * np.max(np.abs(want))


def test_the_state_carries_the_lags_only_when_a_length_is_configured() -> None:
    default = FilterArrays.from_config(EstimatorConfig())
    relaxing = EstimatorConfig(vehicle=VehicleParams(relaxation_length=0.3))
    assert default.initial_state.shape == (HEADING_STATES,)
    assert FilterArrays.from_config(relaxing).initial_state.shape == (HEADING_LAG_STATES,)
    yaw_rate = dataclasses.replace(relaxing, options=dataclasses.replace(relaxing.options, measurement="yaw_rate"))
    assert JointEKF(yaw_rate).state.shape == (YAW_RATE_LAG_STATES,)


def relaxing_drives(configured: float, seeds: range = SEEDS) -> list:
    """The identification drive (2 m/s, +-15 deg sine) of tires relaxing over 0.3 m, the estimator told ``configured``."""
    drives = []
    for seed in seeds:
        sim = sine_drive(seed, relaxation_length=0.3)
        drives.append((simulate(sim), EstimatorConfig(vehicle=dataclasses.replace(sim.vehicle,
                                                                                  relaxation_length=configured))))
    return drives


def test_a_configured_relaxation_length_makes_relaxing_drives_right() -> None:
    """0.3 m of relaxation at 2 m/s, seeds 0-5: right and valid with the length configured, wrong without.

    Configured: valid in >= 70 % of the epochs (measured 94 %), <= 5 % of those outside +-2 sigma (0),
    final |error| median <= 3 % (1.0 %) and worst <= 6 % (3.4 %). Not configured (seeds 0-2, so that
    this test can fail), and without the validity's relaxation check (test_relaxation_measure.py): >= 30 %
    of the valid epochs outside +-2 sigma (measured 39 % on seeds 0-2; 82 % over seeds 0-5 with the narrower
    band of config/exact_calibration.yaml, the defaults until session 38).
    """
    told = pooled_validity_figures(relaxing_drives(0.3), epochs_of)
    assert told.valid >= 0.7 and told.missed <= 0.05
    assert np.median(told.finals) <= 0.03 and max(told.finals) <= 0.06
    unchecked = ValiditySettings(max_relaxation_sigmas=100.0, max_relaxation_shift=100.0)
    untold = pooled_validity_figures(relaxing_drives(0.0, range(3)), epochs_of, settings=unchecked)
    assert untold.valid > 0.0 and untold.missed >= 0.3


def test_the_independent_simulators_relaxing_drives_are_right() -> None:
    """The independent simulator's force lag (0.3 m, Magic Formula mu 0.8), seeds 0-3, the length configured.

    Required: valid in >= 70 % of the epochs (measured 89 %), <= 5 % outside +-2 sigma (0), final |error|
    median <= 3 % (1.3 %), worst <= 6 % (3.1 %).
    """
    config = EstimatorConfig(vehicle=VehicleParams(relaxation_length=0.3))
    figures = pooled_validity_figures([(independent_drive(seed, relaxation_length=0.3), config) for seed in range(4)],
                                      epochs_of)
    assert figures.valid >= 0.7 and figures.missed <= 0.05
    assert np.median(figures.finals) <= 0.03 and max(figures.finals) <= 0.06


def test_relaxing_drives_at_changing_speed_stay_right() -> None:
    """Field work (rows at 2 m/s, headland U-turns at 1.2 m/s) on tires relaxing over 0.3 m, the length set.

    The lag d = alpha - F / C is carried to each interval's speed (alpha holds 1 / vx, the force does
    not jump): without that, the speed-ups after the turns threw the estimate (final error median 138 %,
    worst 199 %, seeds 0-5). Required over seeds 0-3: final |error| median <= 6 % (measured 4.4 %; 2.5 %
    over seeds 0-5) and worst <= 12 % (9.9 %); unset, seeds 0-5 end at 6.0 / 14.9 % (measured with the
    re-linearised passes' bounded prior and ekf.change_scale 2; 4.2 / 9.8 and 6.0 / 14.5 before).
    """
    finals = []
    for seed in range(4):
        sim = sine_drive(seed, relaxation_length=0.3, **FIELD_WORK)
        config = EstimatorConfig(vehicle=dataclasses.replace(sim.vehicle, relaxation_length=0.3))
        finals.extend(abs(e) for e in run_drive(simulate(sim), config).final_errors())
    assert np.median(finals) <= 0.06 and max(finals) <= 0.12

