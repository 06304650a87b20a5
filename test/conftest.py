"""Fixtures shared by several test modules."""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def warmed_numba_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An empty numba cache folder that ``python -m transplanter_ident.cli.warm`` filled (what `make venv` does).

    Compiled once per run (~70-100 s), shared by pytest-xdist's workers (the first takes a file lock
    and fills it, the others wait for it), and never written again: a test that loads from it works
    on a copy.
    """
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, which every worker's base folder is in
    cache, filled = root / "numba_cache_warmed", root / "numba_cache_warmed.filled"
    with open(root / "numba_cache_warmed.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not filled.exists():
            shutil.rmtree(cache, ignore_errors=True)  # a worker that failed half way
            cache.mkdir()
            result = subprocess.run([sys.executable, "-m", "transplanter_ident.cli.warm"], capture_output=True,
                                    text=True, env={**os.environ, "NUMBA_CACHE_DIR": str(cache)}, cwd=ROOT,
                                    timeout=900)
            assert result.returncode == 0, result.stderr[-3000:]
            assert "numba's cache is filled" in result.stdout
            filled.touch()
    return cache
