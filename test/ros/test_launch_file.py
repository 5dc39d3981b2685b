"""The `ros2 launch` file: it names only executables the package installs, and builds its nodes where the
`launch` packages are importable (a full ROS 2 install; not in the project's venv, where this is skipped)."""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_launch_file_names_installed_executables():
    text = (ROOT / "launch" / "orchard_graph.launch.py").read_text()
    ast.parse(text)
    used = set(re.findall(r'executable="([a-z_]+)"', text))
    scripts = set(re.findall(r'"([a-z_]+) = orchard_mapping\.ros\.', (ROOT / "setup.py").read_text()))
    assert used and used <= scripts, (used, scripts)


def test_launch_description_builds():
    pytest.importorskip("launch_ros")
    import importlib.util

    spec = importlib.util.spec_from_file_location("orchard_graph_launch", ROOT / "launch" / "orchard_graph.launch.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.generate_launch_description().entities
