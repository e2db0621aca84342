"""``colcon build`` of the workspace, as a ROS user builds it, and what the install tree must hold.

colcon-core with colcon-ros (requirements-dev.txt) identifies each package by its ``package.xml`` as
``ament_python`` and builds it with its ``setup.py`` into a temporary build, install and log base (nothing is
written into the source tree; checked). The install tree must then hold, for every package in ros2_ws/src:

- its ``package.xml`` and its ament index marker (what ``ros2 pkg`` and ``ros2 launch`` find it by);
- every file of its Python package: modules, and data beside them (the policy node's models and Fast DDS
  profiles) -- a file there that ``setup.py`` does not install fails here, not on a robot;
- every file of its ``launch/`` and ``config/`` directories, under ``share/<package>/``;
- an executable in ``lib/<package>/`` for each console script of its ``setup.py``, run by this Python, whose
  entry point resolves, with the install tree first on the path (as a sourced ``setup.sh`` puts it), to a
  function in the install tree's modules; ``morph-train --help`` runs from there.

Limits: the ROS of this environment is the rclpy wheels, without ``launch``, ``launch_ros`` or the ``ros2``
command, so the launch files are checked to be installed, not launched, and the nodes' executables to resolve,
not started (``tests/test_ros_nodes.py`` starts the nodes through their entry points in the venv). The build
is the plain one (no ``--symlink-install``, which needs ``setup.py develop``).
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "ros2_ws" / "src"
COLCON = Path(sys.executable).parent / "colcon"
PACKAGES = sorted(p.parent.name for p in SRC.glob("*/package.xml"))
SITE = f"lib/python{sys.version_info.major}.{sys.version_info.minor}/site-packages"


def _source_files() -> set[Path]:
    return {p for p in SRC.rglob("*") if "__pycache__" not in p.parts and not p.name.endswith(".pyc")}


def _console_scripts(package: str) -> dict[str, str]:
    """name -> "module:function" of the console scripts in ``package``'s setup.py (read, not run)."""
    tree = ast.parse((SRC / package / "setup.py").read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == "entry_points":
            scripts = ast.literal_eval(node.value).get("console_scripts", [])
            return dict(tuple(part.strip() for part in s.split("=", 1)) for s in scripts)
    return {}


@pytest.fixture(scope="module")
def install(tmp_path_factory) -> Path:
    if not COLCON.exists():
        pytest.fail(f"no colcon at {COLCON}: pip install -c constraints.txt -r requirements-dev.txt")
    base = tmp_path_factory.mktemp("colcon")
    before = _source_files()
    env = {**os.environ, "COLCON_HOME": str(base / "home"), "PATH": f"{COLCON.parent}{os.pathsep}{os.environ['PATH']}"}
    result = subprocess.run(
        [str(COLCON), "--log-base", str(base / "log"), "build", "--base-paths", str(SRC)]
        + ["--build-base", str(base / "build"), "--install-base", str(base / "install")]
        + ["--event-handlers", "console_direct-"],
        cwd=base,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, f"colcon build failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    for package in PACKAGES:
        assert f"Finished <<< {package}" in result.stdout, result.stdout
    assert _source_files() == before, "colcon build wrote into the source tree"
    return base / "install"


def test_every_package_is_installed_as_an_ament_package(install):
    assert PACKAGES == ["morph_core", "morph_policy_node", "morph_ros_util", "swimmer_sim_node", "trainer"]
    for package in PACKAGES:
        share = install / package / "share"
        assert (share / package / "package.xml").is_file()
        assert (share / "ament_index" / "resource_index" / "packages" / package).is_file()


def test_the_python_packages_are_installed_whole_with_their_data(install):
    missing = []
    for package in PACKAGES:
        source = SRC / package / package
        installed = install / package / SITE / package
        for path in sorted(source.rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                if not (installed / path.relative_to(source)).is_file():
                    missing.append(str(path.relative_to(SRC)))
    assert missing == [], "not installed: " + ", ".join(missing)
    models = install / "morph_policy_node" / SITE / "morph_policy_node" / "models"
    assert sorted(p.name for p in models.glob("*.safetensors")) == [
        "centipede_gnn.safetensors",
        "legged_gnn.safetensors",
        "swimmer_gnn.safetensors",
        "swimmer_trees_gnn.safetensors",
    ]


def test_the_launch_and_config_files_are_installed(install):
    found = []
    for package in PACKAGES:
        for kind in ("launch", "config"):
            for path in sorted((SRC / package / kind).glob("*")):
                assert (install / package / "share" / package / kind / path.name).is_file(), f"{path} not installed"
                found.append(f"{package}/{kind}/{path.name}")
    assert "morph_policy_node/launch/swimmer_policy.launch.py" in found
    assert "morph_policy_node/config/swimmer_policy.yaml" in found
    assert "trainer/launch/live_training.launch.py" in found


def test_every_console_script_is_installed_and_resolves_in_the_install_tree(install):
    scripts = {package: _console_scripts(package) for package in PACKAGES}
    assert "morph-train" in scripts["trainer"] and "morph_policy_node" in scripts["morph_policy_node"]
    for package, entries in scripts.items():
        for name in entries:
            path = install / package / "lib" / package / name
            assert path.is_file() and os.access(path, os.X_OK), f"{package}: no executable {name}"
            assert path.read_text(encoding="utf-8").splitlines()[0] == f"#!{sys.executable}"
    # The entry points as the install tree's metadata states them, loaded with the install tree first on the
    # path: each must be the function setup.py names, from a module of the install tree.
    code = (
        "import importlib.metadata as md, json, sys\n"
        "out = {}\n"
        f"for package in {PACKAGES!r}:\n"
        "    dist = md.distribution(package)\n"
        "    for ep in dist.entry_points.select(group='console_scripts'):\n"
        "        fn = ep.load()\n"
        "        out[ep.name] = [package, ep.value, str(dist.locate_file('')), sys.modules[fn.__module__].__file__]\n"
        "import morph_policy_node.policy_node as node\n"
        "out['shipped model'] = [str(node.SHIPPED_MODEL), node.SHIPPED_MODEL.is_file()]\n"
        "print(json.dumps(out))\n"
    )
    path = os.pathsep.join(str(install / package / SITE) for package in PACKAGES)
    env = {**os.environ, "PYTHONPATH": path}
    result = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-4000:]
    import json

    loaded = json.loads(result.stdout.splitlines()[-1])
    model, exists = loaded.pop("shipped model")
    assert exists and Path(model).is_relative_to(install)
    assert {name: value for name, (_, value, _, _) in loaded.items()} == {
        name: value for entries in scripts.values() for name, value in entries.items()
    }
    for name, (package, _, dist_root, module_file) in loaded.items():
        assert Path(dist_root).is_relative_to(install / package), f"{name}: metadata from {dist_root}"
        assert Path(module_file).is_relative_to(install / package), f"{name}: code from {module_file}"
    # one of them run as a user runs it, from the install tree
    help_ = subprocess.run(
        [str(install / "trainer" / "lib" / "trainer" / "morph-train"), "--help"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert help_.returncode == 0 and help_.stdout.startswith("usage: morph-train"), help_.stderr[-4000:]
