"""Policy update step: dense chain NNConv (eager and compiled) vs PyTorch Geometric's; tanh vs 2*sigmoid(2x)-1.

    python bench/bench_policy.py

One PPO-sized minibatch (256 swimmer states, chains of 2..10 joints): forward,
backward and a fused-Adam step, one torch thread, with the same parameters,
measured side by side: the dense layer in eager mode and under torch.compile
(as training runs it), and PyG's NNConv. Then the heads' activation alone.
"""

from __future__ import annotations

import time

import gymnasium
import torch

import morph_core  # noqa: F401  (registers MorphSwimmer-v0)
from morph_core.algo.compiled import compiled
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.chains import ChainBatch


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

    def loss_of(net, batch, actions):
        mean, _, value = net(batch)
        return net.log_prob(batch, actions, mean).mean() + value.pow(2).mean()

    fast_loss = compiled(loss_of)
    print("| backend | forward+backward+Adam, 256 states (ms) |\n|---|---:|")
    for name, net, loss_fn in (
        ("dense chain NNConv, eager", dense, loss_of),
        ("dense chain NNConv, torch.compile", dense, fast_loss),
        ("PyG NNConv, eager", pyg, loss_of),
    ):
        opt = torch.optim.Adam(net.parameters(), lr=1e-5, fused=True)

        def step(net=net, opt=opt, loss_fn=loss_fn):
            loss = loss_fn(net, batch, actions)
            opt.zero_grad()
            loss.backward()
            opt.step()

        print(f"| {name} | {per_call_ms(step, 100):.2f} |")
    x = torch.randn(1536, 64)  # ~the actor head's hidden layer on a minibatch's joints
    t_tanh = per_call_ms(lambda: torch.tanh(x), 1000) * 1e3
    t_sig = per_call_ms(lambda: torch.sigmoid(2.0 * x).mul(2.0).sub(1.0), 1000) * 1e3
    print(f"\ntanh on 1536x64: torch.tanh {t_tanh:.0f} us, 2*sigmoid(2x)-1 {t_sig:.0f} us ({t_tanh / t_sig:.1f}x)")


if __name__ == "__main__":
    main()
