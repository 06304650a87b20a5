"""``tuner --report DIR``: the report folder, staged and moved into place whole, or not at all.

An existing DIR is replaced only if it is empty or an earlier report (its files only, REPORT_NAMES):
never a folder of other files (``--report .``).
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from pathlib import Path

from transplanter_ident.cli.util import CliError
from transplanter_ident.files import atomic_output_dir

#: an existing ``--report`` folder holding only such files (an earlier report) may be replaced
REPORT_NAMES = re.compile(r"fig\d[\w.-]*\.png|report\.txt|leave_one_out\.txt")


@contextlib.contextmanager
def report_folder(path: str | None) -> Iterator[Path | None]:
    """A staging folder for ``--report DIR``, moved to DIR on success; None without ``--report``.

    An existing DIR is replaced only if it is empty or an earlier report (its files only): never a
    folder of other files (``--report .``).
    """
    if path is None:
        yield None
        return
    check_report_path(path)
    with atomic_output_dir(path, overwrite=True) as staged:
        yield staged


def check_report_path(path: str) -> None:
    """CliError if ``--report DIR`` cannot be written, or would replace something that is not a report."""
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if target.exists() and (not target.is_dir() or any(not REPORT_NAMES.fullmatch(p.name) for p in target.iterdir())):
        raise CliError(f"{target}: exists and is not an earlier report; choose a new folder for --report")
    if not parent.is_dir():
        raise CliError(f"{target}: directory {parent} does not exist")
