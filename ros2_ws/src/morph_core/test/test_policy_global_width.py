"""The policy's global input width: a config field whose default (4, the swimmer's) leaves every swimmer
checkpoint as it was, and a wider input (the centipede's) that the torch and NumPy policies read alike."""

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch, pad_observations
from morph_core.policy.config import PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import load_checkpoint

MODELS = Path(__file__).resolve().parents[2] / "morph_policy_node" / "morph_policy_node" / "models"
REFERENCE = Path(__file__).parent / "data" / "shipped_policy_outputs.npz"
"""the shipped checkpoints' outputs on fixed inputs, computed at commit 38f60c4 (before the width was a field),
torch's with one intra-op thread"""


@pytest.fixture
def one_torch_thread():
    """torch's float sums depend on its thread count (the machine's cores, or what an earlier test set): the
    reference was computed with one thread, so the comparison runs with one."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("name", ["swimmer_gnn", "swimmer_trees_gnn"])
def test_shipped_checkpoints_answer_as_before_bit_for_bit(name, one_torch_thread):
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


def test_a_checkpoint_without_the_field_reads_as_four_globals():
    meta = json.loads((MODELS / "swimmer_gnn.json").read_text())
    assert "global_features" not in meta["policy"]  # written before the field existed
    weights = load_checkpoint(MODELS / "swimmer_gnn.safetensors")
    assert weights.config.global_features == 4
    assert weights.arrays["features.global_mlp.0.weight"].shape == (128, 4)


def _perturbed(config: PolicyConfig, seed: int) -> GraphActorCritic:
    torch.manual_seed(seed)
    policy = GraphActorCritic(config)
    with torch.no_grad():  # away from the near-zero initial action head
        for p in policy.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return policy


@pytest.mark.parametrize("bidirectional", [True, False])
def test_a_wider_global_input_numpy_equals_torch(bidirectional, tmp_path):
    g = 12
    policy = _perturbed(PolicyConfig(bidirectional=bidirectional, global_features=g), seed=3)
    assert policy.features.global_mlp[0].weight.shape == (128, g)
    rng = np.random.default_rng(4)
    n = np.array([4, 8, 12, 40])
    width = int(n.max())
    pos, vel = rng.normal(0, 1, (4, width)), rng.normal(0, 3, (4, width))
    pos, vel = pos * (np.arange(width) < n[:, None]), vel * (np.arange(width) < n[:, None])
    glob = rng.normal(0, 1, (4, g))
    # centipede-like trees: legs of two joints (hip, ankle) off the root
    parents = np.full((4, width), -1)
    for b, count in enumerate(n):
        parents[b, :count] = [-1 if j % 2 == 0 else j - 1 for j in range(count)]
    batch = ChainBatch.from_padded(pos, vel, glob, n, trim=False, parents=parents)
    with torch.no_grad():
        t_mean, _, t_value = policy(batch)
    fast = NumpyPolicy(policy)
    mean, value = fast.forward(pos, vel, glob, n, parents)
    np.testing.assert_allclose(mean, t_mean.numpy(), atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(value, t_value.numpy(), atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(fast.mean(pos[1, :8], vel[1, :8], glob[1], parents[1, :8]), mean[1, :8], atol=1e-5)
    # the globals matter: another global vector moves the actions
    other = fast.forward(pos, vel, glob + 1.0, n, parents)[0]
    assert np.abs(other - mean).max() > 1e-3

    # persistence: the width travels in the checkpoint's JSON and comes back
    policy.save(tmp_path / "wide.safetensors")
    assert json.loads((tmp_path / "wide.json").read_text())["policy"]["global_features"] == g
    loaded = load_checkpoint(tmp_path / "wide.safetensors")
    assert loaded.config == policy.config
    np.testing.assert_array_equal(NumpyPolicy(loaded).forward(pos, vel, glob, n, parents)[0], mean)
    again = GraphActorCritic.load(tmp_path / "wide.safetensors")
    with torch.no_grad():
        np.testing.assert_array_equal(again(batch)[0].numpy(), t_mean.numpy())


def test_a_global_vector_of_the_wrong_width_is_refused_clearly():
    policy = _perturbed(PolicyConfig(global_features=12), seed=5)
    pos, vel = np.zeros((1, 4)), np.zeros((1, 4))
    with pytest.raises(ValueError, match="reads 12 global features, the batch has 4"):
        policy(ChainBatch.from_padded(pos, vel, np.zeros((1, 4)), [4]))
    with pytest.raises(ValueError, match="reads 12 global features, got 4"):
        NumpyPolicy(policy).forward(pos, vel, np.zeros((1, 4)), np.array([4]))
    with pytest.raises(ValueError, match="reads 4 global features, got 12"):
        NumpyPolicy(_perturbed(PolicyConfig(), seed=6)).mean(pos[0], vel[0], np.zeros(12))


@pytest.mark.parametrize("bad", [0, -1, 257, True, 4.0, "4", None])
def test_bad_global_widths_are_refused(bad):
    with pytest.raises(ValueError, match="global_features must be an integer in 1..256"):
        PolicyConfig(global_features=bad)
    with pytest.raises(ValueError, match="global_features"):
        PolicyConfig.from_dict({**asdict(PolicyConfig()), "global_features": bad})


def test_observations_of_mixed_global_widths_do_not_pad_silently():
    obs = [
        {"joint_pos": np.zeros(2), "joint_vel": np.zeros(2), "global": np.zeros(4)},
        {"joint_pos": np.zeros(4), "joint_vel": np.zeros(4), "global": np.zeros(12)},
    ]
    with pytest.raises(ValueError, match="global features differ"):
        pad_observations(obs)
    assert pad_observations(obs[1:])[2].shape == (1, 12)
