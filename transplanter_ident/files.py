"""Atomic output files and directories, one-line messages and coarse progress (DESIGN.md section 6).

* :func:`atomic_write_text`, :func:`atomic_output_file` and :func:`atomic_output_dir` write
  output files and directories atomically: into a temporary name in the target's directory,
  then ``os.replace``; on failure the temporary is removed and the target is untouched.
* :func:`one_line` squeezes a message to one line; :class:`Progress` prints coarse progress of
  long jobs to stderr.
* :class:`OptionalOutput` is an optional append-only text output (the node's latency log) that
  an I/O error (a full disk) disables, with the reason kept, instead of killing its writer.

No ROS and no numerics: every layer that writes a file uses these.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, TextIO


class OutputError(ValueError):
    """An output path that cannot be written (message fit for the user, one line)."""


def one_line(message: object) -> str:
    """Collapse a message to a single line (no newlines, runs of whitespace squeezed)."""
    return " ".join(str(message).split())



@contextlib.contextmanager
def atomic_output_file(path: str | Path, mode: str = "w", *, encoding: str | None = "utf-8",
                       newline: str | None = None) -> Iterator[IO]:
    """Open a temporary file beside ``path``; on success fsync it and rename it over ``path``.

    ``mode`` is ``"w"`` or ``"wb"``. On any exception the temporary file is removed and
    ``path`` is left as it was. An existing target keeps its permission bits.
    """
    target = Path(path)
    if target.is_dir():
        raise OutputError(f"{target}: is a directory, cannot write a file there")
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{target}: directory {parent} does not exist")
    file_mode = target.stat().st_mode & 0o777 if target.is_file() else 0o644
    fd, tmp = tempfile.mkstemp(dir=parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        binary = "b" in mode
        with os.fdopen(fd, mode, **({} if binary else {"encoding": encoding, "newline": newline})) as handle:
            os.fchmod(handle.fileno(), file_mode)
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically (temporary file, then rename)."""
    with atomic_output_file(path, "w") as handle:
        handle.write(text)


@contextlib.contextmanager
def atomic_output_dir(path: str | Path, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a not-yet-existing path to build a directory at; move it to ``path`` on success.

    The directory is built under a temporary parent in ``path``'s directory, so the final
    name inside (for example a rosbag2 directory's ``<name>.mcap``) is already right. An
    existing ``path`` is an error unless ``overwrite``; then it is replaced only after the
    new directory is complete. On failure nothing at ``path`` changes.
    """
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if target.exists() and not overwrite:
        raise OutputError(f"{target}: already exists (choose another path, or remove it first)")
    if not parent.is_dir():
        raise OutputError(f"{target}: directory {parent} does not exist")
    staging = Path(tempfile.mkdtemp(dir=parent, prefix=f".{target.name}.", suffix=".tmp"))
    try:
        built = staging / target.name
        yield built
        if not built.exists():
            raise OutputError(f"{target}: nothing was written")
        if target.exists():
            old = staging / (target.name + ".old")
            os.replace(target, old)
        os.replace(built, target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


# --------------------------------------------------------------------------- optional outputs


class OptionalOutput:
    """An append-only text file that is nice to have: the first I/O error closes it and keeps the reason.

    Opening it (the constructor) raises OSError as usual, so a wrong path is refused at start-up;
    later, :meth:`write` and :meth:`flush` never raise: after a failure they do nothing, and
    :attr:`error` says why (``No space left on device``).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.error: str | None = None
        self._handle: TextIO | None = open(self.path, "a", encoding="utf-8")  # noqa: SIM115 - closed in close()

    @property
    def active(self) -> bool:
        return self._handle is not None

    def write(self, text: str) -> None:
        if self._handle is not None:
            try:
                self._handle.write(text)
            except OSError as exc:
                self._fail(exc)

    def flush(self) -> None:
        if self._handle is not None:
            try:
                self._handle.flush()
            except OSError as exc:
                self._fail(exc)

    def close(self) -> None:
        handle, self._handle = self._handle, None
        if handle is not None:
            try:
                handle.close()
            except OSError as exc:
                self.error = self.error or (exc.strerror or one_line(exc))

    def _fail(self, exc: OSError) -> None:
        self.error = exc.strerror or one_line(exc)
        handle, self._handle = self._handle, None
        try:
            handle.close()
        except OSError:
            pass  # the buffer that failed to flush fails again: the output is off either way


# --------------------------------------------------------------------------- progress


class Progress:
    """Coarse progress on stderr: a line at every ``step`` fraction of ``total``.

    Silent for small jobs: it reports only when ``total`` exceeds ``min_total`` and stderr is
    a terminal, or always when ``total`` exceeds ``always_total``. Call :meth:`update` with
    the running count (cheap: one comparison per call) and :meth:`done` at the end.
    """

    def __init__(self, total: int, label: str, *, stream: TextIO | None = None, step: float = 0.1,
                 min_total: int = 10_000, always_total: int = 100_000) -> None:
        self.total = max(int(total), 0)
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        isatty = getattr(self.stream, "isatty", lambda: False)()
        self.enabled = self.total > always_total or (self.total > min_total and isatty)
        self._step = max(1, int(self.total * step))
        #: the count at which the next line is due (callers in hot loops may compare against it)
        self.next_at = self._step if self.enabled else sys.maxsize
        self._start = time.monotonic()

    def update(self, count: int) -> None:
        """Report if ``count`` has passed the next reporting point."""
        if count >= self.next_at:
            self._report(count)
            while self.next_at <= count:
                self.next_at += self._step

    def _report(self, count: int) -> None:
        percent = 100.0 * count / self.total if self.total else 100.0
        elapsed = time.monotonic() - self._start
        print(f"{self.label}: {min(percent, 100.0):3.0f} % ({count}/{self.total}, {elapsed:.1f} s)",
              file=self.stream, flush=True)

    def done(self) -> None:
        """Final line (only when enabled)."""
        if self.enabled:
            elapsed = time.monotonic() - self._start
            print(f"{self.label}: done ({elapsed:.1f} s)", file=self.stream, flush=True)
            self.enabled = False
            self.next_at = sys.maxsize
