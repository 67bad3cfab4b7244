"""The interop tests' stock nodes are what someone else would write: rclpy, the ROS 2 message
packages, numpy and the standard library, never this repository's code."""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

NODES = Path(__file__).resolve().parent / "nodes"
ALLOWED = {"rclpy", "std_msgs", "builtin_interfaces", "sensor_msgs", "nav_msgs", "geometry_msgs", "diagnostic_msgs",
           "visualization_msgs", "numpy", "stock_common"} | set(sys.stdlib_module_names)


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            names.add("." if node.level else node.module.split(".")[0])
    return names


@pytest.mark.parametrize("script", sorted(p.name for p in NODES.glob("*.py")))
def test_a_stock_node_imports_only_ros_2_numpy_and_the_standard_library(script):
    foreign = _imports(NODES / script) - ALLOWED
    assert not foreign, f"{script} imports {sorted(foreign)}"


def test_the_check_finds_this_repositorys_code(tmp_path):
    script = tmp_path / "node.py"
    script.write_text("import rclpy\nimport hil_sim.cli\nfrom runtime.io.ros import messages\nfrom . import x\n")
    assert _imports(script) - ALLOWED == {"hil_sim", "runtime", "."}
