"""Real GNSS drivers' output shapes, for ``simulate --driver NAME`` (issue #12; data only).

Each :class:`DriverShape` names what a driver publishes (message types, frames, stamping and its
conventions) as :class:`transplanter_ident.bags.SimBagOptions` fields plus the GNSS stamping
delay of the simulator. ``simulate --driver NAME --params-out P.yaml`` writes the bag and the
estimator parameters that read it; README.md has the same table for the real drivers. Topic
names are the drivers' usual ones. Angles in rad, times in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

#: message types ``simulate`` writes (bags.sim_bag.SimBagOptions): velocity and heading
VELOCITY_TYPES = ("twist", "twist-cov", "odometry")
HEADING_TYPES = ("quaternion", "imu", "pose-cov", "odometry", "none")  # none: one antenna (ekf.measurement course)


@dataclass(frozen=True)
class DriverShape:
    """One driver: what it publishes, as bag options, and how it stamps."""

    description: str
    bag: dict[str, Any] = field(default_factory=dict)  # SimBagOptions fields
    gnss_delay: float = 0.0  # s: velocity and heading stamped this late (on arrival)


DRIVERS: dict[str, DriverShape] = {
    "ublox": DriverShape(
        "ublox (KumarRobotics): fix_velocity TwistWithCovarianceStamped, ENU, receiver time; navheading "
        "sensor_msgs/Imu with the NAV-RELPOSNED heading (clockwise from north) as yaw, stamped on arrival "
        "35-45 ms later; the baseline (moving base to rover) across the vehicle, rover on the right",
        {"velocity_topic": "/ublox_gps_node/fix_velocity", "heading_topic": "/ublox_gps_node/navheading",
         "velocity_type": "twist-cov", "heading_type": "imu", "heading_frame": "ned", "heading_lag": 0.040,
         "heading_lag_jitter": 0.005, "heading_offset": -math.pi / 2.0}),
    "nmea": DriverShape(
        "nmea_navsat_driver: vel TwistStamped (ENU) and heading QuaternionStamped with the HDT compass heading "
        "put straight into yaw, both stamped on arrival (80 ms after the receiver epoch, the heading 4 ms later)",
        {"velocity_topic": "/vel", "heading_topic": "/heading", "velocity_type": "twist", "heading_type": "quaternion",
         "heading_frame": "ned", "heading_lag": 0.004}, gnss_delay=0.08),
    "nmea-single": DriverShape(
        "nmea_navsat_driver with one antenna: vel TwistStamped (ENU) from the RMC/VTG speed and track, stamped on "
        "arrival 80 ms after the receiver epoch; no heading (no HDT sentence), so the estimator reads the course "
        "(ekf.measurement course)",
        {"velocity_topic": "/vel", "velocity_type": "twist", "heading_type": "none"}, gnss_delay=0.08),
    "septentrio": DriverShape(
        "septentrio: the INS's nav_msgs/Odometry (twist in the body frame) and the dual-antenna heading in a "
        "PoseWithCovarianceStamped (ENU yaw of the baseline, mounted across, aux antenna on the left); NaN "
        "fields in 2 % of the epochs (the driver's do-not-use values)",
        {"velocity_topic": "/localization", "heading_topic": "/pose", "velocity_type": "odometry",
         "heading_type": "pose-cov", "heading_offset": math.pi / 2.0, "invalid_fraction": 0.02,
         "invalid_marker": "nan"}),
    "odometry": DriverShape(
        "novatel (oem7 odom), robot_localization and other GNSS/INS units: one nav_msgs/Odometry topic, twist in "
        "the child frame, orientation the heading",
        {"velocity_topic": "/odometry/filtered", "heading_topic": "/odometry/filtered", "velocity_type": "odometry",
         "heading_type": "odometry"}),
    "swiftnav": DriverShape(
        "swiftnav: TwistWithCovarianceStamped (ENU) and the INS orientation as sensor_msgs/Imu, receiver time; an "
        "invalid velocity is zeros with covariance[0] = -1 (2 % of the epochs)",
        {"velocity_topic": "/gnss/twist", "heading_topic": "/gnss/imu", "velocity_type": "twist-cov",
         "heading_type": "imu", "invalid_fraction": 0.02, "invalid_marker": "covariance"}),
}
