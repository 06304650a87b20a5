"""A tire relaxation length left out of ``vehicle.relaxation_length``: the filter measures it, the validity uses it.

Left out, 0.3 m at 2 m/s made Cf ~12 % high while the estimate stayed valid in 84 % of the epochs,
88 % of those outside +-2 sigma (README, the robustness table). Checked here:

* the signature's missed motion (``relaxation_signature.propagate_relaxation_bias``) against a slow,
  obvious version: the bicycle model integrated by scipy with and without the slip deficits;
* the measure (layout.O_RELAXATION) against the simulator's length, over seeds, and its z on drives
  without relaxation;
* the validity: on relaxing drives far fewer valid epochs miss the truth, and the reason says what to
  set; on clean drives and with the length configured, availability stays.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from drives import judged_figures, run_drive, sine_drive
from scipy.integrate import solve_ivp
from test_validity import epochs_of

from transplanter_ident.config.parameters import EstimatorConfig, ValiditySettings, VehicleParams
from transplanter_ident.ekf.layout import (
    B_DIRECT,
    EXACT,
    N_MEMO,
    N_MOTION_HEADING,
    N_MOTION_YAW_RATE,
    N_PARAMETER_STATES,
    O_RELAXATION,
    O_RELAXATION_SENS_F,
    O_RELAXATION_STD,
    W_BIAS,
    W_E,
    W_F,
    X_PSI,
    X_R,
)
from transplanter_ident.ekf.model import discretize, vehicle_array, work_buffer
from transplanter_ident.ekf.relaxation_signature import propagate_relaxation_bias, slip_deficits
from transplanter_ident.evaluation.validity import decide_sequence, monitor_for, sample_of
from transplanter_ident.sim.simulator import simulate

SEEDS = range(8)
CHECK_OFF = ValiditySettings(max_relaxation_sigmas=100.0, max_relaxation_shift=100.0)


def slow_missed_motion(vehicle: VehicleParams, cf: float, cr: float, vx: float, dt: float, start: np.ndarray,
                       delta: float, rate: float, deficits: tuple[float, float], heading: bool) -> np.ndarray:
    """[vy, r, (psi)] after dt with each axle's slip short by ``deficits``, minus without: scipy, eq. 4 written out."""

    def rhs(_t: float, z: np.ndarray, eps: tuple[float, float]) -> np.ndarray:
        vy, r = z[0], z[1]
        wheel = delta + rate * _t
        force_f = 2.0 * cf * (wheel - (vy + vehicle.lf * r) / vx - eps[0])
        force_r = 2.0 * cr * ((vehicle.lr * r - vy) / vx - eps[1])
        derivative = [-vx * r + (force_f + force_r) / vehicle.mass,
                      (vehicle.lf * force_f - vehicle.lr * force_r) / vehicle.yaw_inertia]
        return np.array(derivative + ([r] if heading else []))

    ends = [solve_ivp(rhs, (0.0, dt), start, args=(eps,), rtol=1e-12, atol=1e-14).y[:, -1]
            for eps in (deficits, (0.0, 0.0))]
    return ends[0] - ends[1]


