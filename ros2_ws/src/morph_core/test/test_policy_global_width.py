"""The policy's global input width: a config field whose default (4, the swimmer's) leaves every swimmer
checkpoint as it was, and a wider input (the centipede's) that the torch and NumPy policies read alike."""

from pathlib import Path

import numpy as np
import pytest
import torch

from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import load_checkpoint

MODELS = Path(__file__).resolve().parents[2] / "morph_policy_node" / "morph_policy_node" / "models"
REFERENCE = Path(__file__).parent / "data" / "shipped_policy_outputs.npz"
"""the shipped checkpoints' outputs on fixed inputs, computed at commit 38f60c4 (before the width was a field)"""


@pytest.mark.parametrize("name", ["swimmer_gnn", "swimmer_trees_gnn"])
def test_shipped_checkpoints_answer_as_before_bit_for_bit(name):
    ref = np.load(REFERENCE)
    pos, vel, glob, n, parents = (ref[k] for k in ("pos", "vel", "glob", "n", "parents"))
    path = MODELS / f"{name}.safetensors"
    fast = NumpyPolicy(load_checkpoint(path))
    mean, value = fast.forward(pos, vel, glob, n, parents)
    np.testing.assert_array_equal(mean, ref[f"{name}_numpy_mean"])
    np.testing.assert_array_equal(value, ref[f"{name}_numpy_value"])
    np.testing.assert_array_equal(fast.mean(pos[4], vel[4], glob[4]), ref[f"{name}_numpy_single"])
    policy = GraphActorCritic.load(path)
    with torch.no_grad():
        t_mean, _, t_value = policy(ChainBatch.from_padded(pos, vel, glob, n, trim=False, parents=parents))
    np.testing.assert_array_equal(t_mean.numpy(), ref[f"{name}_torch_mean"])
    np.testing.assert_array_equal(t_value.numpy(), ref[f"{name}_torch_value"])
