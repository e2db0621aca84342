"""morph_core is ROS-free: no module in it imports rclpy or any ROS message package."""

import ast
import pathlib
import subprocess
import sys

import pytest

import morph_core

ROS_MODULES = (
    "rclpy",
    "rosidl",
    "rcl_interfaces",
    "builtin_interfaces",
    "std_msgs",
    "sensor_msgs",
    "nav_msgs",
    "geometry_msgs",
    "rosgraph_msgs",
    "trajectory_msgs",
    "std_srvs",
    "launch",
    "ament_index_python",
)
CORE = pathlib.Path(morph_core.__file__).parent


def _imported_modules(path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield node.module


def test_no_ros_import_in_source():
    files = sorted(CORE.rglob("*.py"))
    assert len(files) >= 20 and any(f.parent != CORE for f in files)  # the subpackages are scanned
    offenders = [
        (str(f.relative_to(CORE)), mod)
        for f in files
        for mod in _imported_modules(f)
        if mod.split(".")[0] in ROS_MODULES
    ]
    assert offenders == []


@pytest.mark.slow
def test_importing_every_core_module_loads_no_ros():
    modules = sorted(
        ".".join(("morph_core", *f.relative_to(CORE).with_suffix("").parts)).removesuffix(".__init__")
        for f in CORE.rglob("*.py")
    )
    assert "morph_core.algo.train" in modules and "morph_core.msgs.joint_state" in modules
    code = (
        "import importlib, sys\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        f"print(sorted(k for k in sys.modules if k.split('.')[0] in {ROS_MODULES!r}))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
