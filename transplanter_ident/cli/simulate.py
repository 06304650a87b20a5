"""The `simulate` command: write a synthetic MCAP bag with the input topics and the ground truth.

The scenario (``--scenario``, see :mod:`transplanter_ident.sim.scenarios`) is simulated with
:func:`transplanter_ident.sim.simulate` and written with :func:`transplanter_ident.bag_io.write_sim_bag`:

* ``/gnss/vel`` geometry_msgs/TwistStamped, ENU (``--velocity-type twist-cov``, ``--velocity-frame ned``);
* ``/gnss/heading`` geometry_msgs/QuaternionStamped, ENU yaw (``--heading-type imu``,
  ``--heading-frame ned`` for a compass heading);
* ``/steering_angle`` sensor_msgs/JointState, joint ``front_steering`` (``--steering-type float64``);
* ``/sim/cornering_stiffness`` Vector3Stamped (x = Cf, y = Cr) and ``/sim/body_velocity``
  TwistStamped at the CG (linear.x vx, linear.y vy, angular.z r): the ground truth.

Example: ``simulate -o bags/sine --scenario sine --seed 1``.
"""

from __future__ import annotations

import argparse
import sys

from transplanter_ident.cli.util import CliError, cli_main
from transplanter_ident.sim.scenarios import DEFAULT_SCENARIO, SCENARIOS


