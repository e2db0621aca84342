"""The minibatch gradient training takes (forward and backward one compiled graph) equals autograd's."""

import copy
import functools

import numpy as np
import pytest
import torch

from morph_core.algo.batch import Minibatch
from morph_core.algo.compiled import compiled
from morph_core.algo.learner import minibatch_gradient
from morph_core.algo.param_buffer import FlatParameters
from morph_core.algo.ppo import ppo_loss
from morph_core.algo.trust_region import get_rule
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch


def _minibatch(rng, size, max_joints, weighted):
    n = rng.integers(2, max_joints + 1, size)
    pos = rng.normal(0, 1, (size, max_joints)) * (np.arange(max_joints) < n[:, None])
    batch = ChainBatch.from_padded(pos, rng.normal(0, 3, (size, max_joints)), rng.normal(0, 1, (size, 4)), n)
    actions = rng.normal(0, 0.5, (size, batch.max_joints))
    old_log_prob, advantages, returns = rng.normal(-5, 1, size), rng.normal(0, 1, size), rng.normal(0, 1, size)
    tensors = [torch.as_tensor(x, dtype=torch.float32) for x in (actions, old_log_prob, advantages, returns)]
    clip_range = get_rule("compensated").clip_range(0.111, batch.num_joints.to(torch.float32))
    weight = torch.as_tensor(rng.uniform(0.2, 1.0, size), dtype=torch.float32) if weighted else None
    return batch, *tensors, clip_range, weight


class _Paths:
    """A policy's loss under ``rule`` differentiated three ways: plain autograd on the module's own
    parameters (a copy of it), and the training path's function of the flat parameters, eager and
    compiled (each made once, so every minibatch goes through the same compiled graph)."""

    def __init__(self, rule):
        self.plain_policy = GraphActorCritic()
        self.loss = functools.partial(ppo_loss, rule=get_rule(rule))
        policy = copy.deepcopy(self.plain_policy)
        self.flat = FlatParameters(policy)
        self.fns = {c: minibatch_gradient(policy, self.flat, get_rule(rule), c) for c in (False, True)}

    def __call__(self, args, kwargs):
        """(loss terms, gradient) by plain autograd; {compile: (gradient, (loss, statistics))}."""
        *samples, vf_coef, ent_coef = args
        mb = Minibatch(*samples, **kwargs)  # the samples as the loss reads them
        self.plain_policy.zero_grad()
        out = self.loss(self.plain_policy, mb, vf_coef, ent_coef)
        out[0].backward()
        plain = (out, torch.cat([p.grad.flatten() for p in self.plain_policy.parameters()]))
        share = torch.tensor(1.0)
        return plain, {c: fn(self.flat.theta.detach(), share, mb, vf_coef, ent_coef) for c, fn in self.fns.items()}


