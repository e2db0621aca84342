"""Graph actor-critic: shapes for any chain length, PyG equivalence, log-probs, persistence."""

import json
import os
import subprocess
import sys
import tempfile

import gymnasium
import numpy as np
import pytest
import torch

import morph_core.env.registration  # noqa: F401  (registers MorphSwimmer-v0)
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig, count_parameters, gaussian_log_prob
from morph_core.policy.chains import ChainBatch


def _observations(lengths, seed=0):
    obs = []
    for i, n in enumerate(lengths):
        env = gymnasium.make("MorphSwimmer-v0", num_joints=int(n))
        o, _ = env.reset(seed=seed + i)
        for _ in range(3):  # move away from the rest pose so joint states differ
            o, *_ = env.step(env.action_space.sample())
        obs.append(o)
    return obs


def test_parameter_counts_match_the_paper():
    one_way = GraphActorCritic(PolicyConfig(bidirectional=False))
    assert count_parameters(one_way.features) == 4376  # paper: feature extractor
    assert count_parameters(one_way) == 15003  # reference: whole actor-critic
    # both ways: one more edge network per layer (2*24 + 24 and 2*384 + 384 weights)
    assert count_parameters(GraphActorCritic().features) == 4376 + 72 + 1152


@pytest.mark.parametrize("lengths", [[1], [2], [7], [20], [64], [2, 10, 3, 20, 1, 5]])
def test_shapes_for_any_chain_length(lengths):
    policy = GraphActorCritic()
    batch = ChainBatch.from_observations(_observations(lengths))
    mean, log_std, value = policy(batch)
    assert mean.shape == (len(lengths), max(lengths)) and value.shape == (len(lengths),)
    assert log_std.shape == ()
    # padding stays exactly zero, real joints do not
    assert torch.all(mean[~batch.mask] == 0)
    assert torch.all(mean[batch.mask] != 0)
    action, logp, _, _ = policy.act(batch)
    assert torch.all(action[~batch.mask] == 0) and logp.shape == (len(lengths),)


def test_batched_forward_equals_one_chain_at_a_time():
    policy = GraphActorCritic()
    obs = _observations([3, 9, 2, 14])
    mean, _, value = policy(ChainBatch.from_observations(obs))
    for i, o in enumerate(obs):
        m_i, _, v_i = policy(ChainBatch.from_observations([o]))
        n = len(o["joint_pos"])
        torch.testing.assert_close(mean[i, :n], m_i[0], atol=1e-6, rtol=1e-5)
        torch.testing.assert_close(value[i], v_i[0], atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("bidirectional", [True, False])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dense_chain_conv_equals_pytorch_geometric(bidirectional, seed):
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, 21, size=32)
    dense = GraphActorCritic(PolicyConfig(bidirectional=bidirectional), backend="dense")
    pyg = GraphActorCritic(PolicyConfig(bidirectional=bidirectional), backend="pyg")
    pyg.load_state_dict(dense.state_dict())
    # random joint states, larger than the env's, to stress every weight
    j = int(lengths.max())
    batch = ChainBatch.from_padded(
        rng.normal(0, 2, (32, j)), rng.normal(0, 5, (32, j)), rng.normal(0, 1, (32, 4)), lengths
    )
    for a, b in zip(dense(batch), pyg(batch), strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    # gradients agree too
    actions = torch.randn(32, j)
    grads = []
    for net in (dense, pyg):
        net.zero_grad()
        mean, _, value = net(batch)
        (net.log_prob(batch, actions, mean).sum() + value.sum()).backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
    torch.testing.assert_close(grads[0], grads[1], atol=1e-4, rtol=1e-4)


def test_one_way_messages_never_reach_the_torso_side():
    # With torso-to-tail edges a joint cannot hear joints behind it; both ways, it can.
    for bidirectional, should_change in ((False, False), (True, True)):
        torch.manual_seed(0)
        policy = GraphActorCritic(PolicyConfig(bidirectional=bidirectional))
        pos = torch.zeros(1, 6)
        base = policy(ChainBatch.from_padded(pos, torch.zeros(1, 6), torch.zeros(1, 4), [6]))[0]
        pos[0, 5] = 1.0  # move the last joint
        moved = policy(ChainBatch.from_padded(pos, torch.zeros(1, 6), torch.zeros(1, 4), [6]))[0]
        assert not torch.equal(base[0, 5], moved[0, 5])  # its own action always changes
        assert torch.equal(base[0, :3], moved[0, :3])  # beyond two message hops: never
        # joints 3 and 4 lie towards the torso, two and one hops away
        assert (not torch.equal(base[0, 3:5], moved[0, 3:5])) == should_change
        assert torch.equal(base[0, 3:5], moved[0, 3:5]) != should_change


def test_log_prob_is_the_sum_over_the_chains_joints():
    mean = torch.tensor([[0.1, -0.2, 0.0], [0.3, 0.0, 0.0]])
    mask = torch.tensor([[True, True, True], [True, False, False]])
    actions = torch.tensor([[0.5, 0.1, -0.3], [0.2, 9.0, 9.0]])  # padding values must not count
    log_std = torch.tensor(-0.5)
    normal = torch.distributions.Normal(mean, log_std.exp())
    expected = torch.stack([normal.log_prob(actions)[0].sum(), normal.log_prob(actions)[1, :1].sum()])
    torch.testing.assert_close(gaussian_log_prob(actions, mean, log_std, mask), expected)


def test_save_load_roundtrip_without_pickle(tmp_path):
    policy = GraphActorCritic(PolicyConfig(bidirectional=False))
    with torch.no_grad():
        policy.log_std.fill_(-0.7)
    path = tmp_path / "policy.safetensors"
    policy.save(path, metadata={"note": "test"})
    assert path.read_bytes()[8:9] == b"{"  # safetensors header, not a pickle
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # written atomically, yet readable like any file
    loaded = GraphActorCritic.load(path)
    assert loaded.config == policy.config
    batch = ChainBatch.from_observations(_observations([4, 11]))
    for a, b in zip(policy(batch), loaded(batch), strict=True):
        torch.testing.assert_close(a, b)
    assert GraphActorCritic.load(path, backend="pyg").backend == "pyg"
    # The backend is how the network executes, not what it is: the file does not record it.
    assert "backend" not in json.loads(path.with_suffix(".json").read_text())["policy"]


def test_model_files_that_record_a_backend_still_load(tmp_path):
    # Files written before the backend left PolicyConfig (the shipped model, docs/results_data) carry it.
    policy = GraphActorCritic(PolicyConfig(bidirectional=False))
    path = tmp_path / "old.safetensors"
    policy.save(path)
    meta = json.loads(path.with_suffix(".json").read_text())
    meta["policy"]["backend"] = "dense"
    path.with_suffix(".json").write_text(json.dumps(meta))
    loaded = GraphActorCritic.load(path)
    assert loaded.config == policy.config and loaded.backend == "dense"
    meta["policy"]["backend"] = "onnx"
    path.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="backend"):
        GraphActorCritic.load(path)


