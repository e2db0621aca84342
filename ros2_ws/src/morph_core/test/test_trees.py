"""Kinematic trees in the graph policy: PyG's NNConv on explicit edge lists, NumPy = torch, chains unchanged."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.chains import ChainBatch
from morph_core.policy.graph_forward import link_embeddings
from morph_core.policy.numpy_actor import NUMPY_OPS, NumpyPolicy

SHIPPED = Path(__file__).resolve().parents[2] / "morph_policy_node/morph_policy_node/models/swimmer_gnn.safetensors"


def _parents(rng: np.random.Generator, n: int, kind: str) -> list[int]:
    if kind == "chain":
        return list(range(-1, n - 1))
    if kind == "star":  # every joint on the torso
        return [-1] * n
    if kind == "fork":  # a chain of two, then every further joint on joint 1
        return [-1, 0, *[1] * (n - 2)][:n]
    return [int(rng.integers(-1, j)) for j in range(n)]  # any topologically ordered tree


def _trees(rng: np.random.Generator, shapes: list[tuple[int, str]]):
    """Padded states of samples of the given (joints, kind), their parents padded with garbage beyond each
    sample (which must be ignored), and the parents as lists."""
    width = max(n for n, _ in shapes)
    b = len(shapes)
    mask = np.arange(width) < np.array([n for n, _ in shapes])[:, None]
    pos = rng.uniform(-1.7, 1.7, (b, width)).astype(np.float32) * mask
    vel = rng.normal(0, 3, (b, width)).astype(np.float32) * mask
    glob = np.concatenate([rng.uniform(-6, 6, (b, 1)), rng.normal(0, 1, (b, 3))], 1).astype(np.float32)
    lists = [_parents(rng, n, kind) for n, kind in shapes]
    parents = rng.integers(-5, 50, (b, width))
    for i, p in enumerate(lists):
        parents[i, : len(p)] = p
    return pos, vel, glob, np.array([n for n, _ in shapes]), parents, lists


def _perturbed(config: PolicyConfig, seed: int) -> GraphActorCritic:
    torch.manual_seed(seed)
    policy = GraphActorCritic(config)
    with torch.no_grad():  # outputs of a trained policy's size, not the init's near-zero action layer
        for p in policy.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return policy


def _reference(policy: GraphActorCritic, pos, vel, glob, lists):
    """Mean (one tensor per sample) and value [B], one sample at a time through PyG's NNConv modules of
    ``policy`` on the tree's explicit edge list (parent link -> child link, and reversed): nothing of the
    packed layout or the index plan."""
    f = policy.features
    means, values = [], []
    for b, parents in enumerate(lists):
        n = len(parents)
        edges = torch.tensor([[p + 1 for p in parents], [j + 1 for j in range(n)]])
        attr = torch.stack([torch.as_tensor(pos[b, :n]), torch.as_tensor(vel[b, :n])], 1)
        x = attr.new_ones(n + 1, 1)
        for conv in (f.conv1, f.conv2):
            out = conv.fwd(x, edges, attr)
            if conv.bwd is not None:
                out = out + conv.bwd(x, edges.flip(0), attr)
            x = torch.relu(out)
        z = x[1:] + f.global_mlp(torch.as_tensor(glob[b : b + 1]))
        means.append(policy.actor_head(z).squeeze(1))
        values.append(policy.critic_head(z.mean(0, keepdim=True)).reshape(()))
    return means, torch.stack(values)


MIXES = {
    "mixed": [(5, "chain"), (6, "star"), (9, "random"), (1, "chain"), (12, "random"), (4, "fork"), (2, "star")],
    "stars": [(1, "star"), (3, "star"), (8, "star")],
    "single joints": [(1, "star"), (1, "chain"), (1, "random")],
    "random": [(n, "random") for n in (3, 17, 30, 2, 11)],
}


@pytest.mark.parametrize("mix", sorted(MIXES))
@pytest.mark.parametrize("bidirectional", [True, False])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dense_trees_equal_pyg_nnconv_outputs_and_gradients(mix, bidirectional, dtype):
    # Outputs to 1e-5. Gradients to 1e-5 in float64, where only a wiring error could differ; in float32
    # to 1e-5 of each parameter's largest gradient: they reach ~50 here, summed over hundreds of joints,
    # and float32 alone leaves ~1e-6 of that between two summation orders.
    rng = np.random.default_rng(len(mix))
    policy = _perturbed(PolicyConfig(bidirectional=bidirectional), seed=3).to(dtype)
    pos, vel, glob, n, parents, lists = _trees(rng, MIXES[mix])
    pos, vel, glob = (x.astype(np.float64) if dtype == torch.float64 else x for x in (pos, vel, glob))
    batch = ChainBatch.from_padded(pos, vel, glob, n, parents=parents)
    if dtype == torch.float64:  # from_padded makes float32: the same batch with its states in float64
        pos, vel = pos * batch.mask.numpy(), vel * batch.mask.numpy()
        t = torch.from_numpy
        batch = ChainBatch(t(pos), t(vel), t(glob), batch.num_joints, batch.mask, batch.parents)
    assert (batch.parents is None) == (mix == "single joints")  # a single joint is a chain
    w = torch.as_tensor(rng.normal(0, 1, batch.mask.shape), dtype=dtype)
    u = torch.as_tensor(rng.normal(0, 1, len(n)), dtype=dtype)

    def gradients(loss):
        policy.zero_grad()
        loss.backward()
        return {k: p.grad.clone() for k, p in policy.named_parameters() if p.grad is not None}

    mean, _, value = policy(batch)
    got = gradients((mean * w).sum() + (value * u).sum())
    ref_means, ref_value = _reference(policy, pos, vel, glob, lists)
    want = gradients(sum((m * w[i, : len(m)]).sum() for i, m in enumerate(ref_means)) + (ref_value * u).sum())
    for i, m in enumerate(ref_means):
        torch.testing.assert_close(mean[i, : len(m)], m, atol=1e-5, rtol=1e-5)
    assert torch.all(mean[~batch.mask] == 0)
    torch.testing.assert_close(value, ref_value, atol=1e-5, rtol=1e-5)
    assert got.keys() == want.keys() and len(got) == len(list(policy.parameters())) - 1  # all but log_std
    for k in want:
        scale = max(1.0, float(want[k].abs().max())) if dtype == torch.float32 else 1.0
        torch.testing.assert_close(got[k], want[k], atol=1e-5 * scale, rtol=1e-5, msg=lambda m, k=k: f"{k}: {m}")

    # The pyg backend (PyG on the packed batch's edge list) agrees too.
    pyg = GraphActorCritic(policy.config, backend="pyg").to(dtype)
    pyg.load_state_dict(policy.state_dict())
    pyg_mean, _, pyg_value = pyg(batch)
    torch.testing.assert_close(pyg_mean, mean, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(pyg_value, value, atol=1e-5, rtol=1e-5)


def _general_path(batch: ChainBatch) -> ChainBatch:
    """``batch`` (of chains) with the tree path's index plan: each slot's sender named explicitly (link k),
    so that the network gathers and scatter-adds instead of its chain path's shifted adds."""
    packed = batch.packed
    assert packed.sender is None
    general = replace(packed, sender=torch.arange(packed.edge_attr.shape[0]))
    out = replace(batch)  # a copy, whose packed layout is then swapped
    object.__setattr__(out, "packed", general)
    return out


