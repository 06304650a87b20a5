"""Helpers the subprocess benchmarks share: the executables, their environment, the cached bags."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def command(name: str) -> list[str]:
    """The installed executable ``name`` next to this interpreter, else ``python -m transplanter_ident.name``."""
    script = Path(sys.executable).parent / name
    return [str(script)] if script.exists() else [sys.executable, "-m", f"transplanter_ident.{name}"]


def child_env(**extra: str) -> dict[str, str]:
    """This environment with the repository on PYTHONPATH (plus ``extra``)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH", "")]))
    env.update(extra)
    return env


def default_cache() -> Path:
    """Where generated benchmark bags are kept: ``$TRANSPLANTER_BENCH_CACHE`` or <tmp>/transplanter_ident_bench."""
    return Path(os.environ.get("TRANSPLANTER_BENCH_CACHE", Path(tempfile.gettempdir()) / "transplanter_ident_bench"))


def cached_bag(cache: Path, name: str, simulate_args: list[str]) -> Path:
    """``cache/name``, written by ``simulate -o ... *simulate_args`` on first use."""
    bag = cache / name
    if (bag / "metadata.yaml").is_file():
        return bag
    cache.mkdir(parents=True, exist_ok=True)
    print(f"generating {bag} (once) ...", flush=True)
    subprocess.run([*command("simulate"), "-o", str(bag), *simulate_args, "--force"],
                   check=True, env=child_env(), cwd=ROOT, stdout=subprocess.DEVNULL)
    return bag
