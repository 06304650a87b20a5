"""The `simulate` command: write a synthetic MCAP bag with the input topics and the ground truth.

The scenario (``--scenario``, see :mod:`transplanter_ident.sim.scenarios`) is simulated with
:func:`transplanter_ident.sim.simulate` and written with :func:`transplanter_ident.bags.write_sim_bag`:

* ``/gnss/vel`` geometry_msgs/TwistStamped, ENU (``--velocity-type twist-cov|odometry``, ``--velocity-frame ned``);
* ``/gnss/heading`` geometry_msgs/QuaternionStamped, ENU yaw (``--heading-type imu|pose-cov|odometry``,
  ``--heading-frame ned`` for a compass heading);
* ``/steering_angle`` sensor_msgs/JointState, joint ``front_steering`` (``--steering-type float64``);
* ``/sim/cornering_stiffness`` Vector3Stamped (x = Cf, y = Cr) and ``/sim/body_velocity``
  TwistStamped at the CG (linear.x vx, linear.y vy, angular.z r): the ground truth.

``--driver ublox|nmea|nmea-single|septentrio|odometry|swiftnav`` writes a real GNSS driver's shape (types,
topics, stamping, conventions, invalid markers; :mod:`transplanter_ident.sim.drivers`); single
flags override it. ``--params-out P.yaml`` writes the estimator parameters that read the bag.

Example: ``simulate -o bags/sine --scenario sine --seed 1``;
``simulate -o /tmp/ublox --driver ublox --params-out /tmp/ublox.yaml``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from transplanter_ident.cli.util import CliError, cli_main
from transplanter_ident.sim.drivers import DRIVERS, HEADING_TYPES, VELOCITY_TYPES
from transplanter_ident.sim.scenarios import DEFAULT_SCENARIO, SCENARIOS

#: SimBagOptions field -> the option that sets it
ENCODING_OPTIONS = ("velocity_type", "heading_type", "steering_type", "velocity_frame", "heading_frame", "heading_lag",
                    "heading_lag_jitter", "heading_offset", "invalid_fraction", "invalid_marker", "velocity_topic",
                    "heading_topic", "steering_topic", "joint_name", "report_noise")


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
    imperfect.add_argument("--gnss-degraded", metavar=("START", "END", "FACTOR"), type=float, nargs=3,
                           help="GNSS velocity and heading noise FACTOR times larger from START to END s (an RTK "
                                "fix lost to float); with --report-noise the messages say so")
    imperfect.add_argument("--gnss-correlation-time", metavar="S", type=float,
                           help="GNSS velocity and heading errors correlated in time (first-order Gauss-Markov, "
                                "this time constant, the same 1-sigma; default 0: white)")
    imperfect.add_argument("--side-slope", metavar="RAD", type=float,
                           help="a cross slope along the path: gravity adds g sin(slope) to the lateral "
                                "acceleration (+: to the left; default 0)")
    imperfect.add_argument("--steering-scale", metavar="K", type=float,
                           help="the steering sensor reads the wheel angle x K (a calibration's gain error; default 1)")
    imperfect.add_argument("--steering-play", metavar="RAD", type=float,
                           help="free travel of the steering linkage, in wheel angle: > 0 the wheels follow the "
                                "sensor through it, < 0 the sensor follows the wheels (replay with "
                                "vehicle.steering_play: RAD; default 0)")
    imperfect.add_argument("--relaxation-length", metavar="M", type=float,
                           help="the tires build their force over M of travel, lagging the slip by about M / vx "
                                "(a real tire's is of the order of its radius; the filter's model has no lag; "
                                "default 0)")
    imperfect.add_argument("--gnss-first", action="store_true",
                           help="log each GNSS message before the steering sample of the same instant")
    enc = parser.add_argument_group("message types, frames, topics and drivers (issue #12)")
    enc.add_argument("--driver", choices=sorted(DRIVERS),
                     help="write a real GNSS driver's shape (the flags below override it): "
                     + "; ".join(f"{name}: {shape.description}" for name, shape in DRIVERS.items()).replace("%", "%%"))
    enc.add_argument("--velocity-type", choices=VELOCITY_TYPES,
                     help="TwistStamped, TwistWithCovarianceStamped or nav_msgs/Odometry (twist in body axes) "
                     "(default twist)")
    enc.add_argument("--heading-type", choices=HEADING_TYPES,
                     help="QuaternionStamped, sensor_msgs/Imu, PoseWithCovarianceStamped or nav_msgs/Odometry (on the "
                     "velocity topic, one message carries both), or none: one antenna, --params-out then sets "
                     "ekf.measurement course (default quaternion)")
    enc.add_argument("--steering-type", choices=("joint-state", "float64", "float32"),
                     help="sensor_msgs/JointState, std_msgs/Float64 or std_msgs/Float32 (default joint-state)")
    enc.add_argument("--velocity-frame", choices=("enu", "ned"),
                     help="linear.x/y = east/north (enu) or north/east (ned) (default enu)")
    enc.add_argument("--heading-frame", choices=("enu", "ned"),
                     help="ENU yaw (enu) or compass heading clockwise from north (ned) (default enu)")
    enc.add_argument("--heading-lag", metavar="S", type=float,
                     help="heading stamped S after its epoch's velocity, as on arrival (default 0)")
    enc.add_argument("--heading-lag-jitter", metavar="S", type=float, help="+- uniform spread of the lag (default 0)")
    enc.add_argument("--heading-offset", metavar="RAD", type=float,
                     help="yaw of the heading source relative to the vehicle x axis (default 0)")
    enc.add_argument("--invalid-fraction", metavar="F", type=float,
                     help="share of GNSS epochs written with the driver's invalid marker (default 0)")
    enc.add_argument("--invalid-marker", choices=("nan", "covariance"),
                     help="nan: NaN velocity and orientation; covariance: zero velocity with covariance[0] = -1")
    enc.add_argument("--report-noise", action="store_const", const=True,
                     help="every GNSS message reports the noise applied to it as its covariance (all types "
                     "that have one); --params-out then sets ekf.measurement_noise_from_covariance")
    enc.add_argument("--velocity-topic", metavar="TOPIC", help="(default /gnss/vel)")
    enc.add_argument("--heading-topic", metavar="TOPIC", help="(default /gnss/heading)")
    enc.add_argument("--steering-topic", metavar="TOPIC", help="(default /steering_angle)")
    enc.add_argument("--joint-name", metavar="NAME", help="JointState joint name (default front_steering)")
    enc.add_argument("--params-out", metavar="P.yaml",
                     help="write the estimator parameters that read this bag (topics, types, frames, gnss.delay, "
                     "heading offset, lever arm); layer it over config/estimator.yaml")
    enc.add_argument("--start-time", metavar="SEC", type=float, default=1_700_000_000.0,
                     help="bag time of simulation time 0, s since the epoch (default 1700000000)")
    enc.add_argument("--no-truth", action="store_true", help="leave out the /sim/* ground truth topics")
    enc.add_argument("--compress", action="store_true", help="zstd-compress the MCAP chunks")
    parser.add_argument("--force", action="store_true", help="replace BAG_DIR if it exists")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    return parser


def _encoding(args: argparse.Namespace) -> dict[str, object]:
    """SimBagOptions fields: the driver's shape, overridden by the single flags given."""
    fields: dict[str, object] = dict(DRIVERS[args.driver].bag) if args.driver else {}
    fields.update({name: getattr(args, name) for name in ENCODING_OPTIONS if getattr(args, name) is not None})
    return fields


