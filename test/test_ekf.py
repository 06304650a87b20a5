"""Tests of the joint-state EKF driver code (transplanter_ident.ekf.kernels): online = offline, bad numbers, gate, P."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from helpers import paper_config, simulate_epochs

from transplanter_ident.config.parameters import EstimatorConfig, NoiseParams
from transplanter_ident.ekf.entries import ekf_step, predict
from transplanter_ident.ekf.joint_ekf import (
    Estimate,
    FilterArrays,
    JointEKF,
    run_sequence,
    sequence_objective,
)
from transplanter_ident.ekf.layout import (
    M_SPEED_CROSS,
    N_MEMO,
    N_MODEL,
    N_OUTPUTS,
    O_CF,
    O_CR,
    O_E0,
    O_E1,
    O_NOISE_SCALE_SECOND,
    O_NOISE_SCALE_VY,
    O_STATUS,
    V_SPEED_GAIN,
    W_F,
    W_VEC,
    X_HEADING_OFFSET,
    X_OFFSET,
    X_THETA_F,
    X_THETA_R,
    StepStatus,
)
from transplanter_ident.ekf.model import work_buffer
from transplanter_ident.epochs.epoch import Epoch, EpochArrays
from transplanter_ident.sim.simulator import SensorNoise, SimConfig

TRUE_CF, TRUE_CR = 8000.0, 10000.0
STIFFNESS = [X_THETA_F, X_THETA_R]  # the two stiffness states
#: the filter's defaults but R as configured or adapted, white (the widening is test_noise_correlation.py's)
DEFAULT = EstimatorConfig(options=dataclasses.replace(EstimatorConfig().options, noise_correlation=False))
CONFIGS = {"default": DEFAULT, "paper": paper_config()}
INJECT = 100  # epoch index (t = 20 s) at which bad input is injected, after the initial convergence


@pytest.fixture(scope="module")
def sequence() -> EpochArrays:
    """60 s of the standard scenario (2 m/s, +-15 deg sine steer, 5 Hz GNSS, default sensor noise), seed 0."""
    _, epochs = simulate_epochs(SimConfig(duration=60.0, seed=0))
    assert len(epochs) == 300
    return epochs


@pytest.fixture(scope="module")
def clean_rows(sequence) -> np.ndarray:
    return run_sequence(DEFAULT, sequence)


def row(estimate: Estimate) -> np.ndarray:
    """An Estimate's kernel output row, checked against its named fields."""
    values = [int(estimate.status), estimate.lateral_velocity, estimate.yaw_rate,
              estimate.cornering_stiffness_front, estimate.cornering_stiffness_rear,
              estimate.cornering_stiffness_front_std, estimate.cornering_stiffness_rear_std,
              estimate.lateral_velocity_model, estimate.yaw_rate_model, *estimate.innovation,
              *estimate.innovation_covariance, estimate.normalized_innovation_squared]
    assert len(estimate.row) == N_OUTPUTS
    np.testing.assert_array_equal(np.array(estimate.row[:len(values)]), np.array(values, dtype=np.float64))
    return np.array(estimate.row, dtype=np.float64)


def step_all(ekf: JointEKF, epochs: list[Epoch]) -> np.ndarray:
    rows = []
    for epoch in epochs:
        estimate = ekf.step(epoch)
        rows.append(row(estimate))
        assert np.all(np.isfinite(rows[-1])), f"non-finite output at t={epoch.t}: {estimate}"
        assert np.all(np.isfinite(ekf.state)) and np.all(np.isfinite(ekf.covariance))
    return np.array(rows)


def epoch_list(epochs: EpochArrays) -> list[Epoch]:
    return [epochs[i] for i in range(len(epochs))]


# --------------------------------------------------------------------------- online == offline


@pytest.mark.parametrize("name", list(CONFIGS))
def test_step_by_step_equals_run_sequence(sequence, name):
    config = CONFIGS[name]
    offline = run_sequence(config, sequence)
    online = step_all(JointEKF(config), epoch_list(sequence))
    np.testing.assert_array_equal(online, offline)
    assert np.all(np.isfinite(offline))
    statuses = np.bincount(offline[:, O_STATUS].astype(int), minlength=len(StepStatus))
    assert statuses[StepStatus.INITIALISED] == 1
    assert statuses[StepStatus.UPDATED] >= 290


