"""Fixtures shared by several test modules."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def warmed_numba_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An empty numba cache folder that ``python -m transplanter_ident.cli.warm`` filled (what `make venv` does).

    Compiled once per session (~70 s) and never written again: a test that loads from it works on a copy.
    """
    cache = tmp_path_factory.mktemp("numba_cache_warmed")
    result = subprocess.run([sys.executable, "-m", "transplanter_ident.cli.warm"], capture_output=True, text=True,
                            env={**os.environ, "NUMBA_CACHE_DIR": str(cache)}, cwd=ROOT, timeout=900)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "numba's cache is filled" in result.stdout
    return cache
