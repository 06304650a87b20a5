"""The Cramér-Rao bound of the stiffness (issue #11 item 2): the compiled information against a slow, obvious one.

The compiled kernel carries the output sensitivities forward with the exact dE/dtheta of the
model; the obvious version re-simulates the open-loop model at perturbed parameters (central
differences) with the plain Phi/Gamma matrices. Then what the bound says on the project's drives:
small on the identification drive, large in the weak direction of the paper's slow held step, and
below the filter's sigma wherever the filter is calibrated (10 seeds).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from drives import TRUE_CF, TRUE_CR, sine_drive
from helpers import epochs_from_result

from transplanter_ident.bags import SimBagOptions, write_sim_bag
from transplanter_ident.cli import replay as replay_cli
from transplanter_ident.config.parameters import EstimatorConfig, VehicleParams
from transplanter_ident.ekf.information import N_INFORMATION, output_error_information
from transplanter_ident.ekf.joint_ekf import kernel_input, run_sequence
from transplanter_ident.ekf.layout import EXACT, O_CF, O_CF_STD, O_CR, O_CR_STD
from transplanter_ident.ekf.model import discrete_matrices, vehicle_array, work_buffer
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.evaluation.cramer_rao import cramer_rao_bound
from transplanter_ident.sim.signals import step_steering
from transplanter_ident.sim.simulator import simulate

SEEDS = range(10)
HELD_STEP = {"speed": 1.0, "duration": 90.0, "steering": step_steering(math.radians(20.0), start=2.0, ramp=0.5)}
R_NOISE = (4.0e-4, 1.2e-5)


def slow_information(epochs: EpochArrays, theta: np.ndarray, vehicle: VehicleParams, segment: float) -> np.ndarray:
    """Central differences of the open-loop outputs [vy + ax r, psi], restarted every ``segment`` s."""

    def outputs(th: np.ndarray) -> np.ndarray:
        cf, cr, offset, gain = math.exp(th[0]), math.exp(th[1]), th[2], 1.0 + th[3]
        rows, start, x = [], -math.inf, np.zeros(3)
        for k in range(len(epochs)):
            t = epochs.t[k]
            if t - start >= segment:
                x = np.array([epochs.antenna_lateral_velocity[k] - vehicle.antenna_x * epochs.yaw_rate[k],
                              epochs.yaw_rate[k], epochs.heading[k]])
                start = t
                rows.append(None)
                continue
            dt, rate = t - epochs.t[k - 1], epochs.steering_rate[k]
            phi, gamma = discrete_matrices(vehicle, cf, cr, epochs.speed[k], dt, with_heading=True)
            ramp = discrete_ramp_column(vehicle, cf, cr, epochs.speed[k], dt)
            x = phi @ x + gamma * (gain * (epochs.steering[k] - 0.5 * rate * dt) - offset) + ramp * gain * rate
            rows.append(np.array([x[0] + vehicle.antenna_x * x[1], x[2]]))
        return rows

    steps = (1e-5, 1e-5, 1e-7, 1e-6)
    plus, minus = [], []
    for i, h in enumerate(steps):
        up, down = theta.copy(), theta.copy()
        up[i] += h
        down[i] -= h
        plus.append(outputs(up))
        minus.append(outputs(down))
    information = np.zeros((N_INFORMATION, N_INFORMATION))
    for k in range(len(epochs)):
        if plus[0][k] is None:
            continue
        sens = np.column_stack([(plus[i][k] - minus[i][k]) / (2.0 * steps[i]) for i in range(N_INFORMATION)])
        v = epochs.speed[k]
        r = np.array([[R_NOISE[0] + v * v * R_NOISE[1], -v * R_NOISE[1]], [-v * R_NOISE[1], R_NOISE[1]]])
        information += sens.T @ np.linalg.solve(r, sens)
    return information


def discrete_ramp_column(vehicle: VehicleParams, cf: float, cr: float, speed: float, dt: float) -> np.ndarray:
    """The steering-rate column of the exact discretisation (E[:3, 4] of model.discretize)."""
    from transplanter_ident.ekf.layout import W_E
    from transplanter_ident.ekf.model import discretize

    ws = work_buffer()
    discretize(cf, cr, 1.0, 1.0, speed, dt, vehicle_array(vehicle), True, EXACT, False, ws)
    return ws[W_E, :3, 4].copy()


def test_the_compiled_information_matches_central_differences_of_the_open_loop_model() -> None:
    vehicle = VehicleParams(antenna_x=0.5)
    result = simulate(sine_drive(3, duration=25.0, vehicle=vehicle))
    epochs = EpochArrays(epochs_from_result(result, vehicle))
    theta = np.array([math.log(7000.0), math.log(11000.0), 0.004, -0.01])
    fast = np.zeros((N_INFORMATION, N_INFORMATION))
    used = output_error_information(kernel_input(epochs), theta, vehicle_array(vehicle), vehicle.antenna_x,
                                    np.array(R_NOISE), 10.0, 0.3, 2.0, EXACT, False, work_buffer(), fast)
    slow = slow_information(epochs, theta, vehicle, 10.0)
    assert used == len(epochs) - 3  # one restart per 10 s segment
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-6 * np.max(np.abs(slow)))


@pytest.mark.parametrize("from_covariance", [False, True])
def test_the_information_takes_each_epochs_reported_variance_as_the_filter_does(from_covariance: bool) -> None:
    """With ekf.measurement_noise_from_covariance, R is the reported variance where larger (R floors it)."""
    from transplanter_ident.ekf.layout import E_VAR_PSI, E_VAR_VY

    vehicle = VehicleParams(antenna_x=0.5)
    rows = kernel_input(EpochArrays(epochs_from_result(simulate(sine_drive(4, duration=20.0, vehicle=vehicle)))))
    theta = np.array([math.log(8000.0), math.log(10000.0), 0.0, 0.0])

    def information(reported_scale: float) -> np.ndarray:
        scaled = rows.copy()
        scaled[:, E_VAR_VY], scaled[:, E_VAR_PSI] = reported_scale * R_NOISE[0], reported_scale * R_NOISE[1]
        out = np.zeros((N_INFORMATION, N_INFORMATION))
        output_error_information(scaled, theta, vehicle_array(vehicle), vehicle.antenna_x, np.array(R_NOISE), 10.0,
                                 0.3, 2.0, EXACT, from_covariance, work_buffer(), out)
        return out

    configured = information(0.0)
    assert np.all(np.linalg.eigvalsh(configured[:2, :2]) > 0.0)
    np.testing.assert_array_equal(information(0.5), configured)  # smaller than R: R is the floor
    np.testing.assert_allclose(information(4.0), configured / 4.0 if from_covariance else configured, rtol=1e-12)


def final_bound(name: str, seed: int) -> tuple[tuple[float, float], tuple[float, float], object]:
    """(filter final relative 1-sigma, final relative error, bound at the truth) of one drive."""
    scenario = HELD_STEP if name == "held step" else {}
    epochs = EpochArrays(epochs_from_result(simulate(sine_drive(seed, **scenario))))
    last = run_sequence(EstimatorConfig(), epochs)[-1]
    bound = cramer_rao_bound(EstimatorConfig(), epochs, (TRUE_CF, TRUE_CR), 0.0)
    return ((last[O_CF_STD] / last[O_CF], last[O_CR_STD] / last[O_CR]),
            (math.log(last[O_CF] / TRUE_CF), math.log(last[O_CR] / TRUE_CR)), bound)


def test_the_bound_names_the_weak_direction_and_sits_below_a_calibrated_filter() -> None:
    clean = [final_bound("clean", seed) for seed in SEEDS]
    step = [final_bound("held step", seed) for seed in SEEDS[:3]]
    clean_weak = np.median([b.identifiability.weak_std for _, _, b in clean])
    step_weak = np.median([b.identifiability.weak_std for _, _, b in step])
    ratios = np.array([np.divide(sigma, b.relative_std) for sigma, _, b in clean])
    spread = np.std(np.array([error for _, error, _ in clean]), axis=0)
    bound = np.median(np.array([b.relative_std for _, _, b in clean]), axis=0)
    print(f"\nbound at the truth, weakest direction: clean drive {100 * clean_weak:.2f} %, held step "
          f"{100 * step_weak:.1f} %; clean: filter sigma / bound {ratios.min():.2f}-{ratios.max():.2f}, spread of the "
          f"final ln C over 10 seeds {100 * spread[0]:.2f} / {100 * spread[1]:.2f} % vs bound "
          f"{100 * bound[0]:.2f} / {100 * bound[1]:.2f} %")
    assert clean_weak <= 0.03
    assert step_weak >= 5.0 * clean_weak
    assert ratios.min() >= 1.0  # the calibrated filter never claims more than the data hold
    assert np.all(spread >= 0.5 * bound)  # a bound: no estimator scatters much below it (10 seeds)


def test_replay_prints_the_bound_and_the_filter_sigma_against_it(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    write_sim_bag(simulate(sine_drive(1, duration=30.0)), tmp_path / "b", SimBagOptions())
    assert replay_cli.main([str(tmp_path / "b"), "--quiet"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("Cramér-Rao bound"))
    assert "Cf +- " in line and "of it" in line and "weakest along" in line, line