def test_objective_is_the_mean_absolute_innovation(sequence, clean_rows):
    """sequence_objective('mae') is eq. (21) over the epochs with a prediction (UPDATED, GATED, NONLINEAR).

    Over one pass: the tuner's objective takes no re-linearised pass (ekf/relinearization.py).
    """
    options = dataclasses.replace(DEFAULT.options, relinearization_window=0.0)
    one_pass = run_sequence(dataclasses.replace(DEFAULT, options=options), sequence)
    predicted = np.isin(one_pass[:, O_STATUS], [StepStatus.UPDATED, StepStatus.GATED, StepStatus.NONLINEAR])
    expected = np.mean(np.abs(one_pass[predicted, O_E0]) + np.abs(one_pass[predicted, O_E1]))
    assert sequence_objective(DEFAULT, sequence, "mae") == pytest.approx(expected, rel=1e-12)
    assert math.isfinite(sequence_objective(DEFAULT, sequence, "nll"))


# --------------------------------------------------------------------------- bad numbers (DESIGN.md section 6)


FILTER_FIELDS = ("t", "antenna_lateral_velocity", "heading", "yaw_rate", "steering", "steering_rate", "speed")


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("field", FILTER_FIELDS)
def test_non_finite_epoch_is_rejected_and_changes_nothing(sequence, clean_rows, field, value):
    """REJECTED_INVALID, state untouched, outputs finite; the rest of the run is bit-identical to the clean run."""
    epochs = epoch_list(sequence)
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    state, covariance = ekf.state.copy(), ekf.covariance.copy()
    estimate = ekf.step(dataclasses.replace(epochs[INJECT], **{field: value}))
    assert estimate.status is StepStatus.REJECTED_INVALID
    assert not estimate.status.stiffness_updated
    assert np.all(np.isfinite(row(estimate)))
    np.testing.assert_array_equal(ekf.state, state)
    np.testing.assert_array_equal(ekf.covariance, covariance)
    # the published stiffness is the last one
    assert estimate.cornering_stiffness_front == clean_rows[INJECT - 1, O_CF]
    np.testing.assert_array_equal(step_all(ekf, epochs[INJECT:]), clean_rows[INJECT:])


def test_non_finite_longitudinal_velocity_is_not_used_by_the_filter(sequence, clean_rows):
    """The filter's input is the interval-mean ``speed``; vx at t_k only travels with the epoch."""
    epochs = epoch_list(sequence)
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    estimate = ekf.step(dataclasses.replace(epochs[INJECT], longitudinal_velocity=math.nan))
    np.testing.assert_array_equal(row(estimate), clean_rows[INJECT])


@pytest.mark.parametrize("kind", ["reversed", "duplicate"])
def test_stale_stamp_is_rejected_and_changes_nothing(sequence, clean_rows, kind):
    epochs = epoch_list(sequence)
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    state = ekf.state.copy()
    previous_t = epochs[INJECT - 1].t
    stamp = previous_t - 0.1 if kind == "reversed" else previous_t
    estimate = ekf.step(dataclasses.replace(epochs[INJECT], t=stamp))
    assert estimate.status is StepStatus.REJECTED_STAMP
    assert np.all(np.isfinite(row(estimate)))
    np.testing.assert_array_equal(ekf.state, state)
    np.testing.assert_array_equal(step_all(ekf, epochs[INJECT:]), clean_rows[INJECT:])


def assert_recovers(ekf: JointEKF, rest: list[Epoch], clean_rows: np.ndarray) -> None:
    """After a disturbance the filter carries on updating and ends close to the truth.

    Within 3 % of the truth and 1.5 % of the undisturbed run (whose own final errors are +0.4 % / +0.2 %
    on this seed).
    """
    rows = step_all(ekf, rest)
    assert np.all(np.isin(rows[1:, O_STATUS], [StepStatus.UPDATED, StepStatus.NONLINEAR]))
    final = rows[-1]
    assert final[O_CF] == pytest.approx(TRUE_CF, rel=0.03)
    assert final[O_CR] == pytest.approx(TRUE_CR, rel=0.03)
    assert final[O_CF] == pytest.approx(clean_rows[-1, O_CF], rel=0.015)
    assert final[O_CR] == pytest.approx(clean_rows[-1, O_CR], rel=0.015)


