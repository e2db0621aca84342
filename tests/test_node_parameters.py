"""The nodes' parameters come from one table each: declared from it, listed by ``--help`` from it (no DDS)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from rclpy.parameter import Parameter

from morph_policy_node.policy_node import parameters as policy_parameters
from morph_ros_util.parameters import NodeParameter, parameters_help
from swimmer_sim_node.sim_node import PARAMETERS as SIM_PARAMETERS
from trainer.bags.record import PARAMETERS as RECORD_PARAMETERS


def test_a_range_becomes_the_descriptor_rclpy_enforces():
    ints = NodeParameter("n", 3, "joints", (1, 64)).descriptor()
    assert [(r.from_value, r.to_value, r.step) for r in ints.integer_range] == [(1, 64, 1)]
    assert not ints.floating_point_range and not ints.read_only
    floats = NodeParameter("t", 0.5, "seconds", (0.001, 10.0), read_only=True).descriptor()
    assert [(r.from_value, r.to_value, r.step) for r in floats.floating_point_range] == [(0.001, 10.0, 0.0)]
    assert floats.read_only and not floats.integer_range


@pytest.mark.parametrize("default", ["text", True, Parameter.Type.STRING_ARRAY])
def test_a_range_on_a_non_number_is_refused_by_name(default):
    with pytest.raises(TypeError, match="parameter p: a range needs a numeric default"):
        NodeParameter("p", default, "what", (0, 1)).descriptor()


def test_help_lists_each_row_with_its_default_range_and_read_only():
    text = parameters_help([NodeParameter("rate", 2.0, "steps per second", (0.0, 9.0), read_only=True),
                            NodeParameter("keys", Parameter.Type.STRING_ARRAY, "key files")])  # fmt: skip
    assert "rate  steps per second (default: 2.0; 0.0..9.0; read-only)" in text
    assert "keys  key files (default: unset)" in text


@pytest.mark.parametrize(
    "module, table",
    [("swimmer_sim_node.sim_node", SIM_PARAMETERS), ("morph_policy_node.policy_node", policy_parameters())],
)
def test_a_node_prints_its_parameters_for_help_and_starts_nothing(module, table):
    done = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: ") and "parameters (-p NAME:=VALUE" in done.stdout
    for row in table:
        assert f"  {row.name} " in done.stdout, row.name
    assert "[INFO]" not in done.stdout + done.stderr  # no node was made


def test_every_table_names_each_parameter_once():
    for table in (SIM_PARAMETERS, policy_parameters(), RECORD_PARAMETERS):
        names = [row.name for row in table]
        assert len(names) == len(set(names)) and all(row.description for row in table)
