"""The numba disk cache gives the right kernel for each state size (issue #9, item 5).

The per-size closures are not cached (numba keys a cached closure by name and source line, which
every size shares); the module-level entries are. Here one cache folder that `warm` filled with the
kernels of both state sizes (conftest's ``warmed_numba_cache``, a copy) is loaded back, in
alternating orders, in separate processes: every run must give the numbers of the same code run
as plain Python (``NUMBA_DISABLE_JIT=1``, no cache involved).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

PROGRAM = """
import json, sys
sys.path.insert(0, {test!r})
from helpers import simulate_epochs
from transplanter_ident.config.parameters import EstimatorConfig, FilterOptions
from transplanter_ident.ekf.joint_ekf import run_sequence, sequence_objective
from transplanter_ident.sim.simulator import SimConfig
_, epochs = simulate_epochs(SimConfig(duration=20.0, seed=1))
values = {{}}
for measurement in sys.argv[1].split(","):
    config = EstimatorConfig(options=FilterOptions(measurement=measurement))
    values[measurement] = [sequence_objective(config, epochs, "nll"), float(run_sequence(config, epochs)[-1, 3])]
print(json.dumps(values))
"""


def run(order: str, cache: Path | None, program: str = PROGRAM) -> dict:
    """The JSON line ``program`` prints, run with ``order`` in a fresh process on the numba cache ``cache``.

    ``cache`` None: numba's compiler off (``NUMBA_DISABLE_JIT=1``), the kernels run as Python.
    """
    extra = {"NUMBA_CACHE_DIR": str(cache)} if cache is not None else {"NUMBA_DISABLE_JIT": "1"}
    env = {**os.environ, **extra, "PYTHONPATH": str(ROOT)}
    result = subprocess.run([sys.executable, "-c", program.format(test=str(ROOT / "test")), order],
                            capture_output=True, text=True, timeout=900, env=env, cwd=ROOT)
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_both_state_sizes_load_their_own_kernels_from_one_cache_folder(warmed_numba_cache: Path,
                                                                      tmp_path: Path) -> None:
    cache = shutil.copytree(warmed_numba_cache, tmp_path / "numba-cache")
    assert any(cache.rglob("*.nbi")), "nothing was cached"
    python = run("heading,yaw_rate", None)  # the reference: the same code as plain Python
    assert python["heading"] != python["yaw_rate"]  # the two filters do differ, so a mix-up would show
    for order in ("heading,yaw_rate", "yaw_rate,heading", "heading", "yaw_rate"):  # loaded back, alternately
        loaded = run(order, cache)
        for measurement, values in loaded.items():
            assert values == pytest.approx(python[measurement], rel=1e-12, abs=0.0), (order, measurement)


LEAN_PROGRAM = """
import json, sys
sys.path.insert(0, {test!r})
from transplanter_ident.jit import load_cached_kernels_lean
lean = sys.argv[1] == "lean" and load_cached_kernels_lean()
from helpers import simulate_epochs
from transplanter_ident.config.parameters import EstimatorConfig
from transplanter_ident.ekf.joint_ekf import JointEKF
from transplanter_ident.sim.simulator import SimConfig
_, epochs = simulate_epochs(SimConfig(duration=20.0, seed=2))
ekf = JointEKF(EstimatorConfig())
rows = [[e.cornering_stiffness_front, e.cornering_stiffness_rear, e.cornering_stiffness_front_std,
         e.cornering_stiffness_rear_std, e.steering_offset] for e in map(ekf.step, epochs)]
print(json.dumps({{"lean": lean, "registries": "numba.np.linalg" in sys.modules, "rows": rows}}))
"""


def test_the_nodes_lean_loading_gives_the_same_filter(warmed_numba_cache: Path, tmp_path: Path) -> None:
    """load_cached_kernels_lean (the node's): the same numbers from the cache, and when the step is missing.

    From a filled cache (`warm`'s, a copy) it skips numba's registries (what saves the memory); on a
    cache miss numba compiles as usual: here the angle wrap (the simulator's heading, the filter's
    innovation) is missing, and the others are loaded lean (a partial miss, for which the compiler
    must refresh numba's context itself; a whole cold cache compiled everything and took a minute).
    """
    cache = shutil.copytree(warmed_numba_cache, tmp_path / "cache")
    plain = run("plain", cache, LEAN_PROGRAM)
    lean = run("lean", cache, LEAN_PROGRAM)
    assert lean["lean"] and not lean["registries"] and plain["registries"]
    assert lean["rows"] == plain["rows"] and len(plain["rows"]) > 50
    partial = shutil.copytree(warmed_numba_cache, tmp_path / "partial-cache")
    wrap_files = list(partial.rglob("frames.wrap_angle-*"))
    assert wrap_files, "warm cached no angle wrap"
    for path in wrap_files:
        path.unlink()
    missed = run("lean", partial, LEAN_PROGRAM)
    assert missed["lean"] and missed["rows"] == plain["rows"]
    assert list(partial.rglob("frames.wrap_angle-*.nbi")), "the missing kernel was not compiled into the cache"


def test_each_variant_of_a_factory_kernel_has_a_name_of_its_own() -> None:
    """Cached entries compiled by different processes must never define one symbol for two sizes.

    numba names a function's symbol by its qualified name and a per-process counter, so two
    processes can both emit ``run_n$2``, one per size; a process loading both entries then calls one
    size's code with the other's arrays (heap corruption in ``make demo``, session 14). The
    factories' kernels are renamed after their variant (jit._variant_named), the same in every process.
    """
    from transplanter_ident.ekf import entries, model
    from transplanter_ident.jit import sized_kernel

    pairs = [(entries._run_heading, entries._run_yaw_rate), (entries._step_heading, entries._step_yaw_rate),
             (entries._objective_heading, entries._objective_yaw_rate),
             (model.discretize_heading, model.discretize_yaw_rate)]
    for heading, yaw_rate in pairs:
        assert heading.py_func.__qualname__ != yaw_rate.py_func.__qualname__, heading.py_func.__qualname__

    def factory(size: int):  # noqa: ANN202
        @sized_kernel
        def kernel(x):  # noqa: ANN001, ANN202
            return x * size

        return kernel

    names = [factory(size).py_func.__qualname__ for size in (5, 6, 5)]
    assert names[0] != names[1] and names[0] == names[2]  # per variant, and the same when made again
