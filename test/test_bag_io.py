"""Bag I/O (transplanter_ident.bags): real MCAP bags written and read with rosbags and mcap, no mocks."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

import transplanter_ident.bags as bag_io
from transplanter_ident.bags import (
    BagError,
    BagWriter,
    SimBagOptions,
    decode_message,
    read_bag,
    read_epochs,
    read_samples,
    read_truth,
    summarize_rejections,
    write_output_bag,
    write_sim_bag,
    yaw_quaternion,
)
from transplanter_ident.config.params_file import EstimatorParams, FrameConfig, SteeringConfig, TopicConfig
from transplanter_ident.ekf.layout import N_OUTPUTS
from transplanter_ident.epochs.epoch import Rejection
from transplanter_ident.epochs.frames import quaternion_yaw
from transplanter_ident.sim.scenarios import build_config
from transplanter_ident.sim.simulator import simulate

TS = bag_io.TYPESTORE
T = TS.types


@pytest.fixture(scope="module")
def sim_result():
    return simulate(build_config("sine", duration=30.0, seed=3))


def epoch_matrix(epochs) -> np.ndarray:
    return np.column_stack([epochs.t, epochs.longitudinal_velocity, epochs.lateral_velocity, epochs.heading,
                            epochs.yaw_rate, epochs.steering, epochs.steering_rate, epochs.speed])


# --------------------------------------------------------------------------- decoding


def _header(sec: int, nanosec: int, frame_id: str):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                    frame_id=frame_id)


def _messages(frame_id: str, rng: np.random.Generator, joint_names: list[str]):
    v3 = T["geometry_msgs/msg/Vector3"]
    quat = T["geometry_msgs/msg/Quaternion"]
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    lin = v3(x=float(rng.normal()), y=float(rng.normal()), z=float(rng.normal()))
    ang = v3(x=float(rng.normal()), y=float(rng.normal()), z=float(rng.normal()))
    twist = T["geometry_msgs/msg/Twist"](linear=lin, angular=ang)
    head = _header(1_700_000_123, 456_789_012, frame_id)
    positions = rng.normal(size=len(joint_names))
    empty = np.zeros(0)
    covariance = rng.normal(size=36)
    twist_cov = T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=covariance)
    point = T["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=3.0)
    pose_covariance, orientation_covariance = rng.normal(size=36), rng.normal(size=9)
    pose_cov = T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](
        position=point, orientation=quat(*q)), covariance=pose_covariance)
    return {
        bag_io.TWIST_STAMPED: (T[bag_io.TWIST_STAMPED](header=head, twist=twist), (lin.x, lin.y)),
        bag_io.TWIST_COV_STAMPED: (T[bag_io.TWIST_COV_STAMPED](header=head, twist=twist_cov),
                                   (lin.x, lin.y, covariance[0], covariance[7])),
        bag_io.ODOMETRY: (T[bag_io.ODOMETRY](header=head, child_frame_id="base_link", pose=pose_cov, twist=twist_cov),
                          (lin.x, lin.y, covariance[0], covariance[7])),
        bag_io.POSE_COV_STAMPED: (T[bag_io.POSE_COV_STAMPED](header=head, pose=pose_cov), (*q, pose_covariance[35])),
        bag_io.QUATERNION_STAMPED: (T[bag_io.QUATERNION_STAMPED](header=head, quaternion=quat(*q)), tuple(q)),
        bag_io.IMU: (T[bag_io.IMU](header=head, orientation=quat(*q), orientation_covariance=orientation_covariance,
                                   angular_velocity=ang, angular_velocity_covariance=np.zeros(9),
                                   linear_acceleration=lin, linear_acceleration_covariance=np.zeros(9)),
                     (*q, orientation_covariance[8])),  # the yaw variance rides along (issue #12 item 5)
        bag_io.JOINT_STATE: (T[bag_io.JOINT_STATE](header=head, name=joint_names, position=positions,
                                                   velocity=positions * 2, effort=empty),
                             (float(positions[joint_names.index("front_steering")]),)),
        bag_io.FLOAT64: (T[bag_io.FLOAT64](data=float(positions[0])), (float(positions[0]),)),
        bag_io.FLOAT32: (T[bag_io.FLOAT32](data=np.float32(positions[0])), (float(np.float32(positions[0])),)),
    }


@pytest.mark.parametrize("little_endian", [True, False])
def test_decode_message_every_type(little_endian: bool) -> None:
    rng = np.random.default_rng(1)
    names = ["rear_left", "front_steering", "rear"]
    log_ns = 1_700_000_999_000_000_001
    for msgtype, (msg, expected) in _messages("gnss_link", rng, names).items():
        data = bytes(TS.serialize_cdr(msg, msgtype, little_endian=little_endian))
        stamp, values = decode_message(msgtype, data, log_ns, "front_steering")
        assert values == pytest.approx(expected, rel=0, abs=1e-15), msgtype
        expected_stamp = log_ns / 1e9 if msgtype in (bag_io.FLOAT64, bag_io.FLOAT32) else 1_700_000_123_456_789_012 / 1e9
        assert stamp == expected_stamp, msgtype
    odometry, _ = _messages("base_link", np.random.default_rng(1), names)[bag_io.ODOMETRY]
    data = bytes(TS.serialize_cdr(odometry, bag_io.ODOMETRY))
    orientation = odometry.pose.pose.orientation
    assert decode_message(bag_io.ODOMETRY, data, log_ns, role="heading")[1] == (
        orientation.x, orientation.y, orientation.z, orientation.w, odometry.pose.covariance[35])


def test_quaternion_yaw_round_trip() -> None:
    for yaw in np.linspace(-math.pi + 1e-9, math.pi - 1e-9, 41):
        assert quaternion_yaw(*yaw_quaternion(float(yaw))) == pytest.approx(yaw, abs=1e-12)


def test_zero_header_stamp_falls_back_to_log_time() -> None:
    msg = T[bag_io.TWIST_STAMPED](header=_header(0, 0, "gnss"), twist=T["geometry_msgs/msg/Twist"](
        linear=T["geometry_msgs/msg/Vector3"](x=1.0, y=2.0, z=0.0),
        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)))
    stamp, values = decode_message(bag_io.TWIST_STAMPED, bytes(TS.serialize_cdr(msg, bag_io.TWIST_STAMPED)), 5 * 10**9)
    assert stamp == 5.0 and values == (1.0, 2.0)


# --------------------------------------------------------------------------- writing and reading


def test_sim_bag_round_trip_and_truth(tmp_path: Path, sim_result) -> None:
    bag = tmp_path / "sine"
    count = write_sim_bag(sim_result, bag)
    n_gnss, n_steer = len(sim_result.gnss_time), len(sim_result.steering_time)
    assert count == 4 * n_gnss + n_steer
    assert (bag / "metadata.yaml").is_file() and (bag / "sine.mcap").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporary files left behind"

    with Reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
    assert types == {"/gnss/vel": bag_io.TWIST_STAMPED, "/gnss/heading": bag_io.QUATERNION_STAMPED,
                     "/steering_angle": bag_io.JOINT_STATE, "/sim/cornering_stiffness": bag_io.VECTOR3_STAMPED,
                     "/sim/body_velocity": bag_io.TWIST_STAMPED}

    truth = read_truth(bag)
    assert truth is not None
    np.testing.assert_allclose(truth.t - truth.t[0], sim_result.gnss_time, atol=1e-6)
    np.testing.assert_array_equal(truth.cf, sim_result.truth_cf)
    np.testing.assert_array_equal(truth.cr, sim_result.truth_cr)
    np.testing.assert_array_equal(truth.vy, sim_result.truth_vy)
    np.testing.assert_array_equal(truth.r, sim_result.truth_yaw_rate)

    samples = list(read_samples(bag, EstimatorParams()))
    assert len(samples) == 2 * n_gnss + n_steer
    stamps = [s[1] for s in samples]
    assert stamps == sorted(stamps), "samples must stream in time order"
    first_velocity = next(s for s in samples if s[0] == "velocity")
    assert first_velocity[2] == pytest.approx(tuple(sim_result.velocity_enu[0]), abs=0)

    epochs, rejections = read_epochs(bag, EstimatorParams())
    assert len(epochs) == n_gnss - 1 and rejections == []


def test_read_samples_is_lazy(tmp_path: Path, sim_result) -> None:
    bag = tmp_path / "bag"
    write_sim_bag(sim_result, bag)
    stream = read_samples(bag, EstimatorParams())
    assert next(stream)[0] == "steering"  # the steering sample at t=0 is written before the GNSS pair
    stream.close()


def test_bag_without_truth(tmp_path: Path, sim_result) -> None:
    bag = tmp_path / "no_truth"
    write_sim_bag(sim_result, bag, SimBagOptions(truth=False))
    assert read_truth(bag) is None
    assert read_bag(bag, EstimatorParams()).truth is None


VARIANTS = {
    "twist-cov": (dict(velocity_type="twist-cov"), {}),
    "imu": (dict(heading_type="imu"), {}),
    "float64": (dict(steering_type="float64"), {}),
    "ned-velocity": (dict(velocity_frame="ned"), dict(frames=FrameConfig(velocity="ned"))),
    "ned-compass": (dict(heading_frame="ned"), dict(frames=FrameConfig(heading="ned"))),
    "all-alternatives": (
        dict(velocity_type="twist-cov", heading_type="imu", steering_type="float64", velocity_frame="ned",
             heading_frame="ned", velocity_topic="/fix/vel", heading_topic="/fix/heading",
             steering_topic="/steer", joint_name="unused"),
        dict(frames=FrameConfig(velocity="ned", heading="ned"),
             topics=TopicConfig(velocity="/fix/vel", heading="/fix/heading", steering="/steer"))),
    "joint-name": (dict(joint_name="wheel_angle"), dict(steering=SteeringConfig(joint_name="wheel_angle"))),
}


@pytest.fixture(scope="module")
def reference_epochs(tmp_path_factory, sim_result):
    bag = tmp_path_factory.mktemp("ref") / "bag"
    write_sim_bag(sim_result, bag)
    epochs, rejections = read_epochs(bag, EstimatorParams())
    assert rejections == []
    return epoch_matrix(epochs)


@pytest.mark.parametrize("name", list(VARIANTS))
def test_every_accepted_type_and_frame_gives_the_same_epochs(tmp_path: Path, sim_result, reference_epochs,
                                                             name: str) -> None:
    options, params = VARIANTS[name]
    bag = tmp_path / name
    write_sim_bag(sim_result, bag, SimBagOptions(**options))
    epochs, rejections = read_epochs(bag, replace(EstimatorParams(), **params))
    assert rejections == []
    got = epoch_matrix(epochs)
    assert got.shape == reference_epochs.shape
    np.testing.assert_allclose(got, reference_epochs, rtol=0, atol=1e-9)


def test_float32_steering_gives_the_same_epochs_to_its_precision(tmp_path: Path, sim_result, reference_epochs) -> None:
    """std_msgs/Float32 steering (a CAN bridge's type): the epochs of the Float64 bag within float32 rounding."""
    bag = tmp_path / "float32"
    write_sim_bag(sim_result, bag, SimBagOptions(steering_type="float32"))
    epochs, rejections = read_epochs(bag, EstimatorParams())  # the reader takes the bag's type
    assert rejections == []
    got = epoch_matrix(epochs)
    assert got.shape == reference_epochs.shape
    np.testing.assert_allclose(got, reference_epochs, rtol=0, atol=1e-6)  # 2^-24 of angles < 1 rad, and rates
    assert not np.array_equal(got, reference_epochs)  # the rounding is there: the bag does hold float32


def test_our_bags_read_with_the_mcap_library(tmp_path: Path, sim_result) -> None:
    bag = tmp_path / "bag"
    write_sim_bag(sim_result, bag, SimBagOptions(compress=True))
    with open(bag / "bag.mcap", "rb") as handle:
        reader = make_reader(handle)
        assert reader.get_header().profile == "ros2"
        counts: dict[str, int] = {}
        for schema, channel, message in reader.iter_messages():
            assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
            msg = TS.deserialize_cdr(message.data, schema.name)
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == message.log_time
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert counts["/steering_angle"] == len(sim_result.steering_time)
    assert counts["/gnss/vel"] == counts["/sim/body_velocity"] == len(sim_result.gnss_time)


def test_joint_state_without_the_joint_and_out_of_range_steering_are_rejected(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with BagWriter(bag) as writer:
        for k in range(60):
            ns = 1_000_000_000 + k * 200_000_000
            for j in range(10):
                angle = 0.9 if (k == 20 and j == 0) else 0.05
                names = ["other"] if (k == 30 and j == 5) else ["front_steering"]
                writer.write_joint_state("/steering_angle", ns + j * 20_000_000, names, [angle])
            writer.write_twist("/gnss/vel", ns + 10_000_000, (1.0, 0.0, 0.0))
            writer.write_quaternion("/gnss/heading", ns + 10_000_000, yaw_quaternion(0.0))
    data = read_bag(bag, EstimatorParams())
    assert len(data.epochs) == 59
    summary = summarize_rejections(data.rejections)
    assert ("steering", "joint 'front_steering' not in the JointState", 1) in summary
    assert any(topic == "steering" and reason.startswith("beyond max_steering") and n == 1
               for topic, reason, n in summary)


def test_writer_is_atomic(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with pytest.raises(RuntimeError), BagWriter(bag) as writer:
        writer.write_float("/x", 1, 1.0)
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    with BagWriter(bag) as writer:
        writer.write_float("/x", 1, 1.0)
    with pytest.raises(BagError, match="already exists"), BagWriter(bag):
        pass
    with BagWriter(bag, overwrite=True) as writer:
        writer.write_float("/y", 1, 2.0)
    with Reader(bag) as reader:
        assert [c.topic for c in reader.connections] == ["/y"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag"]


def test_output_bag(tmp_path: Path, sim_result) -> None:
    bag = tmp_path / "in"
    write_sim_bag(sim_result, bag)
    epochs, _ = read_epochs(bag, EstimatorParams())
    outputs = np.zeros((len(epochs), N_OUTPUTS))
    outputs[:, 3] = 8000.0
    outputs[5, 3] = np.nan  # never published
    written = write_output_bag(tmp_path / "out", epochs, outputs)
    assert written == len(epochs) - 1
    with Reader(tmp_path / "out") as reader:
        topics = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        stiffness = [TS.deserialize_cdr(d, c.msgtype) for c, _, d in reader.messages()
                     if c.topic == "/estimator/cornering_stiffness"]
    assert topics == {
        "/estimator/cornering_stiffness": (bag_io.VECTOR3_STAMPED, written),
        "/estimator/cornering_stiffness_std": (bag_io.VECTOR3_STAMPED, written),
        "/estimator/model_output": (bag_io.TWIST_STAMPED, written),
        "/estimator/measurement": (bag_io.TWIST_STAMPED, written),
    }
    assert all(m.vector.x == 8000.0 for m in stiffness)


# --------------------------------------------------------------------------- bad bags


def test_missing_topic(tmp_path: Path, sim_result) -> None:
    bag = tmp_path / "bag"
    write_sim_bag(sim_result, bag, SimBagOptions(heading_topic="/other"))
    with pytest.raises(BagError, match=r"no topic /gnss/heading \(the heading input.*topics in the bag: .*/other"):
        read_epochs(bag, EstimatorParams())


def test_wrong_message_type(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with BagWriter(bag) as writer:
        writer.write_vector3("/gnss/vel", 1, (1.0, 2.0, 3.0))
        writer.write_quaternion("/gnss/heading", 1, yaw_quaternion(0.0))
        writer.write_float("/steering_angle", 1, 0.0)
    with pytest.raises(BagError, match="topic /gnss/vel has type geometry_msgs/msg/Vector3Stamped, but the "
                                       "velocity input accepts"):
        read_epochs(bag, EstimatorParams())


def test_empty_bag(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with BagWriter(bag):
        pass
    with pytest.raises(BagError, match="the bag is empty"):
        read_epochs(bag, EstimatorParams())


@pytest.mark.parametrize("keep", [0.0, 0.3, 0.7, 0.999])
def test_truncated_mcap(tmp_path: Path, sim_result, keep: float) -> None:
    bag = tmp_path / "bag"
    write_sim_bag(sim_result, bag)
    mcap = bag / "bag.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(BagError) as info:
        read_epochs(bag, EstimatorParams())
    assert "\n" not in str(info.value) and str(bag) in str(info.value)
    with pytest.raises(BagError):
        read_epochs(mcap, EstimatorParams())


def test_corrupt_chunk(tmp_path: Path, sim_result) -> None:
    bag = tmp_path / "bag"
    write_sim_bag(sim_result, bag, SimBagOptions(compress=True))
    mcap = bag / "bag.mcap"
    data = bytearray(mcap.read_bytes())
    with open(mcap, "rb") as handle:
        chunk = make_reader(handle).get_summary().chunk_indexes[0]
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2  # inside the zstd-compressed records
    data[middle:middle + 64] = bytes(64)
    mcap.write_bytes(bytes(data))
    with pytest.raises(BagError, match="cannot (open|read) bag: .*(corrupt|Zstandard)"):
        read_epochs(bag, EstimatorParams())


def test_nonexistent_and_foreign_paths(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="no such file or directory"):
        read_epochs(tmp_path / "nope", EstimatorParams())
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(BagError, match="not a rosbag2 directory or .mcap file"):
        read_epochs(tmp_path / "notes.txt", EstimatorParams())
    (tmp_path / "dir").mkdir()
    with pytest.raises(BagError, match="not a rosbag2 directory"):
        read_epochs(tmp_path / "dir", EstimatorParams())


def test_directory_without_metadata_reads_its_single_mcap(tmp_path: Path, sim_result) -> None:
    bag = tmp_path / "bag"
    write_sim_bag(sim_result, bag)
    (bag / "metadata.yaml").unlink()
    epochs, _ = read_epochs(bag, EstimatorParams())
    assert len(epochs) == len(sim_result.gnss_time) - 1


def test_no_epochs_is_an_error(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with BagWriter(bag) as writer:
        for k in range(5):
            writer.write_twist("/gnss/vel", 10**9 * (k + 1), (1.0, 0.0, 0.0))
            writer.write_quaternion("/gnss/heading", 10**9 * (k + 1) + 5 * 10**8, yaw_quaternion(0.0))
            writer.write_float("/steering_angle", 10**9 * (k + 1), 0.0)
    with pytest.raises(BagError, match="no epoch could be formed from 5 velocity, 5 heading, 5 steering"):
        read_epochs(bag, EstimatorParams())


def test_rejection_summary_merges_numbers() -> None:
    rejections = [Rejection("steering", 1.0, "|0.800| rad beyond max_steering 0.700"),
                  Rejection("steering", 2.0, "|0.900| rad beyond max_steering 0.700"),
                  Rejection("velocity", 3.0, "non-finite value")]
    assert summarize_rejections(rejections) == [("steering", "beyond max_steering 0.700", 2),
                                                ("velocity", "non-finite value", 1)]


@pytest.mark.parametrize("compress", [False, True])
def test_multi_chunk_bag_as_directory_and_as_mcap_file(tmp_path: Path, compress: bool) -> None:
    result = simulate(build_config("surface-change", duration=400.0, seed=2))
    bag = tmp_path / "long"
    write_sim_bag(result, bag, SimBagOptions(compress=compress))
    with open(bag / "long.mcap", "rb") as handle:
        assert len(make_reader(handle).get_summary().chunk_indexes) >= 3, "the test needs a multi-chunk bag"
    from_dir = list(read_samples(bag, EstimatorParams()))
    assert len(from_dir) == 2 * len(result.gnss_time) + len(result.steering_time)
    stamps = [s[1] for s in from_dir]
    assert stamps == sorted(stamps)
    assert list(read_samples(bag / "long.mcap", EstimatorParams())) == from_dir
    a, b = read_bag(bag, EstimatorParams()), read_bag(bag / "long.mcap", EstimatorParams())
    assert len(a.epochs) == len(result.gnss_time) - 1
    np.testing.assert_array_equal(epoch_matrix(a.epochs), epoch_matrix(b.epochs))
    np.testing.assert_array_equal(a.truth.cf, result.truth_cf)


def test_undecodable_message_is_rejected_not_fatal(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=TS) for topic, msgtype in (
            ("/gnss/vel", bag_io.TWIST_STAMPED), ("/gnss/heading", bag_io.QUATERNION_STAMPED),
            ("/steering_angle", bag_io.FLOAT64))}
        for k in range(20):
            ns = 10**9 + k * 10**8
            twist = T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=5.0, y=0.0, z=0.0),
                                                 angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0))
            vel = bytes(TS.serialize_cdr(T[bag_io.TWIST_STAMPED](header=_header(1, ns - 10**9, "g"), twist=twist),
                                         bag_io.TWIST_STAMPED))
            heading = T[bag_io.QUATERNION_STAMPED](header=_header(1, ns - 10**9, "g"),
                                                   quaternion=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                                                w=1.0))
            writer.write(conns["/steering_angle"], ns, bytes(TS.serialize_cdr(T[bag_io.FLOAT64](data=0.0),
                                                                              bag_io.FLOAT64)))
            writer.write(conns["/gnss/vel"], ns, vel[:20] if k == 7 else vel)  # k == 7: truncated bytes
            writer.write(conns["/gnss/heading"], ns, bytes(TS.serialize_cdr(heading, bag_io.QUATERNION_STAMPED)))
    data = read_bag(bag, EstimatorParams())
    assert data.counts["velocity"] == 19
    assert ("velocity", f"undecodable {bag_io.TWIST_STAMPED} message", 1) in summarize_rejections(data.rejections)
    assert len(data.epochs) > 0