@pytest.mark.parametrize(("speed", "status"), [(0.1, StepStatus.LOW_SPEED), (0.0, StepStatus.LOW_SPEED),
                                               (-0.1, StepStatus.LOW_SPEED), (-1.0, StepStatus.REVERSING),
                                               (-0.3, StepStatus.REVERSING)])
def test_slow_or_reversing_epoch_holds_the_stiffness(sequence, clean_rows, speed, status):
    """|vx| < min_speed (0.3 m/s): LOW_SPEED; vx <= -min_speed: REVERSING.

    Motion states follow the measurement, stiffness and its variance are held, and the filter continues.
    """
    epochs = epoch_list(sequence)
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    stiffness, variance = ekf.state[STIFFNESS].copy(), np.diag(ekf.covariance)[STIFFNESS].copy()
    slow = dataclasses.replace(epochs[INJECT], speed=speed)
    estimate = ekf.step(slow)
    assert estimate.status is status
    assert np.all(np.isfinite(row(estimate)))
    np.testing.assert_array_equal(ekf.state[STIFFNESS], stiffness)
    np.testing.assert_array_equal(np.diag(ekf.covariance)[STIFFNESS], variance)
    assert ekf.state[0] == slow.lateral_velocity and ekf.state[1] == slow.yaw_rate and ekf.state[2] == slow.heading
    assert_recovers(ekf, epochs[INJECT + 1:], clean_rows)


def test_gap_reinitialises_the_motion_states(sequence, clean_rows):
    """No epoch for 3 s (> max_interval = 2 s): GAP, stiffness held, then the filter continues."""
    epochs = epoch_list(sequence)
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    stiffness = ekf.state[STIFFNESS].copy()
    after_gap = INJECT + 15  # 3 s later at 5 Hz
    assert epochs[after_gap].t - epochs[INJECT - 1].t > DEFAULT.options.max_interval
    estimate = ekf.step(epochs[after_gap])
    assert estimate.status is StepStatus.GAP
    np.testing.assert_array_equal(ekf.state[STIFFNESS], stiffness)
    assert ekf.state[0] == epochs[after_gap].lateral_velocity
    assert_recovers(ekf, epochs[after_gap + 1:], clean_rows)


def test_run_sequence_handles_bad_epochs_like_step(sequence):
    """A sequence salted with every kind of bad epoch: the kernel loop gives the same rows as stepping."""
    epochs = epoch_list(sequence)
    salted = list(epochs[:50])
    salted.append(dataclasses.replace(epochs[50], antenna_lateral_velocity=math.nan))
    salted.append(dataclasses.replace(epochs[50], heading=math.inf))
    salted.append(dataclasses.replace(epochs[50], t=epochs[49].t))
    salted.append(dataclasses.replace(epochs[50], speed=-1.0))
    salted.append(dataclasses.replace(epochs[51], speed=0.05))
    salted.extend(epochs[52:80])
    salted.extend(epochs[95:])  # a 3 s gap
    rows = run_sequence(DEFAULT, EpochArrays(salted))
    np.testing.assert_array_equal(step_all(JointEKF(DEFAULT), salted), rows)
    assert np.all(np.isfinite(rows))
    assert list(rows[50:56, O_STATUS]) == [StepStatus.REJECTED_INVALID, StepStatus.REJECTED_INVALID,
                                           StepStatus.REJECTED_STAMP, StepStatus.REVERSING, StepStatus.LOW_SPEED,
                                           StepStatus.UPDATED]
    assert rows[83, O_STATUS] == StepStatus.GAP  # epochs[95] after epochs[79]: 3.2 s


# --------------------------------------------------------------------------- innovation gate


