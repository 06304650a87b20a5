"""Start-up and shutdown of the `estimator` process: parameter files checked first, signals as a request.

* :func:`check_params_files`: every ``--params-file`` of the ROS arguments is read with the offline
  loader (:func:`~transplanter_ident.config.params_file.read_params_file`: size and alias limits,
  UTF-8, a sealed tuner file cut short, a list that mixes integers and floats, unknown keys,
  types, ranges, topic names) *before* ``rclpy.init`` hands it to the rcl parser, so every error
  is one :class:`~transplanter_ident.config.params_file.ParamsError` naming the file and the key
  (rcl itself would end in a traceback, or name neither).
* :func:`optional_output_report`: the /diagnostics line of an optional output (the latency log),
  WARN once an I/O error (a full disk) has disabled it; the node carries on.
* :class:`StopSignals`: SIGINT and SIGTERM only set a flag that the spin loop checks between two
  callbacks. rclpy's own handlers shut the context down from another thread, which let a callback
  that was publishing an epoch fail half-way ("publisher's context is invalid", a FATAL callback
  exception) in 3 of 4 SIGTERMs under a message flood (issue #14).
"""

from __future__ import annotations

import signal
from collections.abc import Sequence
from types import FrameType

from transplanter_ident.config.params_file import ParamsError, flat_to_params, read_params_file
from transplanter_ident.evaluation.health_report import OK, WARN, HealthReport
from transplanter_ident.files import OptionalOutput

PARAMS_FILE_FLAG = "--params-file"


def params_files(ros_args: Sequence[str]) -> list[str]:
    """The files of ``--params-file FILE`` in the ROS arguments, in order."""
    files = []
    for i, arg in enumerate(ros_args):
        if arg == PARAMS_FILE_FLAG:
            if i + 1 >= len(ros_args):
                raise ParamsError(f"{PARAMS_FILE_FLAG} needs a file name")
            files.append(ros_args[i + 1])
    return files


def node_name(ros_args: Sequence[str], default: str) -> str:
    """The node's name after a ``-r __node:=NAME`` (or ``--remap``) remapping, else ``default``."""
    name = default
    for flag, value in zip(ros_args, ros_args[1:], strict=False):
        if flag in ("-r", "--remap") and value.split(":", 1)[-1].startswith("__node:="):
            name = value.rsplit(":=", 1)[1]
    return name


def check_params_files(ros_args: Sequence[str], default_name: str) -> None:
    """Read and validate each ``--params-file`` as the offline drivers do; ParamsError names the file and key.

    A file with no section for this node (``/**``, ``NAME`` or ``/NAME``) passes: rcl applies none of it.
    """
    name = node_name(ros_args, default_name)
    for path in params_files(ros_args):
        try:
            flat = read_params_file(path, name, require_section=False)
            flat_to_params(flat)
        except ParamsError as exc:
            message = str(exc)
            raise ParamsError(message if message.startswith(f"{path}:") else f"{path}: {message}", exc.key) from None


class StopSignals:
    """SIGINT/SIGTERM set :attr:`requested`; a second one raises KeyboardInterrupt (a stuck shutdown)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested: str | None = None  # the name of the first signal received

    def install(self) -> StopSignals:
        """Take over SIGINT and SIGTERM in this (main) thread; returns self."""
        for signum in self.SIGNALS:
            signal.signal(signum, self._handle)
        return self

    def _handle(self, signum: int, _frame: FrameType | None) -> None:
        if self.requested is not None:
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name


def optional_output_report(name: str, output: OptionalOutput) -> HealthReport:
    """OK while ``output`` writes, WARN with the reason once an I/O error has disabled it."""
    values = (("path", str(output.path)), ("active", str(output.active).lower()), ("error", output.error or ""))
    if output.error is not None:
        return HealthReport(name, WARN, f"disabled after an I/O error writing {output.path}: {output.error} "
                            "(estimation goes on)", values)
    return HealthReport(name, OK, f"writing {output.path}", values)