@pytest.mark.parametrize("heading", [False, True])
def test_the_missed_motion_is_the_models_response_to_the_slip_deficits(heading: bool) -> None:
    """The kernel's direct term against :func:`slow_missed_motion` on 12 random draws.

    Required: within 1e-6 of the largest entry (the identity int e^(A s) ds A = E - I is exact; measured
    ~1e-9, scipy's tolerance).
    """
    rng = np.random.default_rng(3)
    nd = N_MOTION_HEADING if heading else N_MOTION_YAW_RATE
    n = nd + N_PARAMETER_STATES
    for _ in range(12):
        cf, cr = rng.uniform(2000.0, 30000.0, 2)
        vx, dt = rng.uniform(0.5, 3.5), rng.choice([0.05, 0.2, 0.5])
        vehicle = VehicleParams(mass=rng.uniform(500.0, 1500.0), lf=rng.uniform(0.4, 1.0), lr=rng.uniform(0.3, 0.8))
        deficits = tuple(rng.normal(0.0, 0.01, 2))
        start = rng.normal(0.0, 0.1, nd)
        delta, rate = rng.normal(0.0, 0.2), rng.normal(0.0, 0.3)
        ws = work_buffer()
        discretize(cf, cr, 1.0, 1.0, vx, dt, vehicle_array(vehicle), heading, EXACT, False, ws)
        ws[W_F, :nd, :nd] = ws[W_E, :nd, :nd]
        ws[W_F, :nd, nd + 2] = -ws[W_E, :nd, nd]  # d x / d offset (prediction.predict_n)
        propagate_relaxation_bias(np.zeros(N_MEMO), n, nd, nd + 2, X_PSI if heading else X_R, False, vx,
                                  deficits[0], deficits[1], ws)
        want = slow_missed_motion(vehicle, cf, cr, vx, dt, start, delta, rate, deficits, heading)
        assert np.max(np.abs(ws[W_BIAS, B_DIRECT, :nd] - want)) <= 1e-6 * np.max(np.abs(want))


def test_the_slip_deficit_is_the_slip_rate_over_the_speed() -> None:
    """Without lags: ((alpha_end - alpha_start) / dt) / vx per axle, alpha of eq. 3 from the motion and the ramp."""
    vehicle = VehicleParams()
    before, after = np.array([0.05, 0.1, 0.0, 0.0, 0.0]), np.array([0.07, 0.12, 0.0, 0.0, 0.0])
    vx, dt, rate = 2.0, 0.2, 0.3

    def slips(state: np.ndarray, wheel: float) -> np.ndarray:
        return np.array([wheel - (state[0] + vehicle.lf * state[1]) / vx, (vehicle.lr * state[1] - state[0]) / vx])

    want = (slips(after, rate * dt) - slips(before, 0.0)) / dt / vx
    got = slip_deficits(before, after, vehicle_array(vehicle), dt, vx, rate, N_MOTION_HEADING, False, 0.0)
    assert np.allclose(got, want, rtol=1e-12, atol=0.0)


def _runs(relaxation: float, configured: float = 0.0) -> list:
    """The identification drive (2 m/s, +-15 deg sine, 120 s) on tires relaxing over ``relaxation`` m, per seed."""
    runs = []
    for seed in SEEDS:
        sim = sine_drive(seed, relaxation_length=relaxation)
        result = simulate(sim)
        config = EstimatorConfig(vehicle=dataclasses.replace(sim.vehicle, relaxation_length=configured))
        runs.append((result, config, run_drive(result, config)))
    return runs


@pytest.fixture(scope="module")
def relaxing() -> list:
    return _runs(0.3)


@pytest.fixture(scope="module")
def clean() -> list:
    return _runs(0.0)


def test_the_measure_finds_the_relaxation_length(relaxing: list, clean: list) -> None:
    """At 120 s, over 8 seeds: 0.3 m measured within 0.1 m on average, and z = (measure - truth) / std within 3.

    Without relaxation |z| <= 3 on every seed. The sensitivity of Cf times 0.3 m is within 40 % of the
    error the relaxation causes: it is first order, and the response bends (measured 15.2 % against 11.9 %).
    """
    final = np.array([run.outputs[-1, [O_RELAXATION, O_RELAXATION_STD, O_RELAXATION_SENS_F]]
                      for _r, _c, run in relaxing])
    errors = np.array([run.final_errors()[0] for _r, _c, run in relaxing])
    print(f"\nrelaxation 0.3 m: measured {np.round(final[:, 0], 3)} +- {np.round(final[:, 1], 3)}; "
          f"Cf error {np.round(errors, 3)}, sensitivity x 0.3 m {np.round(0.3 * final[:, 2], 3)}")
    assert abs(np.mean(final[:, 0]) - 0.3) <= 0.1
    assert np.all(np.abs(final[:, 0] - 0.3) <= 3.0 * final[:, 1])
    assert abs(np.mean(0.3 * final[:, 2]) / np.mean(errors) - 1.0) <= 0.4
    none = np.array([run.outputs[-1, [O_RELAXATION, O_RELAXATION_STD]] for _r, _c, run in clean])
    print(f"no relaxation: z {np.round(none[:, 0] / none[:, 1], 2)}")
    assert np.all(np.abs(none[:, 0]) <= 3.0 * none[:, 1])


