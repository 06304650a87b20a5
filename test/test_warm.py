"""`warm` (cli/warm.py, run by `make venv`): after it, the tools' first runs compile nothing.

Checked as a user meets it: `warm` fills an empty numba cache folder (conftest's
``warmed_numba_cache``; this test works on a copy), then the tuner (its default worker pool
included), replay writing an output bag, and the node's warm-up run in a fresh process. numba's
compile events in that process, and the cache folder's files (a worker that compiled would add or
rewrite some), show whether anything was compiled. Not timed: ``bench/tuner_bench.py`` times the
tuner's first run after `warm`.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHECK = """
import json, sys
from numba.core import event
from transplanter_ident.cli import replay, tuner
from transplanter_ident.config.params_file import EstimatorParams
from transplanter_ident.ekf.joint_ekf import warm_up
bag, out = sys.argv[1], sys.argv[2]
with event.install_recorder("numba:compile") as recorder:
    codes = [tuner.main([bag, "-o", out + "/tuned.yaml", "--particles", "4", "--iterations", "2", "--seed", "3",
                         "--no-epoch-cache"]),
             replay.main([bag, "-o", out + "/replayed", "--csv", out + "/replay.csv", "--quiet"])]
    warm_up(EstimatorParams().config)
compiled = sorted({e.data["dispatcher"].py_func.__qualname__ for _, e in recorder.buffer if e.is_start})
print(json.dumps({"codes": codes, "compiled": compiled}))
"""


def _files(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in folder.rglob("*") if p.is_file()}


def test_after_warm_the_tuner_replay_and_node_compile_nothing(warmed_numba_cache: Path, tmp_path: Path) -> None:
    cache = shutil.copytree(warmed_numba_cache, tmp_path / "numba_cache")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    filled = _files(cache)
    assert any(name.endswith(".nbc") for name in filled), "warm cached no kernel"

    out = tmp_path / "out"
    out.mkdir()
    run = subprocess.run([sys.executable, "-c", CHECK, str(ROOT / "bags" / "sine"), str(out)],
                         capture_output=True, text=True, env=env, cwd=ROOT, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert report["codes"] == [0, 0]
    assert report["compiled"] == [], f"compiled after warm: {report['compiled']}"
    assert _files(cache) == filled, "a process (a tuner worker?) compiled and cached a kernel after warm"
    assert (out / "tuned.yaml").is_file() and (out / "replay.csv").is_file()