def _assert_same(plain, flat_results):
    (loss, pg_loss, v_loss, entropy, log_ratio, clip_share), grad = plain
    for flat_grad, (flat_loss, stats) in flat_results.values():
        torch.testing.assert_close(flat_grad, grad, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(flat_loss, loss.detach(), atol=1e-5, rtol=1e-4)
        for name, value in (("pg_loss", pg_loss), ("v_loss", v_loss), ("entropy", entropy), ("log_ratio", log_ratio)):
            torch.testing.assert_close(stats[name], value.detach(), atol=1e-5, rtol=1e-4)
        assert ("clip_share" in stats) == (clip_share is not None)
        if clip_share is not None:
            torch.testing.assert_close(stats["clip_share"], clip_share.detach(), atol=1e-5, rtol=1e-4)
    assert grad.abs().max() > 0


@pytest.mark.slow
@pytest.mark.parametrize("weighted", [False, True])
def test_compiled_gradient_of_the_flat_parameters_equals_autograd_on_the_module(weighted):
    # The training path differentiates the loss as a function of all parameters in one vector, compiled
    # (forward and backward one graph, by torch.func) or eagerly (by autograd): both equal plain autograd
    # on the module's own parameters, for two minibatches with different chain mixes (and sizes) through
    # one compiled graph. Weighted: the off-policy loss, each sample's policy term weighted (algo.update).
    torch.manual_seed(0)
    paths = _Paths("compensated")
    rng = np.random.default_rng(0)
    for size, max_joints in ((64, 10), (48, 7)):
        _assert_same(*paths((*_minibatch(rng, size, max_joints, weighted), 0.5, 0.01), {}))
    assert not paths.fns[True].fell_back  # it really ran compiled


@pytest.mark.slow
@pytest.mark.parametrize("rule", ["per-joint-clip", "kl-penalty-per-joint"])
def test_compiled_gradient_of_the_per_joint_rules_equals_autograd(rule):
    # These rules take the proximal policy's means and log-std (and beta), and per-joint-clip returns its
    # clip share from inside the loss: all of it through the compiled graph, for two chain mixes. (It
    # stays before the test without a compiler: run after that one in the same process, it fell back.)
    torch.manual_seed(0)
    paths = _Paths(rule)
    rng = np.random.default_rng(1)
    for size, max_joints in ((64, 10), (48, 7)):
        batch, *rest = _minibatch(rng, size, max_joints, weighted=False)
        with torch.no_grad():
            noise = torch.as_tensor(rng.normal(0, 0.05, batch.mask.shape), dtype=torch.float32)
            old_mean = paths.plain_policy(batch)[0] + noise
        extra = {"old_mean": old_mean * batch.mask, "old_log_std": torch.tensor(-0.6), "kl_beta": torch.tensor(0.7)}
        plain, flat_results = paths((batch, *rest, 0.5, 0.01), extra)
        assert (plain[0][5] is None) == (rule != "per-joint-clip")
        _assert_same(plain, flat_results)
    assert not paths.fns[True].fell_back


def _tree_minibatch(rng, size, max_joints):
    """``_minibatch``'s samples as random kinematic trees (parents drawn per joint from -1..j-1)."""
    batch, *rest = _minibatch(rng, size, max_joints, weighted=False)
    parents = np.array([[rng.integers(-1, j) if j else -1 for j in range(batch.max_joints)] for _ in range(size)])
    tree = ChainBatch.from_padded(batch.joint_pos, batch.joint_vel, batch.global_feats, batch.num_joints,
                                  parents=parents)  # fmt: skip
    assert tree.packed.sender is not None
    return tree, *rest


@pytest.mark.slow
def test_compiled_gradient_on_trees_equals_autograd():
    # Trees go through the compiled update too: their batches (with the index plan's sender) get a graph of
    # their own, which two tree minibatches of other sizes share, and the chains keep theirs.
    torch.manual_seed(0)
    paths = _Paths("compensated")
    rng = np.random.default_rng(4)
    for size, max_joints in ((64, 10), (48, 7)):
        _assert_same(*paths((*_tree_minibatch(rng, size, max_joints), 0.5, 0.01), {}))
    _assert_same(*paths((*_minibatch(rng, 40, 9, weighted=False), 0.5, 0.01), {}))
    assert len(paths.fns[True].graphs) == 2
    assert not paths.fns[True].fell_back


def test_a_share_scales_the_gradient_and_the_losses():
    # A process's part of a split minibatch (algo.data_parallel) scales its loss by its share.
    torch.manual_seed(0)
    policy = GraphActorCritic()
    flat = FlatParameters(policy)
    args = (Minibatch(*_minibatch(np.random.default_rng(2), 32, 6, weighted=False)), 0.5, 0.01)
    fn = minibatch_gradient(policy, flat, get_rule("compensated"), compile=False)
    (g1, (l1, s1)), (g4, (l4, s4)) = (fn(flat.theta.detach(), torch.tensor(s), *args) for s in (1.0, 0.25))
    torch.testing.assert_close(g4, 0.25 * g1)
    torch.testing.assert_close(l4, 0.25 * l1)
    torch.testing.assert_close(s4["pg_loss"], 0.25 * s1["pg_loss"])
    torch.testing.assert_close(s4["log_ratio"], s1["log_ratio"])  # per sample: not scaled


@pytest.mark.slow
def test_without_a_cxx_compiler_training_falls_back_to_eager():
    import torch._inductor.config as inductor_config

    def scaled_softplus(x):
        return torch.nn.functional.softplus(3.0 * x) / 3.0

    eager_calls = []

    def eager_softplus(x):  # the eager form given for the fallback: what runs when compiling fails
        eager_calls.append(x)
        return torch.log1p(torch.exp(3.0 * x)) / 3.0

    x = torch.linspace(-2, 2, 9)
    fn = compiled(scaled_softplus, eager=eager_softplus)
    # Inductor's own patch, not monkeypatch: undoing a monkeypatch deleted fx_graph_cache from the config,
    # and every later compile in the process then failed and fell back to eager mode unnoticed.
    no_compiler = {"cpp.cxx": ("/nonexistent/c++",), "fx_graph_cache": False}  # a cached kernel needs no compiler
    with inductor_config.patch(no_compiler), pytest.warns(UserWarning, match="eager mode"):
        y = fn(x)
    assert fn.fell_back
    torch.testing.assert_close(y, scaled_softplus(x))
    torch.testing.assert_close(fn(x + 1), scaled_softplus(x + 1))  # later calls stay eager
    assert len(eager_calls) == 2


@pytest.mark.slow
def test_a_call_outside_the_traced_sizes_or_constants_gets_a_graph_of_its_own():
    # The graph is traced with symbolic sizes but assumes what the trace saw: no size of 0 or 1 (a
    # minibatch of one-joint chains is 1 joint wide) and the constants it was given (the value loss
    # coefficient). Calls that break either must not reuse it: each gets its own graph, with the right
    # numbers, and a call like the first again goes back to the first graph.
    torch.manual_seed(0)
    paths = _Paths("compensated")
    rng = np.random.default_rng(3)
    first = _minibatch(rng, 64, 10, weighted=False)
    _assert_same(*paths((*first, 0.5, 0.01), {}))
    states = (rng.normal(0, 1, (32, 1)), rng.normal(0, 3, (32, 1)), rng.normal(0, 1, (32, 4)))
    one_joint = ChainBatch.from_padded(*states, np.ones(32, dtype=np.int64))
    rest = [torch.as_tensor(rng.normal(0, 1, shape), dtype=torch.float32) for shape in ((32, 1), 32, 32, 32)]
    clip_range = get_rule("compensated").clip_range(0.111, one_joint.num_joints.to(torch.float32))
    _assert_same(*paths((one_joint, *rest, clip_range, None, 0.5, 0.01), {}))
    _assert_same(*paths((*first, 0.25, 0.01), {}))  # another value-loss coefficient
    _assert_same(*paths((*_minibatch(rng, 48, 7, weighted=False), 0.5, 0.01), {}))
    assert len(paths.fns[True].graphs) == 3
    assert not paths.fns[True].fell_back


@pytest.mark.slow
def test_calls_beyond_the_graphs_kept_run_eagerly(monkeypatch):
    import morph_core.algo.compiled as compiled_module

    monkeypatch.setattr(compiled_module, "MAX_GRAPHS", 1)  # the limit, not the compiler: nothing replaced
    fn = compiled(lambda x, scale: torch.nn.functional.softplus(scale * x) / scale)
    x = torch.linspace(-2, 2, 9)
    torch.testing.assert_close(fn(x, 3.0), torch.nn.functional.softplus(3.0 * x) / 3.0)
    with pytest.warns(UserWarning, match="run eagerly"):
        y = fn(x, 2.0)
    torch.testing.assert_close(y, torch.nn.functional.softplus(2.0 * x) / 2.0)
    assert len(fn.graphs) == 1 and not fn.fell_back
    torch.testing.assert_close(fn(x + 1, 3.0), torch.nn.functional.softplus(3.0 * (x + 1)) / 3.0)  # still compiled


def test_arguments_it_cannot_trace_are_refused_by_name():
    fn = compiled(lambda x, obj: x * 2)
    with pytest.raises(TypeError, match="object"):
        fn(torch.ones(3), object())


def test_the_policy_has_no_tensors_outside_its_parameters():
    # The compiled gradient takes every parameter through theta; a tensor the policy kept beside them (a
    # buffer, e.g. running observation statistics) would enter the traced graph as a constant and stay
    # stale there (algo.compiled). Adding one needs it passed as an argument of the gradient.
    for backend in ("dense", "pyg"):
        assert not list(GraphActorCritic(backend=backend).buffers())