def build_parser() -> argparse.ArgumentParser:
    """Command line pinned in DESIGN.md section 3, plus the encoding and override options."""
    scenarios = "\n".join(f"  {name:<16}{s.description} ({s.default_duration:g} s)" for name, s in SCENARIOS.items())
    parser = argparse.ArgumentParser(
        prog="simulate",
        description="Write a synthetic MCAP bag (rosbag2 directory) with the estimator's input topics "
                    "and the ground truth.",
        epilog=f"scenarios:\n{scenarios}\n\nexample: simulate -o bags/sine --scenario sine --seed 1",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-o", "--output", metavar="BAG_DIR", required=True, help="bag directory to write")
    parser.add_argument("--scenario", metavar="NAME", default=DEFAULT_SCENARIO, choices=sorted(SCENARIOS),
                        help=f"scenario name (default {DEFAULT_SCENARIO}; see below)")
    parser.add_argument("--seed", metavar="N", type=int, default=0, help="random seed of the sensor noise (default 0)")
    parser.add_argument("--duration", metavar="S", type=float, help="duration in seconds (default: the scenario's)")
    parser.add_argument("--speed", metavar="V", type=float, help="forward speed vx at the CG, m/s")
    parser.add_argument("--tire", choices=("linear", "saturating"), help="tire model (default linear)")
    parser.add_argument("--friction", metavar="MU", type=float, help="friction coefficient of the saturating tire")
    parser.add_argument("--gnss-rate", metavar="HZ", type=float, help="GNSS velocity and heading rate (default 5)")
    parser.add_argument("--steering-rate", metavar="HZ", type=float, help="steering angle rate (default 50)")
    parser.add_argument("--antenna-x", metavar="M", type=float, help="GNSS antenna ahead of the CG, m (default 0)")
    parser.add_argument("--antenna-y", metavar="M", type=float, help="GNSS antenna left of the CG, m (default 0)")
    imperfect = parser.add_argument_group("real-sensor imperfections (DESIGN.md section 7)")
    imperfect.add_argument("--steering-offset", metavar="RAD", type=float,
                           help="the steering sensor reads the wheel angle + RAD (default 0)")
    imperfect.add_argument("--gnss-delay", metavar="S", type=float,
                           help="GNSS velocity and heading stamped S late, as by a driver stamping on arrival "
                                "(default 0; replay with gnss.delay: S)")
    imperfect.add_argument("--gnss-first", action="store_true",
                           help="log each GNSS message before the steering sample of the same instant")
    enc = parser.add_argument_group("message types, frames and topics")
    enc.add_argument("--velocity-type", choices=("twist", "twist-cov"), default="twist",
                     help="TwistStamped or TwistWithCovarianceStamped (default twist)")
    enc.add_argument("--heading-type", choices=("quaternion", "imu"), default="quaternion",
                     help="QuaternionStamped or sensor_msgs/Imu (default quaternion)")
    enc.add_argument("--steering-type", choices=("joint-state", "float64"), default="joint-state",
                     help="sensor_msgs/JointState or std_msgs/Float64 (default joint-state)")
    enc.add_argument("--velocity-frame", choices=("enu", "ned"), default="enu",
                     help="linear.x/y = east/north (enu) or north/east (ned)")
    enc.add_argument("--heading-frame", choices=("enu", "ned"), default="enu",
                     help="ENU yaw (enu) or compass heading clockwise from north (ned)")
    enc.add_argument("--velocity-topic", metavar="TOPIC", default="/gnss/vel")
    enc.add_argument("--heading-topic", metavar="TOPIC", default="/gnss/heading")
    enc.add_argument("--steering-topic", metavar="TOPIC", default="/steering_angle")
    enc.add_argument("--joint-name", metavar="NAME", default="front_steering", help="JointState joint name")
    enc.add_argument("--start-time", metavar="SEC", type=float, default=1_700_000_000.0,
                     help="bag time of simulation time 0, s since the epoch (default 1700000000)")
    enc.add_argument("--no-truth", action="store_true", help="leave out the /sim/* ground truth topics")
    enc.add_argument("--compress", action="store_true", help="zstd-compress the MCAP chunks")
    parser.add_argument("--force", action="store_true", help="replace BAG_DIR if it exists")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    return parser


def _run(args: argparse.Namespace) -> int:
    from transplanter_ident.bags import SimBagOptions, write_sim_bag
    from transplanter_ident.sim.scenarios import build_config
    from transplanter_ident.sim.simulator import simulate

    try:
        config = build_config(args.scenario, duration=args.duration, seed=args.seed, speed=args.speed,
                              tire=args.tire, friction=args.friction, gnss_rate=args.gnss_rate,
                              steering_rate=args.steering_rate, antenna_x=args.antenna_x,
                              antenna_y=args.antenna_y, steering_offset=args.steering_offset,
                              gnss_delay=args.gnss_delay)
        options = SimBagOptions(
            velocity_topic=args.velocity_topic, heading_topic=args.heading_topic,
            steering_topic=args.steering_topic, velocity_type=args.velocity_type,
            heading_type=args.heading_type, steering_type=args.steering_type,
            velocity_frame=args.velocity_frame, heading_frame=args.heading_frame, joint_name=args.joint_name,
            start_time=args.start_time, truth=not args.no_truth, compress=args.compress, overwrite=args.force,
            gnss_first=args.gnss_first,
        )
    except ValueError as exc:
        raise CliError(f"invalid option: {exc}") from exc
    result = simulate(config)
    count = write_sim_bag(result, args.output, options)
    print(f"simulate: wrote {args.output}: scenario {args.scenario}, {config.duration:g} s, {count} messages "
          f"({len(result.gnss_time)} GNSS epochs at {config.gnss_rate:g} Hz, {len(result.steering_time)} "
          f"steering samples at {config.steering_rate:g} Hz, {config.tire} tire, seed {config.seed})")
    vehicle = config.vehicle
    if vehicle.antenna_x or vehicle.antenna_y or args.velocity_frame != "enu" or args.heading_frame != "enu" \
            or args.joint_name != "front_steering" or args.velocity_topic != "/gnss/vel" \
            or args.heading_topic != "/gnss/heading" or args.steering_topic != "/steering_angle":
        print("simulate: replay it with parameters matching the bag: "
              f"vehicle.antenna_x {vehicle.antenna_x:g}, vehicle.antenna_y {vehicle.antenna_y:g}, "
              f"frames {{velocity: {args.velocity_frame}, heading: {args.heading_frame}}}, "
              f"steering.joint_name {args.joint_name}, topics {{velocity: {args.velocity_topic}, "
              f"heading: {args.heading_topic}, steering: {args.steering_topic}}}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `simulate` console script."""
    return cli_main(build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