def test_outlier_is_gated_and_does_not_move_the_stiffness(sequence, clean_rows):
    """A 1 m/s vy outlier (50 sigma of R) is GATED: the stiffness (and its output) stays bit-identical."""
    epochs = epoch_list(sequence)
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    stiffness = ekf.state[STIFFNESS].copy()
    estimate = ekf.step(outlier(epochs[INJECT]))
    assert estimate.status is StepStatus.GATED
    assert estimate.normalized_innovation_squared > DEFAULT.options.gate_threshold
    np.testing.assert_array_equal(ekf.state[STIFFNESS], stiffness)
    assert estimate.cornering_stiffness_front == clean_rows[INJECT - 1, O_CF]
    assert estimate.cornering_stiffness_rear == clean_rows[INJECT - 1, O_CR]
    assert_recovers(ekf, epochs[INJECT + 1:], clean_rows)


def outlier(epoch: Epoch) -> Epoch:
    """The epoch with a 1 m/s error in the measured lateral velocity (50 sigma of R)."""
    return dataclasses.replace(epoch, antenna_lateral_velocity=epoch.antenna_lateral_velocity + 1.0)


def test_repeatedly_gated_measurement_reinitialises_the_motion_and_never_moves_the_stiffness(sequence):
    """max_gated epochs in a row fail the gate: the last one re-initialises the motion states.

    The motion states come from the measurement (REINITIALISED); no stiffness update is forced through.
    """
    epochs = epoch_list(sequence)
    max_gated = DEFAULT.options.max_gated
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    stiffness = ekf.state[STIFFNESS].copy()
    statuses = [ekf.step(outlier(epochs[k])).status for k in range(INJECT, INJECT + max_gated)]
    assert statuses == [StepStatus.GATED] * (max_gated - 1) + [StepStatus.REINITIALISED]
    np.testing.assert_array_equal(ekf.state[STIFFNESS], stiffness)
    assert ekf.state[0] == outlier(epochs[INJECT + max_gated - 1]).antenna_lateral_velocity
    # a good epoch in between restarts the count
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    statuses = []
    for k in range(INJECT, INJECT + 2 * max_gated):
        statuses.append(ekf.step(epochs[k] if k == INJECT + max_gated - 2 else outlier(epochs[k])).status)
    assert statuses[: max_gated - 2] == [StepStatus.GATED] * (max_gated - 2)
    assert statuses[max_gated - 2] is StepStatus.UPDATED
    # the count restarts after a re-initialisation too
    assert statuses[max_gated - 1:] == [StepStatus.GATED] * (max_gated - 1) + [StepStatus.REINITIALISED,
                                                                               StepStatus.GATED]


# --------------------------------------------------------------------------- the update itself


