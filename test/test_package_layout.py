"""Tests of the package layout: console scripts answer -h, package.xml and setup files agree."""

from __future__ import annotations

import configparser
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

import transplanter_ident

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ("estimator", "tuner", "replay", "simulate", "warm")


@pytest.mark.parametrize("name", SCRIPTS)
def test_console_script_help_exits_zero(name: str) -> None:
    script = Path(sys.executable).parent / name
    assert script.exists(), f"{script} is missing: install the package into this venv (make venv)"
    result = subprocess.run([str(script), "-h"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert f"usage: {name}" in result.stdout


def test_package_xml_names_the_package() -> None:
    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "transplanter_ident"
    assert root.findtext("version") == transplanter_ident.__version__
    assert root.findtext("export/build_type") == "ament_python"
    depends = {e.text for e in root.findall("exec_depend")}
    assert {"rclpy", "geometry_msgs", "sensor_msgs", "diagnostic_msgs", "python3-numpy"} <= depends


def test_ament_layout_files() -> None:
    assert (ROOT / "resource" / "transplanter_ident").is_file()
    assert (ROOT / "config" / "estimator.yaml").is_file()
    cfg = configparser.ConfigParser(interpolation=None)
    cfg.read(ROOT / "setup.cfg")
    assert cfg["develop"]["script_dir"] == "$base/lib/transplanter_ident"
    assert cfg["install"]["install_scripts"] == "$base/lib/transplanter_ident"


# --------------------------------------------------------------------------- the data flow in the folders

PACKAGE_DIR = ROOT / "transplanter_ident"
#: subpackages of the numerics: no ROS, no bag library, no plotting
NUMERIC = ("config", "epochs", "ekf", "sim", "evaluation", "tuning")
FORBIDDEN_IN_NUMERICS = ("rclpy", "rosbags", "matplotlib")
MAX_MODULE_LINES = 400


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(path: Path, *, top_level_only: bool) -> set[str]:
    import ast

    tree = ast.parse(path.read_text(encoding="utf-8"))
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    found: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def _subpackage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


@pytest.mark.parametrize("name", sorted(_modules()))
def test_no_module_is_over_the_line_limit(name: str) -> None:
    lines = len(_modules()[name].read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_MODULE_LINES, f"{name} has {lines} lines (limit {MAX_MODULE_LINES}): split it by concern"


def test_numerics_import_no_ros_bags_or_plotting() -> None:
    offenders = []
    for name, path in _modules().items():
        if _subpackage(name) in NUMERIC or name in ("transplanter_ident.files", "transplanter_ident.jit"):
            for imported in _imports(path, top_level_only=False):
                if imported.split(".")[0] in FORBIDDEN_IN_NUMERICS:
                    offenders.append(f"{name} imports {imported}")
    assert offenders == []


def test_only_ros_imports_rclpy_and_only_bags_import_rosbags() -> None:
    offenders = []
    for name, path in _modules().items():
        for imported in _imports(path, top_level_only=False):
            root = imported.split(".")[0]
            if root in ("rclpy",) and _subpackage(name) != "ros":
                offenders.append(f"{name} imports {imported}")
            if root == "rosbags" and _subpackage(name) != "bags":
                offenders.append(f"{name} imports {imported}")
    assert offenders == []


def test_libraries_do_not_import_command_line_modules() -> None:
    offenders = [f"{name} imports {imported}" for name, path in _modules().items() if _subpackage(name) != "cli"
                 for imported in _imports(path, top_level_only=False)
                 if imported.startswith("transplanter_ident.cli")]
    assert offenders == []


def test_no_import_cycles_between_modules_or_subpackages() -> None:
    modules = _modules()
    graph = {name: {m for m in _imports(path, top_level_only=True) if m in modules and m != name}
             for name, path in modules.items()}
    packages: dict[str, set[str]] = {}
    for name, deps in graph.items():
        packages.setdefault(_subpackage(name), set()).update(
            _subpackage(d) for d in deps if _subpackage(d) != _subpackage(name) and _subpackage(d))

    def find_cycle(g: dict[str, set[str]]) -> list[str]:
        state: dict[str, int] = {}
        stack: list[str] = []

        def visit(node: str) -> list[str]:
            state[node] = 1
            stack.append(node)
            for nxt in sorted(g.get(node, ())):
                if state.get(nxt) == 1:
                    return stack[stack.index(nxt):] + [nxt]
                if nxt not in state and (cycle := visit(nxt)):
                    return cycle
            state[node] = 2
            stack.pop()
            return []

        for node in sorted(g):
            if node not in state and (cycle := visit(node)):
                return cycle
        return []

    assert find_cycle(graph) == [], "module import cycle"
    assert find_cycle(packages) == [], "subpackage import cycle"


def test_the_filter_memo_slots_never_overlap() -> None:
    """Every memo slot of ekf/layout.py belongs to one name; the per-state blocks hold MAX_STATES slots.

    A block sized for fewer states than the largest filter (a state added to the layout) overwrote its
    neighbour in the lagged filter only: the std went NaN there (session 27, before this test).
    """
    from transplanter_ident.ekf import layout

    blocks = {"M_BIAS", "M_DELAY_BIAS", "M_SCALE_BIAS", "M_SPEED_CROSS", "M_INERTIA_BIAS", "M_RELAXATION_BIAS",
              "M_HEADING_BIAS", "M_PLAY_BIAS"}
    widths = {"M_SHIFT": layout.N_SHIFT, "M_SHIFT_POWER": 2, "M_SHIFT_LAG": 2, "M_SHIFT_LAST": 2,
              "M_CORRELATION_LAG": 2, "M_CORRELATION_POWER": 2, "M_CORRELATION_LAST": 2}
    owner: dict[int, str] = {}
    for name in (n for n in dir(layout) if n.startswith("M_")):
        start = getattr(layout, name)
        width = layout.MAX_STATES if name in blocks else widths.get(name, 1)
        for slot in range(start, start + width):
            assert slot not in owner, f"memo slot {slot}: {owner.get(slot)} and {name}"
            owner[slot] = name
    assert sorted(owner) == list(range(layout.N_MEMO))
