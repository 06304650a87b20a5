"""The `estimator` executable: command line, executor and the spin loop around :class:`EstimatorNode`.

    estimator [--executor events|single] --ros-args --params-file config/estimator.yaml [...]

Exit codes: 0 after Ctrl-C / SIGTERM, 1 when the node cannot start (a bad or unknown parameter,
an unreadable or malformed parameters file, an invalid topic name, an unwritable latency log), with
one log line that names the cause (and the file and key). The ``--params-file`` files are checked
before ``rclpy.init`` parses them (:mod:`.startup`); a signal is a request that the spin loop honours
between two callbacks, so an epoch is never published half-way.
"""

from __future__ import annotations

import argparse
import gc
import sys
from typing import Any

import rclpy
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
    NameValidationException,
)
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.signals import SignalHandlerOptions

from transplanter_ident.config.params_file import ParamsError
from transplanter_ident.files import one_line
from transplanter_ident.jit import load_cached_kernels_lean
from transplanter_ident.ros.node import NODE_NAME, EstimatorNode
from transplanter_ident.ros.startup import StopSignals, check_params_files

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


#: what makes the node refuse to start: one line each, exit code 1
START_ERRORS = (ParamsError, InvalidParameterValueException, InvalidParameterTypeException, NameValidationException,
                OSError, rclpy_implementation.RCLError)


def _cannot_start(exc: BaseException) -> int:
    rclpy.logging.get_logger(NODE_NAME).fatal(f"cannot start: {one_line(exc)}")
    return 1


def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C / SIGTERM; returns the process exit code."""
    args = list(sys.argv[1:] if argv is None else argv)
    split = args.index("--ros-args") if "--ros-args" in args else len(args)
    try:
        options = build_parser().parse_args(args[:split])
    except SystemExit as exc:
        return int(exc.code or 0)
    stop = StopSignals().install()
    load_cached_kernels_lean()  # the node only runs the filter: ~23 MB less (see its docstring)
    try:
        check_params_files(args[split:], NODE_NAME)
        rclpy.init(args=["estimator", *args[split:]], signal_handler_options=SignalHandlerOptions.NO)
    except (ParamsError, rclpy_implementation.RCLError) as exc:
        return _cannot_start(exc)
    node = None
    try:
        node = EstimatorNode()
        executor = make_executor(options.executor)
        executor.add_node(node)
        gc.collect()
        gc.freeze()  # the ~10^5 start-up objects (rclpy, numba) never die: keep the collector off them
        # not executor.spin(): in rclpy 7.1 EventsExecutor.spin() busy-waits and serves nothing
        while rclpy.ok() and stop.requested is None:
            executor.spin_once(timeout_sec=SPIN_PERIOD)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except START_ERRORS as exc:
        if node is None:
            return _cannot_start(exc)
        raise
    finally:
        _shut_down(node)
    return 0


def _shut_down(node: EstimatorNode | None) -> None:
    """Destroy the node and the context; a second Ctrl-C meanwhile only shortens the wait for acknowledgements."""
    try:
        if node is not None:
            node.destroy_node()
    except KeyboardInterrupt:
        pass
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