def test_shipped_model_on_chains_is_unchanged_by_the_tree_path():
    # Today's outputs on chains of 2..64 joints: the chain path (shifted adds, as before trees) equals the
    # general tree path on the same chains to 1e-6 (torch and NumPy), and PyG's NNConv on the explicit chain
    # edge lists, one chain at a time.
    policy = GraphActorCritic.load(SHIPPED).eval()
    rng = np.random.default_rng(12345)
    shapes = [(n, "chain") for n in range(2, 65)]
    pos, vel, glob, n, parents, lists = _trees(rng, shapes)
    with torch.no_grad():
        batch = ChainBatch.from_padded(pos, vel, glob, n, parents=parents)
        assert batch.parents is None  # chain parents are a chain batch
        mean, _, value = policy(batch)
        tree_mean, _, tree_value = policy(_general_path(batch))
        ref_means, ref_value = _reference(policy, pos, vel, glob, lists)
    assert float((mean - tree_mean).abs().max()) <= 1e-6 and float((value - tree_value).abs().max()) <= 1e-6
    for i, m in enumerate(ref_means):
        torch.testing.assert_close(mean[i, : len(m)], m, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(value, ref_value, atol=1e-5, rtol=1e-5)

    numpy_policy = NumpyPolicy(policy)
    np_mean, np_value = numpy_policy.forward(pos, vel, glob, n)
    np.testing.assert_allclose(np_mean, mean.numpy(), atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(np_value, value.numpy(), atol=1e-5, rtol=1e-5)
    coef = np.ones((64, 3), np.float32)
    coef[:, 0], coef[:, 1] = pos[-1], vel[-1]  # the 64-joint chain: the links by both paths
    convs = numpy_policy.net.convs
    chain_links = link_embeddings(NUMPY_OPS, convs, coef, None)
    tree_links = link_embeddings(NUMPY_OPS, convs, coef, np.arange(64))
    assert np.abs(chain_links - tree_links).max() <= 1e-6 and np.abs(chain_links).max() > 0


@pytest.mark.parametrize("bidirectional", [True, False])
def test_numpy_trees_equal_torch(bidirectional):
    policy = _perturbed(PolicyConfig(bidirectional=bidirectional), seed=4)
    numpy_policy = NumpyPolicy(policy)
    rng = np.random.default_rng(5)
    pos, vel, glob, n, parents, lists = _trees(rng, MIXES["mixed"] + MIXES["random"])
    with torch.no_grad():
        batch = ChainBatch.from_padded(pos, vel, glob, n, parents=parents)
        mean, _, value = policy(batch)
    np_mean, np_value = numpy_policy.forward(pos, vel, glob, n, parents)
    np.testing.assert_allclose(np_mean, mean.numpy(), atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(np_value, value.numpy(), atol=1e-5, rtol=1e-5)
    np.testing.assert_array_equal(numpy_policy.mean_actions(pos, vel, glob, n, parents), np_mean)
    noise = rng.normal(0, 1, pos.shape)
    action, log_prob, act_value, act_mean = numpy_policy.act(pos, vel, glob, n, noise, parents)
    np.testing.assert_array_equal(act_mean, np_mean)
    np.testing.assert_array_equal(act_value, np_value)
    with torch.no_grad():
        torch_log_prob = policy.log_prob(batch, torch.as_tensor(action))
    np.testing.assert_allclose(log_prob, torch_log_prob.numpy(), atol=1e-4, rtol=1e-5)
    for i, p in enumerate(lists):  # one tree at a time, as a controller calls it
        k = len(p)
        one = numpy_policy.mean(pos[i, :k], vel[i, :k], glob[i], np.array(p))
        np.testing.assert_allclose(one, mean[i, :k].numpy(), atol=1e-5, rtol=1e-5)
        sample, sample_mean = numpy_policy.sample(pos[i, :k], vel[i, :k], glob[i], np.random.default_rng(0), p)
        np.testing.assert_array_equal(sample_mean, one.astype(np.float64))
        assert sample.shape == (k,)


def test_a_tree_is_not_its_chain():
    # The same states as a star and as a chain give other actions: the parents reach the network.
    policy = _perturbed(PolicyConfig(), seed=6)
    rng = np.random.default_rng(7)
    pos, vel, glob, n, _, _ = _trees(rng, [(6, "chain")])
    with torch.no_grad():
        chain = policy(ChainBatch.from_padded(pos, vel, glob, n))[0]
        star = policy(ChainBatch.from_padded(pos, vel, glob, n, parents=[[-1] * 6]))[0]
    assert float((chain - star).abs().max()) > 1e-2
    star_np = NumpyPolicy(policy).mean(pos[0], vel[0], glob[0], np.full(6, -1))
    np.testing.assert_allclose(star_np, star[0].numpy(), atol=1e-5, rtol=1e-5)


def test_packed_trees_name_each_slots_parent_link():
    # Two samples: a fork of 3 joints (joints 1 and 2 on joint 0) and a star of 2; links 0..3 and 4..6.
    parents = [[-1, 0, 0], [-1, -1, 7]]  # the 7 is padding: ignored
    batch = ChainBatch.from_padded(torch.ones(2, 3), torch.ones(2, 3), torch.zeros(2, 4), [3, 2], parents=parents)
    packed = batch.packed
    assert batch.parents.tolist() == [[-1, 0, 0], [-1, -1, -1]]
    assert packed.slot_mask.tolist() == [True, True, True, False, True, True]
    assert packed.joint_link.tolist() == [1, 2, 3, 5, 6]  # the child link of each joint
    assert packed.sender.tolist() == [0, 1, 1, 3, 4, 4]  # its parent link (a cut: its own index)
    star = batch.select(torch.tensor([1]))  # trimmed to its 2 joints, still a tree
    assert star.max_joints == 2 and star.parents.tolist() == [[-1, -1]] and star.packed.sender.tolist() == [0, 0]


def test_bad_parents_are_refused_with_the_joint_named():
    pos, glob = np.zeros((2, 3), np.float32), np.zeros((2, 4), np.float32)
    cases = {
        "earlier joint": [[-1, 0, 2], [-1, 0, 1]],  # joint 2 on itself
        "torso": [[-1, 0, 1], [-1, -2, 0]],
    }
    for match, parents in cases.items():
        with pytest.raises(ValueError, match=match):
            ChainBatch.from_padded(pos, pos, glob, [3, 3], parents=parents)
        with pytest.raises(ValueError, match=match):
            ChainBatch.from_zero_padded(pos, pos, glob, np.array([3, 3]), parents=np.array(parents))
        with pytest.raises(ValueError, match=match):
            NumpyPolicy(GraphActorCritic()).forward(pos, pos, glob, np.array([3, 3]), np.array(parents))
    with pytest.raises(ValueError, match="shape|must be"):
        ChainBatch.from_padded(pos, pos, glob, [3, 3], parents=[[-1, 0], [-1, 0]])
    with pytest.raises(ValueError, match="integers"):
        ChainBatch.from_padded(pos, pos, glob, [3, 3], parents=np.zeros((2, 3)) - 1.0)
    with pytest.raises(ValueError, match=r"parents\[1\]"):
        NumpyPolicy(GraphActorCritic()).mean(np.zeros(2), np.zeros(2), np.zeros(4), np.array([-1, 1]))


def test_observations_may_carry_parents():
    rng = np.random.default_rng(8)
    obs = [
        {"joint_pos": rng.normal(0, 1, 4), "joint_vel": rng.normal(0, 1, 4), "global": rng.normal(0, 1, 4),
         "parents": [-1, 0, 0, -1]},
        {"joint_pos": rng.normal(0, 1, 2), "joint_vel": rng.normal(0, 1, 2), "global": rng.normal(0, 1, 4)},
    ]  # fmt: skip
    batch = ChainBatch.from_observations(obs)
    assert batch.parents.tolist() == [[-1, 0, 0, -1], [-1, 0, -1, -1]]  # the second a chain, padded with -1
    assert ChainBatch.from_observations(obs[1:]).parents is None
    chain_too = dict(obs[0], parents=[-1, 0, 1, 2])
    assert ChainBatch.from_observations([chain_too]).parents is None  # a chain, whichever way it is given
    sub = batch.select(torch.tensor([0]))
    assert sub.parents.tolist() == [[-1, 0, 0, -1]]
    assert batch.select(torch.tensor([1])).parents is None
