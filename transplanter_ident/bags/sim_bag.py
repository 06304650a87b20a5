"""A simulated run as an MCAP bag, in any accepted message type and in real GNSS drivers' shapes.

:func:`write_sim_bag` writes a ``sim.SimResult``: the input topics plus the ``/sim/*`` ground truth.
:class:`SimBagOptions` chooses the encoding; beyond the message types and frames it reproduces what
real drivers do (issue #12, :mod:`transplanter_ident.sim.drivers` has one preset per driver):

* ``velocity_type odometry``: a nav_msgs/Odometry whose twist is the antenna's velocity in the child
  (body) frame; with ``heading_type odometry`` on the same topic one message carries both;
* ``heading_type pose-cov``: a geometry_msgs/PoseWithCovarianceStamped orientation;
* ``heading_type none``: no heading at all, a single antenna (the estimator reads the velocity's course);
* ``heading_lag`` (+- ``heading_lag_jitter``): the heading stamped that much after the velocity of
  its epoch, as a driver that stamps it on arrival (ublox: 35-45 ms);
* ``heading_offset``: the heading source's yaw relative to the vehicle x axis (a dual-antenna
  baseline mounted across the vehicle): the heading written is the vehicle's plus this;
* ``report_noise``: each GNSS message reports the noise the simulator applied to it (its
  ``velocity_std``/``heading_std``, e.g. larger while an RTK fix is lost) as its covariance, in every
  type that has one; otherwise the constant ``velocity_std``/``heading_std`` (twist-cov, Imu);
* ``invalid_fraction`` of the GNSS epochs carry the driver's invalid marker: ``nan`` (septentrio:
  NaN velocity and orientation) or ``covariance`` (swiftnav: a zero velocity with covariance[0] -1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from transplanter_ident.bags.messages import (
    FLOAT32,
    FLOAT64,
    OUTPUT_FRAME_ID,
    TRUTH_STIFFNESS_TOPIC,
    TRUTH_VELOCITY_TOPIC,
    to_ns,
    yaw_quaternion,
)
from transplanter_ident.bags.writer import BagWriter
from transplanter_ident.sim.drivers import HEADING_TYPES, VELOCITY_TYPES

INVALID_MARKERS = ("nan", "covariance")
#: SimBagOptions.steering_type -> the std_msgs type of a header-less steering angle
_FLOAT_TYPES = {"float64": FLOAT64, "float32": FLOAT32}


@dataclass(frozen=True)
class SimBagOptions:
    """How :func:`write_sim_bag` encodes a simulated run."""

    velocity_topic: str = "/gnss/vel"
    heading_topic: str = "/gnss/heading"
    steering_topic: str = "/steering_angle"
    velocity_type: str = "twist"  # twist | twist-cov | odometry
    heading_type: str = "quaternion"  # quaternion | imu | pose-cov | odometry
    steering_type: str = "joint-state"  # joint-state | float64 | float32
    velocity_frame: str = "enu"  # enu | ned (ground velocities; an Odometry twist is in body axes)
    heading_frame: str = "enu"  # enu | ned (compass heading, clockwise from north)
    joint_name: str = "front_steering"
    start_time: float = 1_700_000_000.0  # s, bag time of simulation time 0
    truth: bool = True
    compress: bool = False
    overwrite: bool = False
    gnss_frame_id: str = "gnss_link"
    velocity_std: float = 0.02  # m/s, reported in TwistWithCovarianceStamped
    heading_std: float = math.radians(0.2)  # rad, reported in Imu
    report_noise: bool = False  # report the simulator's per-epoch noise as the covariance (all types)
    gnss_first: bool = False  # at equal times, log GNSS before the same-instant steering sample
    heading_lag: float = 0.0  # s: heading stamped (and logged) this long after its epoch's velocity
    heading_lag_jitter: float = 0.0  # s: +- uniform spread of the lag
    heading_offset: float = 0.0  # rad: the heading source's yaw relative to the vehicle x axis
    invalid_fraction: float = 0.0  # share of GNSS epochs written with the invalid marker
    invalid_marker: str = "nan"  # nan | covariance
    seed: int = 0  # of the lag jitter and of which epochs are invalid

    def __post_init__(self) -> None:
        for name, choices in (("velocity_type", VELOCITY_TYPES), ("heading_type", HEADING_TYPES),
                              ("steering_type", ("joint-state", "float64", "float32")), ("velocity_frame", ("enu", "ned")),
                              ("heading_frame", ("enu", "ned")), ("invalid_marker", INVALID_MARKERS)):
            if getattr(self, name) not in choices:
                raise ValueError(f"{name} must be one of {', '.join(choices)}, got {getattr(self, name)!r}")
        if not 0.0 <= self.invalid_fraction < 0.5:
            raise ValueError(f"invalid_fraction must be in [0, 0.5), got {self.invalid_fraction!r}")
        for name in ("heading_lag", "heading_lag_jitter", "heading_offset"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite")
        if not self.has_heading and self.velocity_type == "odometry":
            raise ValueError("heading_type none (one antenna) needs a ground velocity: an Odometry twist in body "
                             "axes has no course")
        if self.heading_lag_jitter < 0.0 or self.heading_lag - self.heading_lag_jitter < 0.0:
            raise ValueError("heading_lag - heading_lag_jitter must be >= 0 (a heading cannot arrive early)")

    @property
    def has_heading(self) -> bool:
        """A heading source is written (not a single antenna's velocity alone)."""
        return self.heading_type != "none"

    @property
    def one_odometry(self) -> bool:
        """One nav_msgs/Odometry topic carries velocity and heading."""
        return self.velocity_type == self.heading_type == "odometry" and self.velocity_topic == self.heading_topic


_STEER, _VEL, _HEAD, _STEER_LAST, _TRUTH = 0, 1, 2, 3, 4  # the write order at equal times


def _order(result: Any, opt: SimBagOptions, rng: np.random.Generator) -> tuple[list[int], list[int], dict]:
    """(kind, index) of every message in log order, and the stamps in ns."""
    start_ns = to_ns(opt.start_time)
    gnss_ns = start_ns + np.rint(np.asarray(result.gnss_stamp) * 1e9).astype(np.int64)
    lag = opt.heading_lag + opt.heading_lag_jitter * rng.uniform(-1.0, 1.0, len(gnss_ns))
    heading_ns = gnss_ns + np.rint(lag * 1e9).astype(np.int64)
    ns = {"gnss": gnss_ns, "heading": heading_ns,
          "truth": start_ns + np.rint(np.asarray(result.gnss_time) * 1e9).astype(np.int64),
          "steer": start_ns + np.rint(np.asarray(result.steering_time) * 1e9).astype(np.int64)}
    n_gnss, n_steer = len(gnss_ns), len(ns["steer"])
    kinds = [np.full(n_steer, _STEER_LAST if opt.gnss_first else _STEER), np.full(n_gnss, _VEL)]
    times, index = [ns["steer"], gnss_ns], [np.arange(n_steer), np.arange(n_gnss)]
    if opt.has_heading and not opt.one_odometry:
        kinds.append(np.full(n_gnss, _HEAD))
        times.append(heading_ns)
        index.append(np.arange(n_gnss))
    if opt.truth:
        kinds.append(np.full(n_gnss, _TRUTH))
        times.append(ns["truth"])
        index.append(np.arange(n_gnss))
    kind, when, idx = np.concatenate(kinds), np.concatenate(times), np.concatenate(index)
    order = np.lexsort((kind, when))
    return kind[order].tolist(), idx[order].tolist(), {k: v.tolist() for k, v in ns.items()}


def _gnss_values(result: Any, opt: SimBagOptions, rng: np.random.Generator) -> dict[str, list]:
    """Per GNSS epoch: the velocity as written, the heading source's quaternion, whether it is invalid."""
    vel = np.asarray(result.velocity_enu, dtype=np.float64)
    if opt.velocity_type == "odometry":  # the antenna's velocity in the child frame (turned with the source)
        psi = np.asarray(result.truth_heading) + (opt.heading_offset if opt.one_odometry else 0.0)
        c, s = np.cos(psi), np.sin(psi)
        vel = np.column_stack((c * vel[:, 0] + s * vel[:, 1], -s * vel[:, 0] + c * vel[:, 1]))
    elif opt.velocity_frame == "ned":
        vel = vel[:, ::-1]
    heading = np.asarray(result.heading, dtype=np.float64) + opt.heading_offset
    if opt.heading_frame == "ned":  # compass heading, clockwise from north, in [0, 2 pi)
        heading = np.mod(math.pi / 2.0 - heading, 2.0 * math.pi)
    invalid = np.zeros(len(vel), dtype=bool)
    if opt.invalid_fraction > 0.0:
        invalid[1:] = rng.uniform(size=len(vel) - 1) < opt.invalid_fraction
    n = len(vel)
    velocity_std, heading_std = np.full(n, opt.velocity_std), np.full(n, opt.heading_std)
    if opt.report_noise and result.velocity_std is not None:
        velocity_std, heading_std = np.asarray(result.velocity_std), np.asarray(result.heading_std)
    return {"velocity": vel.tolist(), "quaternion": [yaw_quaternion(h) for h in heading.tolist()],
            "invalid": invalid.tolist(), "velocity_variance": (velocity_std**2).tolist(),
            "heading_variance": (heading_std**2).tolist()}


def write_sim_bag(result: Any, path: str | Path, options: SimBagOptions | None = None) -> int:
    """Write a ``sim.SimResult`` as an MCAP rosbag2 directory; returns the number of messages.

    At equal times the steering sample is written before the GNSS velocity and heading, or after
    them with ``gnss_first``; then the ground truth. GNSS messages carry ``result.gnss_stamp``
    (late by the simulated GNSS delay; the heading ``heading_lag`` later still); the truth is
    stamped at the motion's time.
    """
    opt = options or SimBagOptions()
    rng = np.random.default_rng(opt.seed)
    kinds, indices, ns = _order(result, opt, rng)
    gnss = _gnss_values(result, opt, rng)
    steer_list = np.asarray(result.steering, dtype=np.float64).tolist()
    truth = (np.column_stack([result.truth_cf, result.truth_cr]).tolist(),
             np.column_stack([result.truth_vx, result.truth_vy, result.truth_yaw_rate]).tolist())

    with BagWriter(path, compress=opt.compress, overwrite=opt.overwrite) as bag:
        for k, i in zip(kinds, indices, strict=True):
            if k in (_STEER, _STEER_LAST):
                if opt.steering_type in _FLOAT_TYPES:
                    bag.write_float(opt.steering_topic, ns["steer"][i], steer_list[i], _FLOAT_TYPES[opt.steering_type])
                else:
                    bag.write_joint_state(opt.steering_topic, ns["steer"][i], [opt.joint_name], [steer_list[i]])
            elif k == _VEL:
                _write_velocity(bag, opt, ns["gnss"][i], gnss, i)
            elif k == _HEAD:
                _write_heading(bag, opt, ns["heading"][i], gnss, i)
            else:
                stamp = ns["truth"][i]
                bag.write_vector3(TRUTH_STIFFNESS_TOPIC, stamp, (*truth[0][i], 0.0), frame_id=OUTPUT_FRAME_ID)
                vx, vy, r = truth[1][i]
                bag.write_twist(TRUTH_VELOCITY_TOPIC, stamp, (vx, vy, 0.0), (0.0, 0.0, r), frame_id=OUTPUT_FRAME_ID)
        return bag.count


def _write_velocity(bag: BagWriter, opt: SimBagOptions, stamp: int, gnss: dict[str, list], i: int) -> None:
    covariance = np.zeros(36)
    covariance[[0, 7, 14]] = gnss["velocity_variance"][i]
    yaw_variance = gnss["heading_variance"][i] if opt.report_noise else 0.0
    vx, vy = gnss["velocity"][i]
    q = gnss["quaternion"][i]
    if gnss["invalid"][i]:
        if opt.invalid_marker == "nan":
            vx = vy = math.nan
            q = (math.nan,) * 4
        else:
            vx = vy = 0.0
            covariance[0] = -1.0
    linear = (vx, vy, 0.0)
    if opt.velocity_type == "odometry":
        bag.write_odometry(opt.velocity_topic, stamp, linear, q, covariance, yaw_variance=yaw_variance)
    elif opt.velocity_type == "twist-cov":
        bag.write_twist_with_covariance(opt.velocity_topic, stamp, linear, covariance=covariance,
                                        frame_id=opt.gnss_frame_id)
    else:
        bag.write_twist(opt.velocity_topic, stamp, linear, frame_id=opt.gnss_frame_id)


def _write_heading(bag: BagWriter, opt: SimBagOptions, stamp: int, gnss: dict[str, list], i: int) -> None:
    q = gnss["quaternion"][i]
    if gnss["invalid"][i] and opt.invalid_marker == "nan":
        q = (math.nan,) * 4
    variance = gnss["heading_variance"][i]
    reported = variance if opt.report_noise else 0.0  # Pose and Odometry report it only with report_noise
    if opt.heading_type == "imu":
        bag.write_imu(opt.heading_topic, stamp, q, frame_id=opt.gnss_frame_id, orientation_variance=variance)
    elif opt.heading_type == "pose-cov":
        bag.write_pose_with_covariance(opt.heading_topic, stamp, q, frame_id=opt.gnss_frame_id, yaw_variance=reported)
    elif opt.heading_type == "odometry":
        bag.write_odometry(opt.heading_topic, stamp, (0.0, 0.0, 0.0), q, yaw_variance=reported)
    else:
        bag.write_quaternion(opt.heading_topic, stamp, q, frame_id=opt.gnss_frame_id)


#: what one antenna needs (README "One antenna"): the course; the GNSS timing stated, as a course cannot show it
#: (the simulator's stamping delay is exact; 2 ms is a receiver's documented latency's spread); its precision
ONE_ANTENNA = {"ekf.measurement": "course", "ekf.delay_uncertainty": 0.002, "validity.max_rel_std": 0.08}

#: SimBagOptions type names -> the estimator's topics.*_type values
_TYPE_NAMES = {"twist": "TwistStamped", "twist-cov": "TwistWithCovarianceStamped", "odometry": "Odometry",
               "quaternion": "QuaternionStamped", "imu": "Imu", "pose-cov": "PoseWithCovarianceStamped",
               "joint-state": "JointState", "float64": "Float64", "float32": "Float32"}


def reading_parameters(opt: SimBagOptions, *, gnss_delay: float = 0.0, antenna_x: float = 0.0,
                       antenna_y: float = 0.0) -> dict[str, Any]:
    """The estimator parameters (flat dotted keys) that read a bag written with ``opt``.

    ``gnss_delay`` is the simulator's GNSS stamping delay; ``antenna_x``/``antenna_y`` its lever arm (for an
    Odometry velocity: the child frame's origin).
    """
    reported = {"ekf.measurement_noise_from_covariance": True} if opt.report_noise else {}
    heading = ({"topics.heading": opt.heading_topic, "topics.heading_type": _TYPE_NAMES[opt.heading_type],
                "frames.heading": opt.heading_frame, "vehicle.heading_offset": float(opt.heading_offset)}
               if opt.has_heading else ONE_ANTENNA)
    return {
        **reported,
        "topics.velocity": opt.velocity_topic, "topics.steering": opt.steering_topic,
        "topics.velocity_type": _TYPE_NAMES[opt.velocity_type], "topics.steering_type": _TYPE_NAMES[opt.steering_type],
        "frames.velocity": opt.velocity_frame, **heading, "steering.joint_name": opt.joint_name,
        "gnss.delay": float(gnss_delay), "vehicle.antenna_x": float(antenna_x), "vehicle.antenna_y": float(antenna_y),
    }