def _figures(runs: list, settings: ValiditySettings) -> tuple[float, float]:
    figures = judged_figures((run, decide_sequence(config, settings, epochs_of(result), run.outputs))
                             for result, config, run in runs)
    return figures.valid, figures.missed


def test_relaxing_drives_are_seldom_valid_and_wrong(relaxing: list) -> None:
    """0.3 m left out, 8 seeds, from 30 s on: valid and outside +-2 sigma in at most 5 % of the epochs.

    And in at most a tenth of the share without the check, which is >= 30 % (measured 1.2 % against 41 %; 0.8 %
    against 73 % with the narrower band of config/exact_calibration.yaml, the defaults until session 38; 5 % with
    validity.max_relaxation_shift 1.5); the reason names vehicle.relaxation_length.
    """
    valid, missed = _figures(relaxing, ValiditySettings())
    valid_off, missed_off = _figures(relaxing, CHECK_OFF)
    print(f"\nrelaxation 0.3 m: valid {valid:.2f}, of those missed {missed:.3f}; without the check {valid_off:.2f}, "
          f"{missed_off:.3f}")
    assert valid_off * missed_off >= 0.3  # the condition this test is about
    assert valid * missed <= 0.05 and valid * missed <= 0.1 * valid_off * missed_off
    result, config, run = relaxing[0]
    monitor = monitor_for(config, ValiditySettings())
    epochs = epochs_of(result)
    reasons = {r for i, row in enumerate(run.outputs) for r in monitor.step(sample_of(epochs[i], row)).reasons}
    assert any("vehicle.relaxation_length" in r for r in reasons)


def test_without_relaxation_or_with_it_configured_availability_stays(clean: list) -> None:
    """8 seeds, from 30 s on: valid at most 3 points less often than without the check, clean or with 0.3 m set.

    Measured: 98.8 % either way clean, 92.0 % either way with the length set.
    """
    configured = _runs(0.3, configured=0.3)
    for name, runs in (("clean", clean), ("0.3 m set", configured)):
        valid, _ = _figures(runs, ValiditySettings())
        valid_off, _ = _figures(runs, CHECK_OFF)
        print(f"\n{name}: valid {valid:.3f}, without the check {valid_off:.3f}")
        assert valid >= valid_off - 0.03


def test_diagnostics_and_replay_show_the_measure(relaxing: list) -> None:
    """/diagnostics "convergence" and replay's model errors line show the last epoch's measure as it is."""
    from transplanter_ident.ekf.estimate import Estimate
    from transplanter_ident.evaluation.convergence_report import convergence_report, model_errors_line

    _result, _config, run = relaxing[0]
    estimate = Estimate.from_row(float(run.t[-1]), run.outputs[-1])
    length, std = run.outputs[-1, [O_RELAXATION, O_RELAXATION_STD]]
    values = dict(convergence_report("estimator", estimate, updates=len(run.t), limit=0.05).values)
    assert values["relaxation_estimate_m"] == f"{length:+.3f} {std:.3f}"
    front = float(values["relaxation_sensitivity_per_cm"].split()[0])
    assert front == pytest.approx(0.01 * run.outputs[-1, O_RELAXATION_SENS_F], abs=1e-4)
    line = model_errors_line(estimate, 0.0)
    assert f"{length:+.3f} +- {std:.3f} m" in line and "vehicle.relaxation_length (0 m)" in line
