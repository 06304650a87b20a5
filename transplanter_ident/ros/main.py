"""The `estimator` executable: command line, executor and the spin loop around :class:`EstimatorNode`.

    estimator [--executor events|single] --ros-args --params-file config/estimator.yaml [...]

Exit codes: 0 after Ctrl-C / SIGTERM, 1 when the node cannot start (a bad or unknown parameter,
an unwritable latency log), with one log line that names the cause.
"""

from __future__ import annotations

import argparse
import gc
import sys
from typing import Any

import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from transplanter_ident.config.params_file import ParamsError
from transplanter_ident.ros.node import NODE_NAME, EstimatorNode

EXECUTORS = ("events", "single")
SPIN_PERIOD = 0.5  # s; spin_once returns on work, on shutdown, or after this


def build_parser() -> argparse.ArgumentParser:
    """Command line of `estimator`; ROS arguments follow `--ros-args`."""
    parser = argparse.ArgumentParser(
        prog="estimator",
        description="Online cornering-stiffness estimator (ROS 2 node): GNSS velocity, heading and steering in, "
        "~/cornering_stiffness, ~/cornering_stiffness_std, ~/model_output, ~/measurement and /diagnostics out.",
        epilog="ROS arguments: estimator --ros-args --params-file config/estimator.yaml "
        "[--params-file tuned.yaml] [-r __ns:=/NS] [-p topics.velocity:=/gnss/vel ...] [-p use_sim_time:=true]. "
        "Every parameter, with its unit, range and default, is in transplanter_ident/config/schema.py.",
    )
    parser.add_argument("--executor", choices=EXECUTORS, default="events",
                        help="events: rclpy's EventsExecutor (rclpy.experimental; about half the CPU of the default "
                        "at 300 inputs/s); single: rclpy's SingleThreadedExecutor (default: %(default)s)")
    return parser


def make_executor(kind: str) -> Any:
    """The executor that spins the node: ``events`` (EventsExecutor) or ``single`` (SingleThreadedExecutor)."""
    if kind == "events":
        from rclpy.experimental import EventsExecutor

        return EventsExecutor()
    return SingleThreadedExecutor()


def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C / SIGTERM; returns the process exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    split = args.index("--ros-args") if "--ros-args" in args else len(args)
    try:
        options = build_parser().parse_args(args[:split])
    except SystemExit as exc:
        return int(exc.code or 0)
    rclpy.init(args=["estimator", *args[split:]])
    node = None
    try:
        node = EstimatorNode()
        executor = make_executor(options.executor)
        executor.add_node(node)
        gc.collect()
        gc.freeze()  # the ~10^5 start-up objects (rclpy, numba) never die: keep the collector off them
        while rclpy.ok():  # not executor.spin(): in rclpy 7.1 EventsExecutor.spin() busy-waits and serves nothing
            executor.spin_once(timeout_sec=SPIN_PERIOD)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ParamsError, InvalidParameterValueException, InvalidParameterTypeException, OSError) as exc:
        rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {exc}")
        return 1
    except Exception:
        if rclpy.ok():
            raise
        # a signal shut the context down between two waits (rclpy raises RCLError then): a clean stop
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
