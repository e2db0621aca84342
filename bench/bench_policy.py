"""Policy update step: dense chain NNConv (eager and compiled) vs PyTorch Geometric's; tanh vs 2*sigmoid(2x)-1.

    python bench/bench_policy.py

One PPO-sized minibatch (256 swimmer states, chains of 2..10 joints), PPO's
loss under the compensated clip: forward, backward and a fused-Adam step, one
torch thread, with the same parameters, measured side by side: the dense layer
in eager mode, with the loss compiled and autograd's backward, with loss and
gradient one compiled graph of the flat parameters called through
``torch.compile`` and called directly (as training runs it,
``learner.minibatch_gradient`` and ``algo.compiled``), and PyG's NNConv. Then
the heads' activation alone. Then kinematic trees against chains of the same
joint counts (random parents), and chains on the trees' general path (gather
and scatter-add with every sender named) against their own shifted adds:

    python bench/bench_policy.py --trees    # that table alone
"""

from __future__ import annotations

import copy
import sys
import time
from dataclasses import replace

import gymnasium
import torch

import morph_core.env.registration  # noqa: F401  (registers MorphSwimmer-v0)
from morph_core.algo.batch import Minibatch
from morph_core.algo.learner import minibatch_gradient
from morph_core.algo.param_buffer import FlatParameters
from morph_core.algo.ppo import ppo_loss
from morph_core.algo.trust_region import get_rule
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.chains import ChainBatch
from morph_core.policy.numpy_actor import NumpyPolicy


def per_call_ms(fn, calls: int) -> float:
    for _ in range(10):
        fn()
    t = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - t) / calls * 1e3


def main() -> None:
    torch.set_num_threads(1)
    env = gymnasium.make("MorphSwimmer-v0", num_joints=(2, 10))
    batch = ChainBatch.from_observations([env.reset(seed=s)[0] for s in range(256)])
    actions = torch.randn(256, batch.max_joints)
    dense = GraphActorCritic(PolicyConfig(), backend="dense")
    pyg = GraphActorCritic(PolicyConfig(), backend="pyg")
    pyg.load_state_dict(dense.state_dict())

    rule = get_rule("compensated")
    mb = Minibatch(batch, actions, torch.randn(256) - 5.0, torch.randn(256), torch.randn(256),
                   rule.clip_range(0.2, batch.num_joints.to(torch.float32)))  # fmt: skip
    loss_args = (mb, 0.5, 0.0)  # the minibatch, vf_coef, ent_coef

    def loss_of(net):
        return ppo_loss(net, *loss_args, rule=rule)[0]

    def autograd_step(net, loss_fn):
        opt = torch.optim.Adam(net.parameters(), lr=1e-5, fused=True)

        def step():
            loss = loss_fn(net)
            opt.zero_grad()
            loss.backward()
            opt.step()

        return step

    def flat_step(net, direct=True):
        policy = copy.deepcopy(net)  # its parameters become views into the flat vector
        flat = FlatParameters(policy)
        opt = torch.optim.Adam([flat.theta], lr=1e-5, fused=True)
        gradient = minibatch_gradient(policy, flat, rule, compile=True)
        if not direct:  # the same function through torch.compile's per-call machinery (training before 3eaadb7)
            gradient = torch.compile(gradient.__wrapped__, dynamic=True, options={"cpp_wrapper": True})
        share = torch.tensor(1.0)

        def step():
            grad, _ = gradient(flat.theta.detach(), share, *loss_args)
            flat.grad.copy_(grad)
            opt.step()

        return step

    loss_compiled = torch.compile(loss_of, dynamic=True, options={"cpp_wrapper": True})
    print("| backend | forward+backward+Adam, 256 states (ms) |\n|---|---:|")
    for name, step in (
        ("dense chain NNConv, eager", autograd_step(dense, loss_of)),
        ("dense chain NNConv, loss compiled, autograd's backward", autograd_step(dense, loss_compiled)),
        ("dense chain NNConv, loss and gradient one graph, through torch.compile", flat_step(dense, direct=False)),
        ("dense chain NNConv, loss and gradient one graph, called directly (training)", flat_step(dense)),
        ("PyG NNConv, eager", autograd_step(pyg, loss_of)),
    ):
        print(f"| {name} | {per_call_ms(step, 300):.2f} |")
    x = torch.randn(1536, 64)  # ~the actor head's hidden layer on a minibatch's joints
    t_tanh = per_call_ms(lambda: torch.tanh(x), 1000) * 1e3
    t_sig = per_call_ms(lambda: torch.sigmoid(2.0 * x).mul(2.0).sub(1.0), 1000) * 1e3
    print(f"\ntanh on 1536x64: torch.tanh {t_tanh:.0f} us, 2*sigmoid(2x)-1 {t_sig:.0f} us ({t_tanh / t_sig:.1f}x)")