@pytest.mark.parametrize("name", list(CONFIGS))
def test_update_is_the_textbook_kalman_update(sequence, name):
    """One step = P- = F P F^T + Q dt + speed terms; K = P- H^T S^-1; x+ = x- + K (z - H x-); P+ = (I - K H) P- (rel 1e-9).

    F and x- come from ekf.predict (tested against finite differences in test_model.py); the rest is
    numpy. This checks eq. (12) and the Joseph form (including its K R K^T term) in the kernel. The
    speed terms: the interval's speed error e = (n_prev + n) / 2 of two GNSS samples of variance var,
    P- += g (var / 2) g^T + (F c g^T + g c^T F^T) / 2 with c = Cov(state error, n_prev) the filter
    kept from the previous step; after the step it keeps c = (I - K H) g var / 2.
    """
    config = CONFIGS[name]
    arrays = FilterArrays.from_config(config)
    heading = config.options.measurement == "heading"
    epochs = epoch_list(sequence)
    ekf = JointEKF(config)
    step_all(ekf, epochs[:INJECT - 1])
    factors = np.array(ekf.step(epochs[INJECT - 1]).row)[[O_NOISE_SCALE_VY, O_NOISE_SCALE_SECOND]]
    x, p = ekf.state.copy(), ekf.covariance.copy()
    epoch = epochs[INJECT]
    x_pred, model, ws = x.copy(), np.zeros(N_MODEL), work_buffer()
    # the model runs at the vehicle's forward speed: the measured one turned back by h (measurement_row.body_speed)
    misalignment, ax = x[X_HEADING_OFFSET], config.vehicle.antenna_x
    body_speed = (epoch.speed - math.sin(misalignment) * (x[0] + ax * x[1])) / math.cos(misalignment)
    predict(x_pred, model, arrays.vehicle, arrays.settings, epoch.t - epochs[INJECT - 1].t, body_speed,
            epoch.steering, epoch.steering_rate, ws)
    n = len(x)
    jac = ws[W_F, :n, :n].copy()
    dt = epoch.t - epochs[INJECT - 1].t
    p_pred = jac @ p @ jac.T + np.diag(arrays.process_noise) * dt  # Q is a density
    gain_v, variance = np.zeros(n), arrays.measurement_noise[0] * factors[0]  # one speed sample's: R_v
    if config.options.speed_noise:
        gain_v[: n - 4] = ws[W_VEC, V_SPEED_GAIN, : n - 4]  # the motion states (not theta_f, theta_r, b, h)
        cross = jac @ ekf._memo[M_SPEED_CROSS:M_SPEED_CROSS + n]  # the filter's memory: no public view
        p_pred += 0.5 * variance * np.outer(gain_v, gain_v) + 0.5 * (np.outer(cross, gain_v) + np.outer(gain_v, cross))
    # z_vy = (vy + antenna_x r) / cos h - vx tan h, the lever arm and the heading's misalignment h
    vx = epoch.speed
    antenna_vy = x_pred[0] + ax * x_pred[1]
    secant, tangent = 1.0 / math.cos(misalignment), math.tan(misalignment)
    h = np.zeros((2, n))
    h[0, 0], h[0, 1] = secant, ax * secant
    h[0, X_HEADING_OFFSET] = antenna_vy * tangent * secant - vx * secant ** 2
    h[1, 2 if heading else 1] = 1.0
    predicted = np.array([antenna_vy * secant - vx * tangent, x_pred[2 if heading else 1]])
    z = np.array([epoch.antenna_lateral_velocity, epoch.heading if heading else epoch.yaw_rate])
    innovation = z - predicted
    r_v, r_2 = arrays.measurement_noise * factors  # R as the innovations showed it (1 with noise_adaptation off)
    # vy is the GNSS velocity turned by the measured heading: its error holds -vx e_psi (heading mode)
    r_full = np.array([[r_v + vx * vx * r_2, -vx * r_2], [-vx * r_2, r_2]]) if heading else np.diag([r_v, r_2])
    s = h @ p_pred @ h.T + r_full
    gain = p_pred @ h.T @ np.linalg.inv(s)
    x_new = x_pred + gain @ innovation
    p_new = (np.eye(n) - gain @ h) @ p_pred
    estimate = ekf.step(epoch)
    assert estimate.status is StepStatus.UPDATED
    np.testing.assert_allclose(estimate.innovation, innovation, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(estimate.innovation_covariance, [s[0, 0], s[0, 1], s[1, 1]], rtol=1e-9)
    assert estimate.normalized_innovation_squared == pytest.approx(innovation @ np.linalg.solve(s, innovation),
                                                                   rel=1e-9)
    np.testing.assert_allclose(ekf.state, x_new, rtol=1e-9, atol=1e-12)
    scale = np.sqrt(np.outer(np.diag(p_new), np.diag(p_new)))
    scale = np.where(scale > 0.0, scale, 1.0)  # a fixed steering offset has no variance
    np.testing.assert_allclose(ekf.covariance / scale, p_new / scale, rtol=0.0, atol=1e-9)
    kept = (np.eye(n) - gain @ h) @ gain_v * 0.5 * variance
    np.testing.assert_allclose(ekf._memo[M_SPEED_CROSS:M_SPEED_CROSS + n], kept, rtol=1e-9, atol=1e-15)
    assert np.any(kept != 0.0) == config.options.speed_noise


# --------------------------------------------------------------------------- covariance


@pytest.mark.parametrize("name", list(CONFIGS))
def test_covariance_stays_symmetric_positive_semidefinite(name):
    """120 s, step by step: P == P^T exactly and min eig(P) >= -1e-12 * max eig(P) after every epoch."""
    _, epochs = simulate_epochs(SimConfig(duration=120.0, seed=3))
    ekf = JointEKF(CONFIGS[name])
    for epoch in epoch_list(epochs):
        ekf.step(epoch)
        p = ekf.covariance
        np.testing.assert_array_equal(p, p.T)
        eig = np.linalg.eigvalsh(p)
        assert eig[0] >= -1e-12 * eig[-1], f"t={epoch.t}: eigenvalues {eig}"
        estimated = FilterArrays.from_config(CONFIGS[name]).initial_covariance.diagonal() > 0.0  # a fixed b or h: 0
        assert np.all(np.diag(p)[estimated] > 0.0) and np.all(np.diag(p)[~estimated] == 0.0)


# --------------------------------------------------------------------------- run-time changes


def test_set_noise_keeps_the_state_and_changes_q_and_r():
    """A new R restarts the learned factors on R, so S changes by exactly the new Q dt and R.

    The heading is twice as noisy as the default R says, so that its innovations have raised R by then.
    """
    noisy = SensorNoise(heading=2.0 * SensorNoise().heading)
    epochs = epoch_list(simulate_epochs(SimConfig(duration=30.0, seed=0, noise=noisy))[1])
    base = DEFAULT.noise
    new_r = dataclasses.replace(base, measurement_noise=(9.0e-4, 4.0e-5))
    new_q = dataclasses.replace(base, process_noise=(4.0e-4, 3.0e-4, 1.0e-6, 1.0e-6))
    for noise in (new_r, new_q):
        changed, reference = JointEKF(DEFAULT), JointEKF(DEFAULT)
        step_all(changed, epochs[:INJECT])
        step_all(reference, epochs[:INJECT - 1])
        factors = np.array(reference.step(epochs[INJECT - 1]).row)[[O_NOISE_SCALE_VY, O_NOISE_SCALE_SECOND]]
        assert factors[1] > 1.0  # the heading's innovations have raised R (else the restart is not tested)
        changed.set_noise(noise)
        assert changed.config.noise == noise
        np.testing.assert_array_equal(changed.state, reference.state)
        np.testing.assert_array_equal(changed.covariance, reference.covariance)
        ws, arrays, epoch = work_buffer(), FilterArrays.from_config(DEFAULT), epochs[INJECT]
        x = reference.state
        body_speed = (epoch.speed - math.sin(x[X_HEADING_OFFSET]) * x[0]) / math.cos(x[X_HEADING_OFFSET])  # antenna_x 0
        predict(x.copy(), np.zeros(N_MODEL), arrays.vehicle, arrays.settings, epoch.t - epochs[INJECT - 1].t,
                body_speed, epoch.steering, epoch.steering_rate, ws)
        g_vy, g_psi = ws[W_VEC, V_SPEED_GAIN, 0], ws[W_VEC, V_SPEED_GAIN, 2]  # dx/dvx: the speed's noise in Q
        secant = 1.0 / math.cos(reference.state[X_HEADING_OFFSET])  # H's vy entry (measurement_row.py); h's prior
        a, b = changed.step(epochs[INJECT]), reference.step(epochs[INJECT])
        assert a.status is b.status is StepStatus.UPDATED
        # S = F P F^T + Q dt + R on the measured states (vy, psi): the difference is exactly the change
        (s00_a, s01_a, s11_a), (s00_b, s01_b, s11_b) = a.innovation_covariance, b.innovation_covariance
        d_q = np.array(noise.process_noise) - np.array(base.process_noise)
        # a new R restarts the factors on it (1 for the changed filter), the same R keeps them
        kept = factors if noise.measurement_noise == base.measurement_noise else np.ones(2)
        d_r = np.array(noise.measurement_noise) * kept - np.array(base.measurement_noise) * factors
        dt = epochs[INJECT].t - epochs[INJECT - 1].t
        vx = epochs[INJECT].speed  # vy's error holds -vx e_psi: R_psi enters S00 and S01 too
        d_speed = 0.5 * d_r[0]  # the speed's variance is half R_v's (a two-sample mean), through dx/dvx
        assert s00_a - s00_b == pytest.approx(secant ** 2 * (d_q[0] * dt + g_vy * g_vy * d_speed) + d_r[0]
                                              + vx * vx * d_r[1], rel=1e-9, abs=1e-15)
        assert s11_a - s11_b == pytest.approx(d_r[1] + g_psi * g_psi * d_speed, rel=1e-9, abs=1e-15)  # psi's Q kept
        print("S01", s01_a, s01_b, g_vy, g_psi, d_speed, secant, vx, d_r)
        assert s01_a - s01_b == pytest.approx(-vx * d_r[1] + secant * g_vy * g_psi * d_speed, rel=1e-9, abs=1e-15)
        assert a.cornering_stiffness_front != b.cornering_stiffness_front


def test_reset_restores_the_initial_state(sequence):
    epochs = epoch_list(sequence)
    fresh = JointEKF(DEFAULT)
    initial_state, initial_covariance = fresh.state.copy(), fresh.covariance.copy()
    assert initial_state[STIFFNESS] == pytest.approx(np.log(DEFAULT.noise.initial_stiffness), rel=1e-15)
    assert initial_state[X_OFFSET] == DEFAULT.vehicle.steering_offset
    first = step_all(fresh, epochs[:60])
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    ekf.reset()
    np.testing.assert_array_equal(ekf.state, initial_state)
    np.testing.assert_array_equal(ekf.covariance, initial_covariance)
    # the whole memory is reset: the next epoch initialises, and the run repeats the fresh one
    np.testing.assert_array_equal(step_all(ekf, epochs[:60]), first)
    # after set_noise, reset starts from the new initial covariance
    noise = NoiseParams(initial_covariance=(1.0e-2, 1.0e-2, 1.0, 2.0))
    ekf.set_noise(noise)
    ekf.reset()
    assert np.diag(ekf.covariance)[STIFFNESS] == pytest.approx([1.0, 2.0])


@pytest.mark.parametrize("array", ["memo", "model", "q", "out", "ws"])
def test_a_wrong_array_size_raises_instead_of_corrupting_memory(array: str) -> None:
    """The compiled step does not bounds-check; the entry point checks every shape first."""
    a = FilterArrays.from_config(DEFAULT)
    args = {"memo": np.zeros(N_MEMO), "model": np.zeros(N_MODEL), "q": a.process_noise.copy(),
            "out": np.zeros(N_OUTPUTS), "ws": work_buffer()}
    args[array] = args[array][..., :-1].copy()  # one entry short
    with pytest.raises(ValueError, match=array):
        ekf_step(a.initial_state.copy(), a.initial_covariance.copy(), args["model"], args["memo"], a.vehicle,
                 a.settings, args["q"], a.measurement_noise, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0, args["ws"],
                 args["out"])


def test_a_lasting_clock_step_back_restarts_the_motion_and_the_filter_carries_on(sequence, clean_rows):
    """Epochs stamped 10 s earlier from some point on (a clock stepped back) restart the motion.

    Beyond max_interval back the step is a GAP (motion re-initialised, stiffness kept); a small
    step back is still REJECTED_STAMP.
    """
    epochs = epoch_list(sequence)
    ekf = JointEKF(DEFAULT)
    step_all(ekf, epochs[:INJECT])
    assert ekf.step(dataclasses.replace(epochs[INJECT], t=epochs[INJECT - 1].t - 0.5)).status \
        is StepStatus.REJECTED_STAMP
    stiffness = ekf.state[STIFFNESS].copy()
    shifted = [dataclasses.replace(e, t=e.t - 10.0) for e in epochs[INJECT:]]
    assert ekf.step(shifted[0]).status is StepStatus.GAP
    np.testing.assert_array_equal(ekf.state[STIFFNESS], stiffness)
    assert_recovers(ekf, shifted[1:], clean_rows)