def _differs(key: str, value: object) -> bool:
    """Whether a parameter value differs from the schema default (message types compared by the type they name)."""
    from transplanter_ident.config.schema import PARAMS

    row = PARAMS[key]
    if row.choices:
        return row.match(str(value)) != row.match(str(row.default))
    return value != row.default


def _run(args: argparse.Namespace) -> int:
    from transplanter_ident.bags import SimBagOptions, reading_parameters, write_sim_bag
    from transplanter_ident.config.params_file import ParamsError
    from transplanter_ident.config.params_writer import write_params_yaml
    from transplanter_ident.sim.scenarios import build_config
    from transplanter_ident.sim.simulator import simulate

    delay = args.gnss_delay
    if delay is None and args.driver:
        delay = DRIVERS[args.driver].gnss_delay
    try:
        config = build_config(args.scenario, duration=args.duration, seed=args.seed, speed=args.speed,
                              tire=args.tire, friction=args.friction, gnss_rate=args.gnss_rate,
                              steering_rate=args.steering_rate, antenna_x=args.antenna_x,
                              antenna_y=args.antenna_y, steering_offset=args.steering_offset,
                              gnss_delay=delay)
        if args.gnss_degraded:
            config = replace(config, gnss_degraded=tuple(args.gnss_degraded))
        if args.side_slope is not None:
            config = replace(config, bank_angle=args.side_slope)
        if args.steering_scale is not None:
            config = replace(config, steering_scale=args.steering_scale)
        if args.steering_play is not None:
            config = replace(config, steering_play=args.steering_play)
        if args.relaxation_length is not None:
            config = replace(config, relaxation_length=args.relaxation_length)
        if args.gnss_correlation_time is not None:
            config = replace(config, noise=replace(config.noise, correlation_time=args.gnss_correlation_time))
        options = SimBagOptions(start_time=args.start_time, truth=not args.no_truth, compress=args.compress,
                                overwrite=args.force, gnss_first=args.gnss_first, seed=args.seed, **_encoding(args))
    except (ValueError, TypeError) as exc:
        raise CliError(f"invalid option: {exc}") from exc
    vehicle = config.vehicle
    reading = reading_parameters(options, gnss_delay=config.gnss_delay, antenna_x=vehicle.antenna_x,
                                 antenna_y=vehicle.antenna_y)
    result = simulate(config)
    count = write_sim_bag(result, args.output, options)
    shape = f", {args.driver} driver shape" if args.driver else ""
    print(f"simulate: wrote {args.output}: scenario {args.scenario}, {config.duration:g} s, {count} messages "
          f"({len(result.gnss_time)} GNSS epochs at {config.gnss_rate:g} Hz, {len(result.steering_time)} "
          f"steering samples at {config.steering_rate:g} Hz, {config.tire} tire, seed {config.seed}{shape})")
    if args.params_out:
        try:
            write_params_yaml(args.params_out, reading, f"Parameters that read {args.output} (simulate{shape}); "
                              "layer over config/estimator.yaml")
        except (OSError, ParamsError) as exc:
            raise CliError(f"{args.params_out}: cannot write: {exc}") from exc
        print(f"simulate: wrote {args.params_out}")
    changed = {key: value for key, value in reading.items() if _differs(key, value)}
    if changed:
        print("simulate: replay it with parameters matching the bag: "
              + ", ".join(f"{key} {value:g}" if isinstance(value, float) else f"{key} {value}"
                          for key, value in changed.items()))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `simulate` console script."""
    return cli_main(build_parser(), _run, argv)


if __name__ == "__main__":
    sys.exit(main())
