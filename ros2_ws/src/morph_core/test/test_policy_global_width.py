"""The policy's global input width: a config field whose default (4, the swimmer's) leaves every swimmer
checkpoint as it was, and a wider input (the centipede's) that the torch and NumPy policies read alike."""

import json
from dataclasses import asdict, replace
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
"""the shipped checkpoints' outputs on fixed inputs, computed at commit 38f60c4 (before the width was a field) on
an Intel Xeon, torch's with one intra-op thread"""

ATOL = RTOL = 1e-5
"""How far outputs recorded on another CPU may lie from this one's. NumPy's OpenBLAS and torch pick their kernels
by processor (SSE, AVX2, AVX-512, AMD's paths) and thread count, so float32 sums are associated differently: on
the recording machine the outputs moved by up to 1.2e-6 (means, |mean| <= 3.9) and 3.8e-6 (values, |value| <= 31,
a few ulps) across the seven OpenBLAS core types and torch's two CPU capabilities, and an AMD EPYC reported
1.0e-6 / 2.1e-6 (relative). 1e-5 absolute plus 1e-5 relative is ten times that spread, and ten times below the
smallest change that matters: an action moved by 1e-4 (the test below shows it is caught)."""


def _outputs(name: str, weights=None):
    """The shipped checkpoint's NumPy (batch and one chain) and torch outputs on the recorded inputs."""
    ref = np.load(REFERENCE)
    pos, vel, glob, n, parents = (ref[k] for k in ("pos", "vel", "glob", "n", "parents"))
    path = MODELS / f"{name}.safetensors"
    fast = NumpyPolicy(weights if weights is not None else load_checkpoint(path))
    mean, value = fast.forward(pos, vel, glob, n, parents)
    out = {"numpy_mean": mean, "numpy_value": value, "numpy_single": fast.mean(pos[4], vel[4], glob[4])}
    policy = GraphActorCritic.load(path)
    with torch.no_grad():
        t_mean, _, t_value = policy(ChainBatch.from_padded(pos, vel, glob, n, trim=False, parents=parents))
    return out | {"torch_mean": t_mean.numpy(), "torch_value": t_value.numpy()}, ref


@pytest.mark.parametrize("name", ["swimmer_gnn", "swimmer_trees_gnn"])
def test_shipped_checkpoints_answer_as_recorded(name):
    # Recorded on another machine: equal within the kernels' rounding (ATOL, RTOL), not to the bit.
    got, ref = _outputs(name)
    for key, value in got.items():
        np.testing.assert_allclose(value, ref[f"{name}_{key}"], atol=ATOL, rtol=RTOL, err_msg=key)


def test_the_tolerance_catches_a_change_a_user_could_see():
    # Moving every action by 1e-4 (the action head's bias) breaks the comparison: the tolerance is not loose.
    weights = load_checkpoint(MODELS / "swimmer_gnn.safetensors")
    arrays = dict(weights.arrays)
    arrays["actor_head.4.bias"] = arrays["actor_head.4.bias"] + np.float32(1e-4)
    got, ref = _outputs("swimmer_gnn", replace(weights, arrays=arrays))
    with pytest.raises(AssertionError):
        np.testing.assert_allclose(got["numpy_mean"], ref["swimmer_gnn_numpy_mean"], atol=ATOL, rtol=RTOL)


@pytest.mark.parametrize("name", ["swimmer_gnn", "swimmer_trees_gnn"])
def test_a_shipped_checkpoint_saved_again_answers_bit_for_bit(name, tmp_path):
    # Both sides computed here, in one process: persistence must not move a bit.
    policy = GraphActorCritic.load(MODELS / f"{name}.safetensors")
    policy.save(tmp_path / "again.safetensors")
    before, ref = _outputs(name)
    pos, vel, glob, n, parents = (ref[k] for k in ("pos", "vel", "glob", "n", "parents"))
    again = NumpyPolicy(load_checkpoint(tmp_path / "again.safetensors")).forward(pos, vel, glob, n, parents)
    np.testing.assert_array_equal(again[0], before["numpy_mean"])
    np.testing.assert_array_equal(again[1], before["numpy_value"])
    with torch.no_grad():
        t_mean, _, t_value = GraphActorCritic.load(tmp_path / "again.safetensors")(
            ChainBatch.from_padded(pos, vel, glob, n, trim=False, parents=parents)
        )
    np.testing.assert_array_equal(t_mean.numpy(), before["torch_mean"])
    np.testing.assert_array_equal(t_value.numpy(), before["torch_value"])


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
