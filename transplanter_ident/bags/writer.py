"""Writing rosbag2 bags (MCAP) with the ROS 2 Jazzy typestore, atomically.

:class:`BagWriter` builds the bag under a temporary name and renames it when complete; it writes
every input message type the estimator accepts (including the drivers' shapes of issue #12).
:func:`write_output_bag` writes the node's output topics for a replayed bag; simulated runs are
written by :mod:`.sim_bag`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from transplanter_ident.bags.errors import BagError
from transplanter_ident.bags.messages import (
    FLOAT32,
    FLOAT64,
    IMU,
    JOINT_STATE,
    NS_PER_S,
    ODOMETRY,
    OUTPUT_FRAME_ID,
    OUTPUT_MEASUREMENT,
    OUTPUT_MODEL,
    OUTPUT_NAMESPACE,
    OUTPUT_STIFFNESS,
    OUTPUT_STIFFNESS_STD,
    POSE_COV_STAMPED,
    QUATERNION_STAMPED,
    TWIST_COV_STAMPED,
    TWIST_STAMPED,
    TYPESTORE,
    VECTOR3_STAMPED,
    to_ns,
)
from transplanter_ident.bags.reader import _reason
from transplanter_ident.epochs.epoch import EpochArrays
from transplanter_ident.epochs.frames import YAW_VARIANCE_POSE
from transplanter_ident.files import atomic_output_dir


def _types() -> dict[str, Any]:
    return TYPESTORE.types


def _header(stamp_ns: int, frame_id: str) -> Any:
    types = _types()
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                        frame_id=frame_id)


def _vector3(xyz: Sequence[float]) -> Any:
    return _types()["geometry_msgs/msg/Vector3"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def _quaternion(q: Sequence[float]) -> Any:
    return _types()["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _pose_with_covariance(orientation: Sequence[float], yaw_variance: float = 0.0) -> Any:
    types = _types()
    pose = types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                                           orientation=_quaternion(orientation))
    covariance = np.zeros(36)
    covariance[YAW_VARIANCE_POSE] = yaw_variance
    return types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=covariance)


class BagWriter:
    """Write an MCAP rosbag2 directory (ROS 2 Jazzy types), atomically.

    Use as a context manager; the bag appears at ``path`` only when the block ends without
    an exception. Each ``write_*`` helper takes the header stamp in integer nanoseconds and
    uses it as the log time too (``log_ns`` overrides). Connections are added on first use.
    """

    def __init__(self, path: str | Path, *, compress: bool = False, overwrite: bool = False) -> None:
        self.path = Path(path)
        self.compress = compress
        self.overwrite = overwrite
        self._writer: Writer | None = None
        self._connections: dict[tuple[str, str], Any] = {}
        self._dir_context: Any = None
        self.count = 0

    def __enter__(self) -> BagWriter:
        try:
            self._dir_context = atomic_output_dir(self.path, overwrite=self.overwrite)
            staging = self._dir_context.__enter__()
            self._writer = Writer(staging, version=9, storage_plugin=StoragePlugin.MCAP)
            if self.compress:
                self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            self._writer.open()
        except Exception as exc:
            if self._dir_context is not None:
                self._dir_context.__exit__(type(exc), exc, exc.__traceback__)
            raise BagError(f"{self.path}: cannot write bag: {_reason(exc)}") from exc
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> bool:
        writer, self._writer = self._writer, None
        try:
            if writer is not None:
                if exc_type is None:
                    writer.close()
                else:
                    try:
                        writer.close()
                    except Exception:  # noqa: BLE001, S110 - the original error matters, the dir is discarded
                        pass
        except Exception as close_exc:
            self._dir_context.__exit__(type(close_exc), close_exc, close_exc.__traceback__)
            raise BagError(f"{self.path}: cannot write bag: {_reason(close_exc)}") from close_exc
        try:
            self._dir_context.__exit__(exc_type, exc, tb)
        except Exception as move_exc:
            if exc_type is None:
                raise BagError(f"{self.path}: cannot write bag: {_reason(move_exc)}") from move_exc
        return False

    def write(self, topic: str, msgtype: str, msg: Any, log_ns: int) -> None:
        """Serialize ``msg`` (a typestore message of ``msgtype``) and write it at ``log_ns``."""
        if self._writer is None:
            raise BagError(f"{self.path}: bag is not open for writing")
        key = (topic, msgtype)
        conn = self._connections.get(key)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=TYPESTORE)
            self._connections[key] = conn
        self._writer.write(conn, int(log_ns), TYPESTORE.serialize_cdr(msg, msgtype))
        self.count += 1

    def write_twist(self, topic: str, stamp_ns: int, linear: Sequence[float], angular: Sequence[float] = (0, 0, 0),
                    *, frame_id: str = "", log_ns: int | None = None) -> None:
        """geometry_msgs/TwistStamped."""
        types = _types()
        twist = types["geometry_msgs/msg/Twist"](linear=_vector3(linear), angular=_vector3(angular))
        msg = types[TWIST_STAMPED](header=_header(stamp_ns, frame_id), twist=twist)
        self.write(topic, TWIST_STAMPED, msg, stamp_ns if log_ns is None else log_ns)

    def write_twist_with_covariance(self, topic: str, stamp_ns: int, linear: Sequence[float],
                                    angular: Sequence[float] = (0, 0, 0), covariance: Sequence[float] | None = None,
                                    *, frame_id: str = "", log_ns: int | None = None) -> None:
        """geometry_msgs/TwistWithCovarianceStamped (covariance: 36 values, default zeros)."""
        types = _types()
        twist = types["geometry_msgs/msg/Twist"](linear=_vector3(linear), angular=_vector3(angular))
        cov = np.zeros(36) if covariance is None else np.asarray(covariance, dtype=np.float64).reshape(36)
        msg = types[TWIST_COV_STAMPED](header=_header(stamp_ns, frame_id),
                                       twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist,
                                                                                           covariance=cov))
        self.write(topic, TWIST_COV_STAMPED, msg, stamp_ns if log_ns is None else log_ns)

    def write_odometry(self, topic: str, stamp_ns: int, linear: Sequence[float], orientation: Sequence[float],
                       twist_covariance: Sequence[float] | None = None, *, frame_id: str = "odom",
                       child_frame_id: str = "base_link", yaw_variance: float = 0.0,
                       log_ns: int | None = None) -> None:
        """nav_msgs/Odometry: the twist ``linear`` in the child (body) frame, the pose's ``orientation`` (x, y, z, w).

        ``yaw_variance`` goes to the pose covariance (0: unknown), the rest of which is zero.
        """
        types = _types()
        twist = types["geometry_msgs/msg/Twist"](linear=_vector3(linear), angular=_vector3((0.0, 0.0, 0.0)))
        cov = np.zeros(36) if twist_covariance is None else np.asarray(twist_covariance, dtype=np.float64).reshape(36)
        msg = types[ODOMETRY](header=_header(stamp_ns, frame_id), child_frame_id=child_frame_id,
                              pose=_pose_with_covariance(orientation, yaw_variance),
                              twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov))
        self.write(topic, ODOMETRY, msg, stamp_ns if log_ns is None else log_ns)

    def write_pose_with_covariance(self, topic: str, stamp_ns: int, orientation: Sequence[float], *,
                                   frame_id: str = "", yaw_variance: float = 0.0, log_ns: int | None = None) -> None:
        """geometry_msgs/PoseWithCovarianceStamped: an orientation, its yaw variance (0: unknown), the rest zero."""
        msg = _types()[POSE_COV_STAMPED](header=_header(stamp_ns, frame_id),
                                         pose=_pose_with_covariance(orientation, yaw_variance))
        self.write(topic, POSE_COV_STAMPED, msg, stamp_ns if log_ns is None else log_ns)

    def write_quaternion(self, topic: str, stamp_ns: int, quaternion: Sequence[float], *, frame_id: str = "",
                         log_ns: int | None = None) -> None:
        """geometry_msgs/QuaternionStamped; ``quaternion`` is (x, y, z, w)."""
        msg = _types()[QUATERNION_STAMPED](header=_header(stamp_ns, frame_id), quaternion=_quaternion(quaternion))
        self.write(topic, QUATERNION_STAMPED, msg, stamp_ns if log_ns is None else log_ns)

    def write_imu(self, topic: str, stamp_ns: int, orientation: Sequence[float], *, frame_id: str = "",
                  orientation_variance: float = 0.0, log_ns: int | None = None) -> None:
        """sensor_msgs/Imu carrying only an orientation (angular velocity and acceleration marked unknown)."""
        unknown = np.zeros(9)
        unknown[0] = -1.0  # REP 145: covariance[0] = -1 means "no estimate of this quantity"
        orientation_cov = np.zeros(9)
        orientation_cov[[0, 4, 8]] = orientation_variance
        msg = _types()[IMU](header=_header(stamp_ns, frame_id), orientation=_quaternion(orientation),
                            orientation_covariance=orientation_cov, angular_velocity=_vector3((0, 0, 0)),
                            angular_velocity_covariance=unknown, linear_acceleration=_vector3((0, 0, 0)),
                            linear_acceleration_covariance=unknown.copy())
        self.write(topic, IMU, msg, stamp_ns if log_ns is None else log_ns)

    def write_joint_state(self, topic: str, stamp_ns: int, names: Sequence[str], positions: Sequence[float], *,
                          frame_id: str = "", log_ns: int | None = None) -> None:
        """sensor_msgs/JointState with positions only."""
        empty = np.zeros(0)
        msg = _types()[JOINT_STATE](header=_header(stamp_ns, frame_id), name=list(names),
                                    position=np.asarray(positions, dtype=np.float64), velocity=empty,
                                    effort=empty)
        self.write(topic, JOINT_STATE, msg, stamp_ns if log_ns is None else log_ns)

    def write_float(self, topic: str, log_ns: int, value: float, msgtype: str = FLOAT64) -> None:
        """std_msgs/Float64, or ``msgtype`` std_msgs/Float32 (no header: the log time is its only stamp)."""
        if msgtype not in (FLOAT64, FLOAT32):
            raise ValueError(f"write_float: msgtype must be {FLOAT64} or {FLOAT32}, got {msgtype!r}")
        self.write(topic, msgtype, _types()[msgtype](data=float(value)), log_ns)

    def write_vector3(self, topic: str, stamp_ns: int, xyz: Sequence[float], *, frame_id: str = "",
                      log_ns: int | None = None) -> None:
        """geometry_msgs/Vector3Stamped."""
        msg = _types()[VECTOR3_STAMPED](header=_header(stamp_ns, frame_id), vector=_vector3(xyz))
        self.write(topic, VECTOR3_STAMPED, msg, stamp_ns if log_ns is None else log_ns)


def write_output_bag(path: str | Path, epochs: EpochArrays, outputs: np.ndarray, *,
                     namespace: str = OUTPUT_NAMESPACE, overwrite: bool = False,
                     frame_id: str = OUTPUT_FRAME_ID) -> int:
    """Write the node's output topics for every epoch, stamped (and logged) at the epoch time, framed ``frame_id``.

    Epochs whose outputs are not all finite are skipped (the node never publishes NaN).
    Returns the number of epochs written.
    """
    from transplanter_ident.ekf.layout import O_CF, O_CF_STD, O_CR, O_CR_STD, O_R_MODEL, O_VY_MODEL

    ns_prefix = namespace.rstrip("/")
    topics = {name: f"{ns_prefix}/{name}" for name in (OUTPUT_STIFFNESS, OUTPUT_STIFFNESS_STD, OUTPUT_MODEL,
                                                       OUTPUT_MEASUREMENT)}
    cols = [O_CF, O_CR, O_CF_STD, O_CR_STD, O_VY_MODEL, O_R_MODEL]
    written = 0
    with BagWriter(path, overwrite=overwrite) as bag:
        t_ns = [to_ns(t) for t in epochs.t.tolist()]
        meas = np.column_stack([epochs.longitudinal_velocity, epochs.lateral_velocity, epochs.yaw_rate]).tolist()
        out = outputs[:, cols].tolist()
        for ns, (vx, vy, r), (cf, cr, cf_std, cr_std, vy_model, r_model) in zip(t_ns, meas, out, strict=True):
            if not all(math.isfinite(v) for v in (vx, vy, r, cf, cr, cf_std, cr_std, vy_model, r_model)):
                continue
            bag.write_vector3(topics[OUTPUT_STIFFNESS], ns, (cf, cr, 0.0), frame_id=frame_id)
            bag.write_vector3(topics[OUTPUT_STIFFNESS_STD], ns, (cf_std, cr_std, 0.0), frame_id=frame_id)
            bag.write_twist(topics[OUTPUT_MODEL], ns, (0.0, vy_model, 0.0), (0.0, 0.0, r_model),
                            frame_id=frame_id)
            bag.write_twist(topics[OUTPUT_MEASUREMENT], ns, (vx, vy, 0.0), (0.0, 0.0, r),
                            frame_id=frame_id)
            written += 1
    return written
