"""The colcon layout `ros2 run` and `ros2 launch` need (DESIGN.md sections 3 and 4).

`colcon build` (colcon-common-extensions from PyPI, in the venv) on a copy of the package must
put the five executables in install/transplanter_ident/lib/transplanter_ident/, register the
package in the ament index, and install config/ and launch/ under share/transplanter_ident.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "transplanter_ident"
EXECUTABLES = ("estimator", "tuner", "replay", "simulate", "warm")
SOURCES = ("setup.py", "setup.cfg", "package.xml", "resource", "config", "launch", PACKAGE)


def colcon() -> Path:
    path = Path(sys.executable).parent / "colcon"
    if not path.is_file():
        pytest.skip(f"colcon is not installed next to {sys.executable} (make venv installs it)")
    return path


@pytest.fixture(scope="module")
def install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Build a copy of the package with `colcon build`; returns the install base."""
    exe = colcon()
    base = tmp_path_factory.mktemp("colcon")
    source = base / "src" / PACKAGE  # colcon and setuptools write egg-info into the source: use a copy
    source.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc", "*.egg-info")
    for name in SOURCES:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, source / name, ignore=ignore)
        else:
            shutil.copy2(src, source / name)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("AMENT_", "COLCON_"))}
    env["COLCON_HOME"] = str(base / "colcon_home")  # no user defaults/mixins
    started = time.monotonic()
    result = subprocess.run(
        [str(exe), "--log-base", str(base / "log"), "build", "--base-paths", str(base / "src"),
         "--build-base", str(base / "build"), "--install-base", str(base / "install"),
         "--event-handlers", "console_direct-"],
        cwd=base, env=env, capture_output=True, text=True, timeout=180)
    elapsed = time.monotonic() - started
    assert result.returncode == 0, result.stdout[-5000:] + result.stderr[-5000:]
    assert elapsed < 60.0, f"colcon build took {elapsed:.0f} s"
    return base / "install"


def test_executables_are_where_ros2_run_looks(install: Path) -> None:
    lib = install / PACKAGE / "lib" / PACKAGE
    for name in EXECUTABLES:
        path = lib / name
        assert path.is_file(), f"{path} missing; lib holds {sorted(p.name for p in lib.iterdir())}"
        assert os.access(path, os.X_OK), f"{path} is not executable"


def test_share_holds_config_launch_and_manifest(install: Path) -> None:
    share = install / PACKAGE / "share" / PACKAGE
    assert (share / "package.xml").is_file()
    assert (share / "config" / "estimator.yaml").is_file()
    assert (share / "launch" / "estimator.launch.py").is_file()
    assert (install / PACKAGE / "share" / "ament_index" / "resource_index" / "packages" / PACKAGE).is_file()


def _installed_env(install: Path) -> dict[str, str]:
    prefix = install / PACKAGE
    site = next((prefix / "lib").glob("python3*/site-packages"))
    env = dict(os.environ)
    env["AMENT_PREFIX_PATH"] = os.pathsep.join([str(prefix), env.get("AMENT_PREFIX_PATH", "")]).rstrip(os.pathsep)
    env["PYTHONPATH"] = str(site)  # the installed copy, not the source tree
    return env


def test_ament_index_finds_the_package(install: Path) -> None:
    code = ("from ament_index_python.packages import get_package_prefix, get_package_share_directory\n"
            f"print(get_package_prefix('{PACKAGE}')); print(get_package_share_directory('{PACKAGE}'))")
    result = subprocess.run([sys.executable, "-c", code], env=_installed_env(install), capture_output=True,
                            text=True, timeout=60, cwd=install)
    assert result.returncode == 0, result.stderr
    prefix, share = result.stdout.split()
    assert Path(prefix) == install / PACKAGE
    assert Path(share) == install / PACKAGE / "share" / PACKAGE


def test_installed_executables_run(install: Path) -> None:
    """What `ros2 run transplanter_ident <exe> -h` would do: run the installed script from its prefix."""
    lib = install / PACKAGE / "lib" / PACKAGE
    env = _installed_env(install)
    for name in EXECUTABLES:
        result = subprocess.run([str(lib / name), "-h"], env=env, capture_output=True, text=True, timeout=120,
                                cwd=install)
        assert result.returncode == 0, (name, result.stderr)
        assert f"usage: {name}" in result.stdout
    where = subprocess.run([sys.executable, "-c", f"import {PACKAGE}; print({PACKAGE}.__file__)"], env=env,
                           capture_output=True, text=True, timeout=60, cwd=install)
    assert str(install) in where.stdout, where.stdout + where.stderr
