"""Checkpoints without torch: the loader, the NumPy actor built from arrays, the node's policy choice, and
the nodes' imports (no torch, no torch_geometric, no TensorBoard, Matplotlib or SciPy; no mujoco and no
gymnasium in the policy node)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.chains import ChainBatch
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import CheckpointError, load_checkpoint, parameter_shapes, untrained_weights
from morph_core.protocol.controller import PolicyOutputError, act
from morph_policy_node.policy_choice import choose_policy
from morph_policy_node.policy_node import SHIPPED_MODEL

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

CONFIGS = [PolicyConfig(), PolicyConfig(bidirectional=False, conv1_channels=5, head_hidden=7, global_hidden=9)]


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    torch.manual_seed(7)
    path = tmp_path_factory.mktemp("ckpt") / "policy.safetensors"
    policy = GraphActorCritic()
    with torch.no_grad():
        policy.log_std.fill_(-0.3)
    policy.save(path, metadata={"note": "test"})
    return policy.eval(), path


@pytest.mark.parametrize("config", CONFIGS)
def test_parameter_shapes_are_the_torch_state_dict(config):
    want = {k: tuple(v.shape) for k, v in GraphActorCritic(config).state_dict().items()}
    assert parameter_shapes(config) == want


@pytest.mark.parametrize("config", CONFIGS)
def test_a_checkpoint_loads_without_torch_into_the_same_policy(tmp_path, config):
    torch.manual_seed(11)
    policy = GraphActorCritic(config).eval()
    policy.save(tmp_path / "p.safetensors")
    weights = load_checkpoint(tmp_path / "p.safetensors")
    assert weights.trained and weights.config == config and weights.source.endswith("p.safetensors")
    from_file, from_torch = NumpyPolicy(weights), NumpyPolicy(policy)
    rng = np.random.default_rng(0)
    b, j = 5, 9
    pos, vel = rng.normal(size=(b, j)).astype(np.float32), rng.normal(size=(b, j)).astype(np.float32)
    glob, n = rng.normal(size=(b, 4)).astype(np.float32), np.array([1, 4, 9, 2, 6])
    mean_f, value_f = from_file.forward(pos, vel, glob, n)
    mean_t, value_t = from_torch.forward(pos, vel, glob, n)
    np.testing.assert_array_equal(mean_f, mean_t)  # the same arrays, so the same bits
    np.testing.assert_array_equal(value_f, value_t)
    with torch.no_grad():
        mean, _, value = policy(ChainBatch.from_padded(pos, vel, glob, n))
    np.testing.assert_allclose(mean_f, mean.numpy(), atol=1e-5)
    np.testing.assert_allclose(value_f, value.numpy(), atol=1e-5)


def test_every_bad_checkpoint_is_one_error_naming_the_file_and_the_reason(bad_checkpoints):
    assert len(bad_checkpoints) >= 10
    for case, (path, words) in bad_checkpoints.items():
        with pytest.raises(CheckpointError) as info:
            load_checkpoint(path)
        err = info.value
        assert err.path == str(path) and str(path) in str(err), case
        assert all(w in str(err) for w in words), (case, str(err))
        assert "\n" not in str(err), case


def test_untrained_weights_are_seeded_and_usable():
    a, b, c = untrained_weights(seed=3), untrained_weights(seed=3), untrained_weights(seed=4)
    assert not a.trained and "seed 3" in a.source
    assert all(np.array_equal(a.arrays[k], b.arrays[k]) for k in a.arrays)
    assert not all(np.array_equal(a.arrays[k], c.arrays[k]) for k in a.arrays if a.arrays[k].size > 1)
    assert {k: v.shape for k, v in a.arrays.items()} == parameter_shapes(PolicyConfig())
    assert all(v.dtype == np.float32 for v in a.arrays.values())
    w = a.arrays["features.global_mlp.0.weight"]  # orthogonal columns, gain sqrt(2)
    np.testing.assert_allclose(w.T @ w, 2 * np.eye(w.shape[1]), atol=1e-5)
    mean = NumpyPolicy(a).mean(np.array([0.2, -0.1, 0.3]), np.zeros(3), np.zeros(4))
    assert np.isfinite(mean).all() and np.abs(mean).max() < 0.5  # action gain 0.01: means start near 0


def test_the_node_runs_an_untrained_policy_only_when_asked(saved):
    _, good = saved
    assert choose_policy(str(good), allow_untrained=False, seed=0).trained
    with pytest.raises(CheckpointError, match="allow_untrained"):
        choose_policy("", allow_untrained=False, seed=0)
    assert not choose_policy("", allow_untrained=True, seed=0).trained
    with pytest.raises(CheckpointError, match="no such file"):
        choose_policy(str(good.with_name("typo.safetensors")), allow_untrained=True, seed=0)


def test_answers_mean_sample_and_a_non_finite_output_refused(saved, overflowing_checkpoint):
    _, good = saved
    numpy_policy = NumpyPolicy(load_checkpoint(good))
    pos, vel, glob = np.array([0.4, -0.3, 0.2, 0.1]), np.full(4, 0.5), np.array([0.1, 0.0, 0.2, 0.0])
    det = act(numpy_policy, pos, vel, glob, None)
    np.testing.assert_array_equal(det.efforts, np.clip(numpy_policy.mean(pos, vel, glob), -1, 1))
    np.testing.assert_array_equal(det.action, numpy_policy.mean(pos, vel, glob).astype(np.float64))
    assert det.mean is None
    rng, again = np.random.default_rng(5), np.random.default_rng(5)
    sample = act(numpy_policy, pos, vel, glob, rng)
    z = again.standard_normal(4)
    np.testing.assert_allclose(sample.action, sample.mean + np.exp(-0.3) * z, atol=1e-12)
    np.testing.assert_array_equal(sample.efforts, np.clip(sample.action, -1, 1))
    np.testing.assert_array_equal(sample.mean, numpy_policy.mean(pos, vel, glob).astype(np.float64))

    overflowing = NumpyPolicy(load_checkpoint(overflowing_checkpoint))
    for rng in (None, np.random.default_rng(0)):
        with pytest.raises(PolicyOutputError):
            act(overflowing, pos, vel, glob, rng)


def _modules_after(code: str) -> set[str]:
    script = textwrap.dedent(code) + "\nimport sys\nprint(' '.join(sorted(sys.modules)))\n"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return set(out.stdout.split())


def test_the_sim_node_imports_no_torch():
    modules = _modules_after("import swimmer_sim_node.sim_node")
    assert "swimmer_sim_node.sim_node" in modules and "mujoco" in modules
    assert not {"torch", "torch_geometric", "tensorboard", "matplotlib", "scipy"} & modules


@pytest.mark.skipif(not SHIPPED_MODEL.is_file(), reason="no shipped model")
def test_the_policy_node_loads_and_acts_without_torch():
    modules = _modules_after(
        f"""
        import numpy as np
        import morph_policy_node.policy_node
        from morph_core.protocol.controller import act
        from morph_policy_node.policy_choice import choose_policy
        from morph_core.policy.numpy_actor import NumpyPolicy
        for checkpoint, allow in (({str(SHIPPED_MODEL)!r}, False), ("", True)):
            policy = NumpyPolicy(choose_policy(checkpoint, allow, 0))
            pos, vel, glob = np.array([0.1, 0.2]), np.zeros(2), np.zeros(4)
            assert np.isfinite(act(policy, pos, vel, glob, None).efforts).all()
            assert np.isfinite(act(policy, pos, vel, glob, np.random.default_rng(0)).efforts).all()
        """
    )
    assert "morph_policy_node.policy_node" in modules and "safetensors" in modules
    # nor the env's gymnasium (a robot that runs only this node has none installed: tests/test_robot_install.py)
    assert not {"torch", "torch_geometric", "tensorboard", "matplotlib", "scipy", "mujoco", "gymnasium"} & modules