def test_bad_config_and_files_give_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="backend"):
        GraphActorCritic(backend="onnx")
    with pytest.raises(ValueError, match="safetensors"):
        GraphActorCritic.load(tmp_path / "policy.pt")
    with pytest.raises(FileNotFoundError, match="json"):
        GraphActorCritic.load(tmp_path / "missing.safetensors")
    with pytest.raises(ValueError, match="num_joints"):
        ChainBatch.from_padded(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 4)), [4])


def test_packed_chains_lay_the_batch_end_to_end_with_cuts():
    # Chains of 2 and 3 joints: links t0 l1 l2 | t0 l1 l2 l3, slots between neighbours, one cut.
    pos = torch.tensor([[0.1, 0.2, 9.0], [0.3, 0.4, 0.5]])
    vel = torch.tensor([[1.0, 2.0, 9.0], [3.0, 4.0, 5.0]])
    packed = ChainBatch.from_padded(pos, vel, torch.zeros(2, 4), [2, 3]).packed
    assert packed.num_links == 7
    assert packed.slot_mask.tolist() == [True, True, False, True, True, True]
    assert packed.joint_link.tolist() == [1, 2, 4, 5, 6]  # the link behind each joint
    assert packed.joint_chain.tolist() == [0, 0, 1, 1, 1]
    assert packed.joint_padded.tolist() == [0, 1, 3, 4, 5]
    expected = [[0.1, 1.0], [0.2, 2.0], [0.0, 0.0], [0.3, 3.0], [0.4, 4.0], [0.5, 5.0]]  # padding never leaks
    torch.testing.assert_close(packed.edge_attr, torch.tensor(expected))


@pytest.mark.slow
def test_building_a_policy_leaves_no_generated_module_file_in_the_temp_directory():
    # PyG writes NNConv's generated propagate module into the temp directory, once per process, and keeps
    # the file; a fresh interpreter shows whether it is still there after a policy is built.
    code = (
        "import os, sys\n"
        "from morph_core.policy.actor_critic import GraphActorCritic\n"
        "GraphActorCritic()\n"
        "path = sys.modules['torch_geometric.nn.conv.nn_conv_NNConv_propagate'].__file__\n"
        "print(path, os.path.exists(path))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    path, exists = out.split()
    assert os.path.dirname(path) == tempfile.gettempdir() and exists == "False"
