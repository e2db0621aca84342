"""A policy node's weight updates without DDS: trusted newer versions adopted between answers; untrusted, replayed
or bad weights refused by reason with the running policy kept; a later trainer run's versions taken; a
checkpoint's signature checked."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np
import pytest
import torch
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from safetensors.torch import save as torch_save

from morph_core.msgs.policy_weights import PolicyWeights, pack_policy_weights
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.chains import chain_batch
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import CheckpointError, SignedWeights, load_checkpoint, weights_from_arrays
from morph_core.protocol.policy_updates import PolicyUpdates, checkpoint_trust
from morph_core.protocol.trust import Signer, TrustedKey, TrustedKeys, fingerprint, sha256_hex

TRAINER = Signer(Ed25519PrivateKey.from_private_bytes(bytes(range(32))))
OTHER = Signer(Ed25519PrivateKey.from_private_bytes(bytes(range(1, 33))))
KEYS = TrustedKeys([TrustedKey(TRAINER.public_key, fingerprint(TRAINER.public_key), "test")])
EPOCH = 1_000


def build(w: PolicyWeights) -> GraphActorCritic:
    """The torch builder: strict state dict loading refuses missing, extra or misshapen tensors."""
    policy = GraphActorCritic(PolicyConfig.from_dict(w.config))
    policy.load_state_dict({k: torch.from_numpy(v.copy()) for k, v in w.tensors.items()})
    return policy.eval()


def message(policy: GraphActorCritic, version: int, epoch: int = EPOCH, tensors=None, signer=TRAINER):
    tensors = tensors if tensors is not None else {k: v.detach().contiguous() for k, v in policy.state_dict().items()}
    dims, data = pack_policy_weights(version, asdict(policy.config), torch_save(tensors), {"run": "r"}, epoch, signer)
    return [d[0] for d in dims], [d[1] for d in dims], data


def updates_of(build, policy, **kw) -> PolicyUpdates:
    return PolicyUpdates(build, policy, KEYS, **kw)


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
    updates = updates_of(build, p0)
    offer = updates.offer(*message(p1, 1))
    assert (offer.outcome, offer.signer) == ("pending", TRAINER.fingerprint)
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


def test_the_same_version_is_ignored_an_older_one_refused_as_a_replay_a_later_run_taken():
    p0, p1, p2 = policies(3)
    updates = updates_of(build, p0)
    updates.offer(*message(p1, 5))
    updates.current()
    assert updates.offer(*message(p2, 5)).code == "not_newer"  # the trainer re-publishes every second
    assert updates.ignored == 1 and updates.rejected_total == 0
    for older in (message(p2, 4), message(p2, 9, epoch=EPOCH - 1)):  # this run's past, or an earlier run's
        offer = updates.offer(*older)
        assert (offer.outcome, offer.code) == ("rejected", "replayed") and "replay" in offer.reason
    np.testing.assert_array_equal(mean_action(updates.current()), mean_action(p1))
    assert updates.offer(*message(p2, 0, epoch=EPOCH + 1)).outcome == "pending"  # a trainer started afresh
    updates.current()
    assert (updates.version, updates.newest) == (0, (EPOCH + 1, 0))


def test_only_weights_a_trusted_key_signed_are_taken():
    p0, p1 = policies(2)
    updates = updates_of(build, p0)
    labels, sizes, data = message(p1, 3)
    altered = bytearray(data)
    altered[-5] ^= 1  # a bit of the weights flipped (still a valid safetensors file)
    forged = list(labels)
    forged[1] = forged[1].replace('"version": 3', '"version": 30')  # a version raised to jump the queue
    moved = list(labels)
    moved[2] = message(p0, 3)[0][2]  # the trainer's signature of other weights
    cases = {
        "unsigned": message(p1, 3, signer=None),
        "untrusted_key": message(p1, 3, signer=OTHER),
        "bad_signature": (labels, sizes, bytes(altered)),
        "bad_signature ": (forged, sizes, data),
        "bad_signature  ": (moved, sizes, data),
        "signature_malformed": (labels[:2] + ["not a signature"], sizes, data),
    }
    for code, msg in cases.items():
        offer = updates.offer(*msg)
        assert (offer.outcome, offer.code) == ("rejected", code.strip()), (code, offer)
    assert updates.rejected_total == len(cases) and updates.newest is None
    np.testing.assert_array_equal(mean_action(updates.current()), mean_action(p0))
    assert updates.offer(*message(p1, 3)).outcome == "pending"  # the genuine one still goes through
    assert not PolicyUpdates(build, p0).enabled and updates.enabled


def test_unsigned_weights_are_taken_only_when_asked_for_and_still_in_order():
    p0, p1, p2 = policies(3)
    assert PolicyUpdates(build, p0).offer(*message(p1, 1, signer=None)).code == "unsigned"
    updates = PolicyUpdates(build, p0, accept_unsigned=True)
    assert updates.enabled
    offer = updates.offer(*message(p1, 2, signer=None))
    assert (offer.outcome, offer.signer) == ("pending", "")
    assert updates.offer(*message(p2, 1, signer=None)).code == "replayed"
    assert updates.offer(*message(p2, 3, signer=OTHER)).code == "untrusted_key"  # a signature is still checked


@pytest.mark.parametrize("damage", ["nan", "missing", "shape", "config", "bytes"])
def test_bad_weights_rejected_and_current_policy_kept(damage):
    p0, p1 = policies(2)
    updates = updates_of(build, p0, newest=(EPOCH, 3))
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
    labels[2] = TRAINER.sign(labels[1], sha256_hex(data)).label  # the trusted trainer sent them: signed as they are
    offer = updates.offer(labels, sizes, data)
    expected = {"nan": "NaN", "missing": "Missing key", "shape": "size mismatch", "config": "size mismatch",
                "bytes": "safetensors"}[damage]  # fmt: skip
    assert expected in offer.reason, offer.reason
    assert offer.outcome == "rejected" and offer.reason == updates.last_error != ""
    assert updates.rejected_total == 1
    np.testing.assert_array_equal(mean_action(updates.current()), mean_action(p0))
    assert (updates.version, updates.adopted, updates.newest) == (None, 0, (EPOCH, 3))
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
    updates = updates_of(numpy_build, NumpyPolicy(p0))
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
        labels[2] = TRAINER.sign(labels[1], sha256_hex(data)).label
    offer = updates.offer(labels, sizes, data)
    expected = {"missing": "missing", "extra": "unexpected", "shape": "has shape", "config": "config"}[damage]
    assert offer.outcome == "rejected" and expected in offer.reason and "version 7" in offer.reason, offer.reason
    pos, vel, glob = np.linspace(-0.3, 0.3, 4), np.zeros(4), np.array([0.1, 0.0, 0.2, 0.0])
    np.testing.assert_array_equal(updates.current().mean(pos, vel, glob), NumpyPolicy(p0).mean(pos, vel, glob))


def test_numpy_builder_runs_the_pushed_policy_as_torch_does():
    p0, p1 = policies(2)
    updates = updates_of(numpy_build, NumpyPolicy(p0))
    assert updates.offer(*message(p1, 1)).outcome == "pending"
    np.testing.assert_allclose(updates.current().mean(np.linspace(-0.3, 0.3, 4), np.zeros(4),
                                                      np.array([0.1, 0.0, 0.2, 0.0])),
                               mean_action(p1)[0], atol=1e-5)  # fmt: skip


def test_replace_drops_a_pending_policy_and_waits_for_the_next_version():
    p0, p1, p2 = policies(3)
    updates = updates_of(build, p0, newest=(EPOCH, 4))
    updates.offer(*message(p1, 5))
    updates.replace(p2)  # a checkpoint set by hand after the offer: the newest action wins
    assert updates.current() is p2 and (updates.version, updates.signer, updates.adopted) == (None, "", 0)
    assert updates.offer(*message(p1, 5)).code == "not_newer"  # no step back to what the file replaced
    assert updates.offer(*message(p1, 6)).outcome == "pending"
    updates.replace(p2, order=(EPOCH + 5, 0))  # a signed checkpoint of a later run raises the bar
    assert updates.offer(*message(p1, 7)).code == "replayed"


def test_a_checkpoint_says_whether_and_by_whom_it_is_signed_and_an_altered_one_is_refused(tmp_path):
    (p0,) = policies(1)
    path = tmp_path / "p.safetensors"
    p0.save(path)
    assert checkpoint_trust(load_checkpoint(path), KEYS).description == "unsigned"
    labels, _, data = message(p0, 12)
    from morph_core.policy.weights import write_checkpoint

    write_checkpoint(path, data, asdict(p0.config), {"note": "x"}, SignedWeights(labels[1], labels[2]))
    trust = checkpoint_trust(load_checkpoint(path), KEYS)
    assert (trust.signer, trust.order) == (TRAINER.fingerprint, (EPOCH, 12)) and "trusted" in trust.description
    untrusted = checkpoint_trust(load_checkpoint(path), TrustedKeys())
    assert untrusted.order is None and "not a trusted key" in untrusted.description
    tampered = bytearray(data)
    tampered[-5] ^= 1
    path.write_bytes(bytes(tampered))
    with pytest.raises(CheckpointError, match="does not match the file"):
        checkpoint_trust(load_checkpoint(path), KEYS)
    assert checkpoint_trust(load_checkpoint(path), TrustedKeys()).order is None  # not ours to check: it runs