def general_path(batch: ChainBatch) -> ChainBatch:
    """A batch of chains whose every slot names its sender (link k), as a tree's does: the network gathers and
    scatter-adds instead of shifting."""
    out = replace(batch)
    object.__setattr__(out, "packed", replace(batch.packed, sender=torch.arange(batch.packed.edge_attr.shape[0])))
    return out


def trees_vs_chains() -> None:
    torch.set_num_threads(1)
    env = gymnasium.make("MorphSwimmer-v0", num_joints=(2, 10))
    chains = ChainBatch.from_observations([env.reset(seed=s)[0] for s in range(256)])
    gen = torch.Generator().manual_seed(0)
    parents = torch.stack([torch.tensor([-1, *(int(torch.randint(-1, j, (1,), generator=gen)) for j in range(1, 10))])
                           for _ in range(256)])[:, : chains.max_joints]  # fmt: skip
    trees = ChainBatch.from_padded(chains.joint_pos, chains.joint_vel, chains.global_feats, chains.num_joints,
                                   parents=parents)  # fmt: skip
    assert trees.parents is not None
    actions = torch.randn(256, chains.max_joints)
    rule = get_rule("compensated")
    policy = GraphActorCritic(PolicyConfig())
    net = copy.deepcopy(policy)  # its parameters become views into the flat vector
    flat = FlatParameters(net)
    gradient = minibatch_gradient(net, flat, rule, compile=True)
    eager = minibatch_gradient(net, flat, rule, compile=False)
    share = torch.tensor(1.0)

    def args(batch):
        return (Minibatch(batch, actions, torch.randn(256) - 5.0, torch.randn(256), torch.randn(256),
                          rule.clip_range(0.2, batch.num_joints.to(torch.float32))), 0.5, 0.0)  # fmt: skip

    numpy_policy = NumpyPolicy(policy)
    six = [0, 1, 2, 3, 4, 5]
    pos, vel, glob, n = (x[six].numpy() for x in (chains.joint_pos, chains.joint_vel, chains.global_feats,
                                                   chains.num_joints))  # fmt: skip
    tree_parents = trees.parents[six].numpy()
    noise = torch.randn(6, chains.max_joints).numpy()
    print(f"\n| 256 states, 2..10 joints ({int(chains.num_joints.sum())} joints), ms | chains | chains, general path "
          "| trees (random parents) |\n|---|---:|---:|---:|")  # fmt: skip
    for name, make in (
        ("update step, loss and gradient one compiled graph", lambda b: lambda: gradient(flat.theta.detach(), share,
                                                                                           *args(b))),
        ("update step, eager", lambda b: lambda: eager(flat.theta.detach(), share, *args(b))),
        ("forward, eager, no grad", lambda b: torch.no_grad()(lambda: policy(b))),
        ("batch building (from_padded)", lambda b: lambda: b.select(torch.arange(256))),
    ):  # fmt: skip
        row = [per_call_ms(make(b), 200) for b in (chains, general_path(chains), trees)]
        print(f"| {name} | " + " | ".join(f"{x:.3f}" for x in row) + " |")
    row = [per_call_ms(lambda p=p: numpy_policy.act(pos, vel, glob, n, noise, p), 2000) for p in (None, tree_parents)]
    print(f"| NumPy act, 6 states (rollout step) | {row[0]:.3f} | | {row[1]:.3f} |")


if __name__ == "__main__":
    if "--trees" not in sys.argv[1:]:
        main()
    trees_vs_chains()
