"""How samples become epochs: the assembler's settings, from the parameters (node and bags alike).

Frames, lever arm, GNSS timing, the steering sensor (``vehicle.steering_scale``, the linkage's play:
:mod:`.steering_play`, and the wheel it sits on: :func:`.steering_line.single_track_angle`) and the
vehicle's physical limits; the assembler
(:mod:`.assembler`) and its batch twin (:mod:`.batch`) read the same :class:`AssemblerSettings`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from transplanter_ident.config.parameters import VehicleParams
from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.config.schema import FRAMES
from transplanter_ident.epochs.steering_line import ackermann_ratio, single_track_angle
from transplanter_ident.epochs.steering_play import SteeringPlay, without_play

#: the estimator's inputs (topics.<role>), in the order a bag summary names them
INPUT_ROLES = ("velocity", "heading", "steering")


def input_roles(params: EstimatorParams) -> tuple[str, ...]:
    """The inputs the node subscribes and a bag must hold: a single antenna (``ekf.measurement: course``) has no heading."""
    return tuple(r for r in INPUT_ROLES if not (r == "heading" and params.config.options.course))


def steering_sensor(vehicle: VehicleParams) -> dict[str, float]:
    """The assembler's ``steering_scale``, ``steering_play`` and ``ackermann`` for the vehicle's steering sensor."""
    ratio = ackermann_ratio(vehicle.steering_sensor_wheel, vehicle.track_width, vehicle.lf + vehicle.lr)
    return {"steering_scale": vehicle.steering_scale, "steering_play": vehicle.steering_play, "ackermann": ratio}


def course_geometry(vehicle: VehicleParams) -> dict[str, float]:
    """The assembler's ``antenna_slip_per_tan``, (lr + antenna_x) / L, and ``wheelbase``, L (:mod:`.course`)."""
    wheelbase = vehicle.lf + vehicle.lr
    return {"antenna_slip_per_tan": (vehicle.lr + vehicle.antenna_x) / wheelbase, "wheelbase": wheelbase}


@dataclass(frozen=True)
class AssemblerSettings:
    """How samples become epochs (the limits default to none; :meth:`from_params` takes the vehicle's)."""

    velocity_frame: str = "enu"
    heading_frame: str = "enu"
    antenna_x: float = 0.0
    antenna_y: float = 0.0
    max_steering: float = 0.7
    match_tolerance: float = 0.02  # s between velocity and heading stamps of one epoch
    steering_timeout: float = 0.5  # s: a newer steering sample must exist within this of t_k
    steering_wait: float = 0.25  # s: an uncovered epoch goes once a GNSS epoch more than this later is matched
    gnss_delay: float = 0.0  # s: GNSS stamped t describes the motion at t - gnss_delay
    steering_buffer: float = 10.0  # s of steering history kept (bounded memory without GNSS)
    heading_offset: float = 0.0  # rad: yaw of the heading source relative to the vehicle x axis (subtracted)
    body_velocity_rotation: float = 0.0  # rad: yaw of a body-frame velocity's axes relative to the vehicle x axis
    max_stamp_jump: float = 1.0  # s: a stamp further from the others is an outlier
    max_speed: float = math.inf  # m/s: |GNSS ground speed| limit
    max_lateral_speed: float = math.inf  # m/s: |vy| at the CG
    max_yaw_rate: float = math.inf  # rad/s: |interval-mean yaw rate|
    max_steering_rate: float = math.inf  # rad/s: |change from the last steering sample| / dt
    steering_scale: float = 1.0  # wheel angle per sensor angle; the limits above apply to the sensor's reading
    steering_play: float = 0.0  # rad of wheel angle, the linkage's free travel (steering_play; sign: where it lies)
    ackermann: float = 0.0  # steering_line.single_track_angle's ratio (0: the sensor gives the single-track angle)
    course: bool = False  # a single antenna (ekf.measurement course): each velocity's direction is its epoch's heading
    antenna_slip_per_tan: float = 0.0  # the antenna's kinematic sideslip per tan(wheel angle), (lr + antenna_x) / L
    wheelbase: float = 1.1  # m, lf + lr: the kinematic yaw rate vx tan(delta) / L

    @classmethod
    def from_params(cls, params: EstimatorParams) -> AssemblerSettings:
        """Frames, lever arm, limits, GNSS timing and steering sensor from the parameters (node and bags alike).

        A nav_msgs/Odometry serving velocity and heading on one topic reports its twist in the frame whose
        yaw it reports, so ``vehicle.heading_offset`` turns that twist too.
        """
        vehicle = params.config.vehicle
        extra = params.extra
        one_odometry = (params.topics.velocity == params.topics.heading
                        and str(extra.get("topics.velocity_type", "")).endswith("Odometry")
                        and str(extra.get("topics.heading_type", "")).endswith("Odometry"))
        return cls(velocity_frame=params.frames.velocity, heading_frame=params.frames.heading,
                   antenna_x=vehicle.antenna_x, antenna_y=vehicle.antenna_y, max_steering=vehicle.max_steering,
                   match_tolerance=params.gnss.pairing_tolerance, gnss_delay=params.gnss.delay,
                   steering_wait=params.steering.max_wait, heading_offset=vehicle.heading_offset,
                   body_velocity_rotation=vehicle.heading_offset if one_odometry else 0.0,
                   max_stamp_jump=params.gnss.max_stamp_jump, max_speed=vehicle.max_speed,
                   max_lateral_speed=vehicle.max_lateral_speed, max_yaw_rate=vehicle.max_yaw_rate,
                   max_steering_rate=vehicle.max_steering_rate, course=params.config.options.course,
                   **course_geometry(vehicle), **steering_sensor(vehicle))

    def __post_init__(self) -> None:
        for name in ("velocity_frame", "heading_frame"):
            if getattr(self, name) not in FRAMES:
                raise ValueError(f"frames.{name.split('_')[0]} must be enu or ned, got {getattr(self, name)!r}")

    def linkage(self) -> SteeringPlay:
        """A fresh steering linkage with this play, for :meth:`wheel_angle`'s readings in order."""
        return SteeringPlay(self.steering_play)

    def wheel_angle(self, sensor: float, linkage: SteeringPlay | None = None) -> float:
        """The single-track steering angle of one steering-sensor reading.

        The sensor's scale, then the linkage's play (``linkage``: the state of the readings before; none:
        no play), then the wheel's Ackermann map.
        """
        scaled = self.steering_scale * sensor
        return single_track_angle(scaled if linkage is None else linkage.wheel(scaled), self.ackermann)

    def wheel_angles(self, sensor: np.ndarray) -> np.ndarray:
        """:meth:`wheel_angle` of every reading in order from :meth:`linkage`, the same operations (batch)."""
        scaled = without_play(self.steering_scale * np.asarray(sensor, dtype=np.float64), self.steering_play)
        if self.ackermann == 0.0:
            return scaled
        return np.array([single_track_angle(angle, self.ackermann) for angle in scaled.tolist()])
