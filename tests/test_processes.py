"""``morph_ros_util.processes``, the one way the bring-ups, benches and tests start and stop node processes:
the command a node gets (its namespace, its parameters as YAML), real processes started, logged and stopped
(SIGTERM, then SIGKILL for one that ignores it), and no other module writing ``--ros-args`` itself."""

from __future__ import annotations

import ast
import signal
import sys
import time
from pathlib import Path

from morph_ros_util.processes import (
    NodeProcess,
    node_command,
    param_text,
    ros_arguments,
    start_node,
    stop_all,
    yaml_string,
)

ROOT = Path(__file__).resolve().parents[1]


def test_parameters_are_written_as_yaml_and_the_namespace_defaults_to_the_root():
    assert [param_text(v) for v in (True, False, 3, 0.5, "", "[1, 2]", "fixed")] == [
        "true", "false", "3", "0.5", "''", "[1, 2]", "fixed"]  # fmt: skip
    assert yaml_string("6") == '"6"' and yaml_string("a b") == '"a b"'  # stays a string, not the number 6
    assert ros_arguments() == ["--ros-args", "-r", "__ns:=/"]
    assert ros_arguments("/r1", {"lockstep": True, "seed": 2}) == [
        "--ros-args", "-r", "__ns:=/r1", "-p", "lockstep:=true", "-p", "seed:=2"]  # fmt: skip


def test_a_module_runs_under_this_python_and_a_path_as_itself_after_its_prefix():
    assert node_command("swimmer_sim_node.sim_node", "/a")[:3] == [sys.executable, "-m", "swimmer_sim_node.sim_node"]
    script = str(Path(sys.executable).parent / "morph_policy_node")
    assert node_command(script, "/a", prefix=["nsenter", "-n"])[:3] == ["nsenter", "-n", script]


# A stand-in for a node: says it is up, then waits; with "stubborn" it ignores SIGTERM (a node stuck in the
# middleware), so only the kill ends it.
CHILD = """
import signal, sys, time
if sys.argv[1] == "stubborn":
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
print("up", sys.argv[1:], flush=True)
time.sleep(600)
"""


def _child(tmp_path: Path, mode: str, echo: bool = False) -> NodeProcess:
    proc = NodeProcess([sys.executable, "-c", CHILD, mode], tmp_path / f"{mode}.log", echo=echo)
    while "up" not in proc.log():
        assert proc.alive(), proc.log()
        time.sleep(0.05)
    return proc


def test_processes_log_and_stop_with_sigterm_or_are_killed(tmp_path):
    polite, stubborn = _child(tmp_path, "polite", echo=True), _child(tmp_path, "stubborn")
    assert polite.log().startswith(f"$ {sys.executable} -c")  # echo: the command first
    assert stubborn.log().startswith("up")
    codes = stop_all([polite, stubborn], timeout=2.0)
    assert codes == [-signal.SIGTERM, -signal.SIGKILL]
    assert not polite.alive() and not stubborn.alive() and polite.stop() == -signal.SIGTERM  # a second stop: a no-op


def test_a_node_that_cannot_start_ends_with_its_error_in_its_log(tmp_path):
    proc = start_node("morph_ros_util.no_such_node", "/x", {"a": 1}, tmp_path / "log")
    assert proc.wait() != 0 and "No module named morph_ros_util.no_such_node" in proc.log()
    proc.close()


def test_no_module_but_processes_writes_ros_arguments():
    """A node's command line is written once: bring-ups, benches and tests ask ``node_command``. The docs
    checks read commands (``test_docs_commands``, ``test_sim_trees``) and ``morph-record`` adds its own
    ``output`` parameter to the arguments it is given."""
    readers = {
        "test_docs_commands.py",
        "test_sim_trees.py",
        "record.py",
        "test_record_cli.py",
        "processes.py",
        Path(__file__).name,
    }
    sources = [p for d in ("ros2_ws/src", "bench", "scripts", "tests") for p in (ROOT / d).rglob("*.py")]
    sources = [p for p in sources if p.name not in readers and "/build/" not in str(p) and "/install/" not in str(p)]
    assert len(sources) > 100
    found = [
        f"{p.relative_to(ROOT)}:{node.lineno}"
        for p in sources
        for node in ast.walk(ast.parse(p.read_text(), str(p)))
        if isinstance(node, ast.Constant) and node.value == "--ros-args"
    ]
    assert not found, "start nodes through morph_ros_util.processes:\n" + "\n".join(found)
