"""A policy node's weight updates without DDS: newer versions adopted between answers, anything bad refused
with the running policy kept, versions of another trainer run taken."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import pytest
import torch
from safetensors.torch import save as torch_save

from morph_core.msgs.joint_state import chain_batch
from morph_core.msgs.policy_weights import PolicyWeights, pack_policy_weights
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import weights_from_arrays
from morph_core.protocol.policy_updates import PolicyUpdates


def build(w: PolicyWeights) -> GraphActorCritic:
    """The torch builder: strict state dict loading refuses missing, extra or misshapen tensors."""
    policy = GraphActorCritic(PolicyConfig.from_dict(w.config))
    policy.load_state_dict({k: torch.from_numpy(v.copy()) for k, v in w.tensors.items()})
    return policy.eval()


def message(policy: GraphActorCritic, version: int, run: str = "r1", tensors=None):
    tensors = tensors if tensors is not None else {k: v.detach().contiguous() for k, v in policy.state_dict().items()}
    dims, data = pack_policy_weights(version, asdict(policy.config), torch_save(tensors), {"run": run})
    return [d[0] for d in dims], [d[1] for d in dims], data


def policies(n: int) -> list[GraphActorCritic]:
    out = []
    for s in range(n):
        torch.manual_seed(100 + s)
        out.append(GraphActorCritic().eval())
    return out


def mean_action(policy) -> np.ndarray:
    batch = chain_batch(np.linspace(-0.3, 0.3, 4), np.zeros(4), np.array([0.1, 0.0, 0.2, 0.0]))
    return policy.act(batch, deterministic=True)[0].numpy()


def test_newer_weights_are_taken_at_the_next_answer_only():
    p0, p1, p2 = policies(3)
    updates = PolicyUpdates(build, p0)
    assert updates.offer(*message(p1, 1)).outcome == "pending"
    assert updates.version is None  # not yet: still mid-answer until current() is called
    acting = updates.current()
    assert updates.version == 1 and updates.adopted == 1
    np.testing.assert_allclose(mean_action(acting), mean_action(p1), rtol=0, atol=0)
    assert not np.allclose(mean_action(acting), mean_action(p0))
    # two offers before the next answer: the newest wins
    updates.offer(*message(p2, 2))
    updates.offer(*message(p0, 3))
    np.testing.assert_array_equal(mean_action(updates.current()), mean_action(p0))
    assert updates.version == 3 and updates.adopted == 2


def test_same_or_older_version_of_the_run_is_ignored_another_run_is_taken():
    p0, p1, p2 = policies(3)
    updates = PolicyUpdates(build, p0)
    updates.offer(*message(p1, 5))
    updates.current()
    assert updates.offer(*message(p2, 5)).outcome == "ignored"
    assert updates.offer(*message(p2, 4)).outcome == "ignored"
    assert updates.ignored == 2
    np.testing.assert_array_equal(mean_action(updates.current()), mean_action(p1))
    assert updates.offer(*message(p2, 0, run="r2")).outcome == "pending"  # a trainer started afresh
    updates.current()
    assert (updates.version, updates.run) == (0, "r2")


@pytest.mark.parametrize("damage", ["nan", "missing", "shape", "config", "bytes"])
def test_bad_weights_rejected_and_current_policy_kept(damage):
    p0, p1 = policies(2)
    updates = PolicyUpdates(build, p0, version=3, run="r1")
    state = {k: v.detach().clone().contiguous() for k, v in p1.state_dict().items()}
    name = next(iter(state))
    if damage == "nan":
        state[name].view(-1)[0] = float("nan")
    elif damage == "missing":
        del state[name]
    elif damage == "shape":
        state[name] = torch.zeros(3, 3)
    if damage == "nan":  # pack refuses NaN: put the bytes in a good message by hand
        labels, sizes, _ = message(p1, 9)
        data = torch_save(state)
    elif damage == "config":
        labels, sizes, data = message(p1, 9)
        labels[1] = labels[1].replace('"conv1_channels": 24', '"conv1_channels": 7')
    elif damage == "bytes":
        labels, sizes, data = message(p1, 9)
        data = data[:-100]
        sizes[0] = len(data)
    else:
        labels, sizes, data = message(p1, 9, tensors=state)
    offer = updates.offer(labels, sizes, data)
    expected = {"nan": "NaN", "missing": "Missing key", "shape": "size mismatch", "config": "size mismatch",
                "bytes": "safetensors"}[damage]  # fmt: skip
    assert expected in offer.reason, offer.reason
    assert offer.outcome == "rejected" and offer.reason == updates.last_error != ""
    assert updates.rejected_total == 1
    np.testing.assert_array_equal(mean_action(updates.current()), mean_action(p0))
    assert (updates.version, updates.adopted) == (3, 0)
    # and the next good one is still taken
    assert updates.offer(*message(p1, 10)).outcome == "pending"
    updates.current()
    assert updates.version == 10


def numpy_build(w: PolicyWeights) -> NumpyPolicy:
    """The policy node's builder: no torch, the checkpoint's checks (``weights_from_arrays``)."""
    return NumpyPolicy(weights_from_arrays(w.config, w.tensors, f"policy_weights version {w.version}"))


@pytest.mark.parametrize("damage", ["missing", "extra", "shape", "config"])
def test_numpy_builder_refuses_what_a_checkpoint_would_and_names_the_version(damage):
    p0, p1 = policies(2)
    updates = PolicyUpdates(numpy_build, NumpyPolicy(p0))
    state = {k: v.detach().clone().contiguous() for k, v in p1.state_dict().items()}
    name = next(iter(state))
    if damage == "missing":
        del state[name]
    elif damage == "extra":
        state["surplus.weight"] = torch.zeros(2)
    elif damage == "shape":
        state[name] = torch.zeros(3, 3)
    labels, sizes, data = message(p1, 7, tensors=state)
    if damage == "config":
        labels[1] = labels[1].replace('"conv1_channels": 24', '"conv1_channels": "many"')
    offer = updates.offer(labels, sizes, data)
    expected = {"missing": "missing", "extra": "unexpected", "shape": "has shape", "config": "config"}[damage]
    assert offer.outcome == "rejected" and expected in offer.reason and "version 7" in offer.reason, offer.reason
    pos, vel, glob = np.linspace(-0.3, 0.3, 4), np.zeros(4), np.array([0.1, 0.0, 0.2, 0.0])
    np.testing.assert_array_equal(updates.current().mean(pos, vel, glob), NumpyPolicy(p0).mean(pos, vel, glob))


def test_numpy_builder_runs_the_pushed_policy_as_torch_does():
    p0, p1 = policies(2)
    updates = PolicyUpdates(numpy_build, NumpyPolicy(p0))
    assert updates.offer(*message(p1, 1)).outcome == "pending"
    np.testing.assert_allclose(updates.current().mean(np.linspace(-0.3, 0.3, 4), np.zeros(4),
                                                      np.array([0.1, 0.0, 0.2, 0.0])),
                               mean_action(p1)[0], atol=1e-5)  # fmt: skip


def test_replace_drops_a_pending_policy_and_restarts_the_version():
    p0, p1, p2 = policies(3)
    updates = PolicyUpdates(build, p0, version=4, run="r1")
    updates.offer(*message(p1, 5))
    updates.replace(p2)  # a checkpoint set by hand after the offer: the newest action wins
    assert updates.current() is p2 and (updates.version, updates.run, updates.adopted) == (None, "", 0)
    assert updates.offer(*message(p1, 1)).outcome == "pending"  # any trainer version is newer than a file
