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
SCRIPTS = ("estimator", "tuner", "replay", "simulate")


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
