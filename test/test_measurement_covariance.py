"""R from the messages' covariance (issue #12 item 5): ``ekf.measurement_noise_from_covariance``.

A GNSS receiver knows when its fix degrades (RTK fixed to float) and says so in the covariance of
its velocity and heading messages. With the option on, each epoch's R is the reported variance
wherever it exceeds the configured R (the configured R is the floor); without a report the
configured R applies. The pieces are tested against the obvious rule; the whole through real MCAP
bags in a driver's types, over 10 seeds, on a drive whose GNSS noise is 3x larger for 40 s.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from transplanter_ident.bags import SimBagOptions, read_bag, reading_parameters, write_sim_bag
from transplanter_ident.bags.messages import IMU, ODOMETRY, POSE_COV_STAMPED, TYPESTORE, decode_message
from transplanter_ident.config.params_file import flat_to_params
from transplanter_ident.ekf.joint_ekf import FilterArrays, JointEKF, run_sequence
from transplanter_ident.ekf.layout import (
    O_CF,
    O_CF_STD,
    O_CR,
    O_CR_STD,
    S_HEADING,
    S_R_FROM_COVARIANCE,
    Z_SECOND,
    Z_VY,
)
from transplanter_ident.ekf.sequence import epoch_measurement_noise
from transplanter_ident.epochs.assembler import AssemblerSettings, EpochAssembler
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.simulator import simulate

SEEDS = range(10)
DEGRADED = (40.0, 80.0, 3.0)  # s, s, noise factor: an RTK fix lost for 40 s
DRIVER = SimBagOptions(velocity_type="twist-cov", heading_type="imu", report_noise=True)


def obvious_noise(configured: tuple[float, float], on: bool, heading: bool,
                  reported: tuple[float, float, float]) -> tuple[float, float]:
    """The rule written out: with the option, the larger of configured and reported (0 or NaN: no report)."""
    if not on:
        return configured
    velocity, heading_variance, yaw_rate_variance = reported
    second = heading_variance if heading else yaw_rate_variance
    pick = [c if math.isnan(r) or r <= c else r for c, r in zip(configured, (velocity, second), strict=True)]
    return pick[0], pick[1]


@pytest.mark.parametrize("heading", [True, False])
@pytest.mark.parametrize("on", [True, False])
def test_epoch_noise_is_the_reported_variance_floored_by_the_configured_r(on: bool, heading: bool) -> None:
    params = flat_to_params({"ekf.measurement_noise_from_covariance": on,
                             "ekf.measurement": "heading" if heading else "yaw_rate"})
    arrays = FilterArrays.from_config(params.config)
    configured = (float(arrays.measurement_noise[Z_VY]), float(arrays.measurement_noise[Z_SECOND]))
    values = (math.nan, 0.0, 1e-9, configured[0], 4e-4, 1e-2, 3e-5, 1.0)
    rng = np.random.default_rng(3)
    for _ in range(200):
        reported = tuple(float(v) for v in rng.choice(values, 3))
        r_epoch = np.zeros(2)
        epoch_measurement_noise(arrays.measurement_noise, arrays.settings[S_R_FROM_COVARIANCE] > 0.5,
                                arrays.settings[S_HEADING] > 0.5,
                                *reported, r_epoch)
        assert tuple(r_epoch) == obvious_noise(configured, on, heading, reported), reported


def test_the_assembler_turns_the_reported_covariance_into_the_epochs_variances() -> None:
    yaw, variance_east, variance_north, heading_variance = 0.6, 4e-4, 9e-4, 2e-5
    for frame in ("enu", "ned"):
        assembler = EpochAssembler(AssemblerSettings(velocity_frame=frame))
        given = (variance_east, variance_north) if frame == "enu" else (variance_north, variance_east)
        epochs = []
        for k in range(4):
            t = 0.2 * k
            epochs += assembler.add_steering(t, 0.0)
            epochs += assembler.add_velocity(t, 1.0, 0.5, *given)
            epochs += assembler.add_heading(t, yaw, heading_variance)
        epochs += assembler.add_steering(0.8, 0.0)
        assert len(epochs) == 3, assembler.drain_rejections()
        expected_vy = math.sin(yaw) ** 2 * variance_east + math.cos(yaw) ** 2 * variance_north
        for epoch in epochs:
            assert epoch.velocity_variance == pytest.approx(expected_vy, rel=1e-12)
            assert epoch.heading_variance == heading_variance
            assert epoch.yaw_rate_variance == pytest.approx(2.0 * heading_variance / 0.2**2, rel=1e-9)
    assembler = EpochAssembler(AssemblerSettings())  # zero covariance: unknown, as in ROS
    epochs = []
    for k in range(3):
        epochs += assembler.add_steering(0.2 * k, 0.0)
        epochs += assembler.add_velocity(0.2 * k, 1.0, 0.5, 0.0, 0.0)
        epochs += assembler.add_heading_quaternion(0.2 * k, 0.0, 0.0, 0.0, 1.0)
    assert epochs and all(e.velocity_variance == e.heading_variance == e.yaw_rate_variance == 0.0 for e in epochs)


@pytest.mark.parametrize(("heading_type", "msgtype"), [("imu", IMU), ("pose-cov", POSE_COV_STAMPED),
                                                       ("odometry", ODOMETRY)])
def test_every_heading_type_with_a_covariance_reports_its_yaw_variance(tmp_path: Path, heading_type: str,
                                                                        msgtype: str) -> None:
    from rosbags.highlevel import AnyReader

    result = simulate(build_config("sine", duration=4.0, seed=1))
    write_sim_bag(result, tmp_path / "b", SimBagOptions(heading_type=heading_type, report_noise=True))
    with AnyReader([tmp_path / "b"], default_typestore=TYPESTORE) as reader:
        connection = next(c for c in reader.connections if c.topic == "/gnss/heading")
        rows = [decode_message(msgtype, raw, ns, role="heading") for _, ns, raw in reader.messages([connection])]
    assert len(rows) == len(result.gnss_time)
    assert [values[4] for _, values in rows] == pytest.approx(np.asarray(result.heading_std) ** 2, rel=1e-12)


def run_degraded(seed: int, tmp_path: Path, on: bool) -> dict[str, float]:
    """One seed through a real bag: errors in the degraded window and at the end, and the +-2 sigma coverage."""
    bag = tmp_path / f"s{seed}"
    if not bag.exists():
        write_sim_bag(simulate(replace(build_config("sine", duration=120.0, seed=seed), gnss_degraded=DEGRADED)),
                      bag, DRIVER)
    params = flat_to_params({**reading_parameters(DRIVER), "ekf.measurement_noise_from_covariance": on})
    data = read_bag(bag, params)
    out = run_sequence(params.config, data.epochs)
    if seed == 0:  # the node's step takes R per epoch as the sequence kernel does
        ekf = JointEKF(params.config)
        assert np.array_equal(np.array([ekf.step(data.epochs[k]).row for k in range(len(data.epochs))]), out)
    true_cf, true_cr = data.truth.at(data.epochs.t)
    t = data.epochs.t - data.epochs.t[0]
    window, late = (t >= DEGRADED[0]) & (t < DEGRADED[1]), t >= 30.0
    error = np.maximum(np.abs(out[:, O_CF] / true_cf - 1.0), np.abs(out[:, O_CR] / true_cr - 1.0))
    front = np.abs(out[:, O_CF] - true_cf) <= 2.0 * out[:, O_CF_STD]
    rear = np.abs(out[:, O_CR] - true_cr) <= 2.0 * out[:, O_CR_STD]
    return {"window": float(np.max(error[window])), "final": float(error[-1]),
            "front": float(np.sum(front[late])), "rear": float(np.sum(rear[late])), "epochs": float(np.sum(late))}


def test_a_degraded_fix_reported_in_the_covariance_does_not_corrupt_the_stiffness(tmp_path: Path) -> None:
    """GNSS noise 3x for 40 s, said in the messages: off, the filter trusts it and the stiffness runs away."""
    runs = {on: [run_degraded(seed, tmp_path, on) for seed in SEEDS] for on in (False, True)}
    figures = {}
    for on, rows in runs.items():
        window = [r["window"] for r in rows]
        final = [r["final"] for r in rows]
        epochs = sum(r["epochs"] for r in rows)
        coverage = min(sum(r["front"] for r in rows) / epochs, sum(r["rear"] for r in rows) / epochs)
        figures[on] = (np.median(window), max(window), np.median(final), max(final), coverage)
        print(f"\nR from covariance {'on' if on else 'off'} ({len(rows)} seeds): worst error in the window median "
              f"{100 * figures[on][0]:.1f} %, worst {100 * figures[on][1]:.1f} %; final median {100 * figures[on][2]:.2f} "
              f"%, worst {100 * figures[on][3]:.2f} %; +-2 sigma covers Cf and Cr after 30 s, the lower: {coverage:.3f}")
    # the scenario matters: without the option the stiffness runs away (ekf.noise_adaptation, whose memory
    # is a minute, halves the excursion of a 40 s degradation but cannot follow it)
    assert figures[False][0] > 0.3
    window_median, window_worst, final_median, final_worst, coverage = figures[True]
    assert window_median <= 0.08 and window_worst <= 0.30
    assert final_median <= 0.03 and final_worst <= 0.06
    assert coverage >= 0.90


def test_without_a_reported_covariance_the_option_changes_nothing(tmp_path: Path) -> None:
    plain = SimBagOptions()  # TwistStamped and QuaternionStamped carry no covariance
    write_sim_bag(simulate(build_config("sine", duration=30.0, seed=2)), tmp_path / "b", plain)
    outputs = []
    for on in (False, True):
        params = flat_to_params({**reading_parameters(plain), "ekf.measurement_noise_from_covariance": on})
        data = read_bag(tmp_path / "b", params)
        outputs.append(run_sequence(params.config, data.epochs))
        ekf = JointEKF(params.config)  # the node's step: the same numbers as the sequence kernel
        online = np.array([ekf.step(data.epochs[k]).row for k in range(len(data.epochs))])
        assert np.array_equal(online, outputs[-1])
    assert np.array_equal(outputs[0], outputs[1])
