"""Shared plumbing of the command-line tools (replay, simulate, tuner): errors, atomic output, progress.

No ROS and no numerics here; every CLI uses the same three pieces:

* :func:`run_cli` runs a command body and turns any exception into one line on stderr,
  ``<prog>: error: <message>``, and a non-zero exit code (DESIGN.md section 6). With
  ``debug=True`` the traceback is printed first. Typical use::

      def main(argv=None) -> int:
          parser = build_parser()
          args = parser.parse_args(argv)
          return run_cli(parser.prog, lambda: _run(args), debug=args.debug)

  Raise :class:`CliError` (or any ``ValueError``/``OSError`` with a clear message, such as
  ``bag_io.BagError`` or ``params_file.ParamsError``) for expected failures; anything else is
  reported as an internal error that names its exception type.
* atomic output and progress live in :mod:`transplanter_ident.files`.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from collections.abc import Callable
from typing import TextIO

from transplanter_ident.files import one_line

#: exit code of a failed command (argparse uses 2 for usage errors)
EXIT_FAILURE = 1
#: exit code after Ctrl-C
EXIT_INTERRUPTED = 130


class CliError(Exception):
    """An expected failure with a message fit for the user (one line)."""


def _describe(exc: BaseException) -> str:
    text = one_line(exc)
    if isinstance(exc, (CliError, ValueError)) and text:
        return text
    if isinstance(exc, OSError) and exc.strerror:
        name = exc.filename if exc.filename is not None else ""
        return f"{name}: {exc.strerror}" if name else exc.strerror
    if isinstance(exc, MemoryError):
        return "out of memory"
    kind = type(exc).__name__
    return f"internal error: {kind}: {text} (run with --debug for the traceback)" if text else (
        f"internal error: {kind} (run with --debug for the traceback)")


def run_cli(prog: str, body: Callable[[], int | None], *, debug: bool = False,
            stderr: TextIO | None = None) -> int:
    """Run ``body`` and return its exit code (None counts as 0).

    Any exception ends as ``<prog>: error: <one-line message>`` on stderr and exit code 1
    (130 after Ctrl-C), with no traceback unless ``debug``. ``SystemExit`` passes through.
    """
    err = stderr if stderr is not None else sys.stderr
    try:
        code = body()
        return 0 if code is None else int(code)
    except SystemExit:
        raise
    except KeyboardInterrupt:
        if debug:
            traceback.print_exc(file=err)
        print(f"{prog}: interrupted", file=err)
        return EXIT_INTERRUPTED
    except BaseException as exc:  # noqa: BLE001 - the point is to catch everything
        if debug:
            traceback.print_exc(file=err)
        print(f"{prog}: error: {_describe(exc)}", file=err)
        return EXIT_FAILURE


def cli_main(parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace], int | None],
             argv: list[str] | None = None) -> int:
    """Parse ``argv`` and run ``run(args)`` under :func:`run_cli` (the parser has ``--debug``)."""
    args = parser.parse_args(argv)
    return run_cli(parser.prog, lambda: run(args), debug=args.debug)


# --------------------------------------------------------------------------- atomic output
