"""How far the reward rebuilt from a centipede's topics lies from the env's own, on the same episodes.

    python bench/bench_legged_reward.py [--bodies centipede:2-4] [--episodes 12] [--steps 200] [--seed 0]

A loopback recording (``protocol.loopback``: the sim and a sampling policy node, in lockstep, recording what
they publish) of the shipped centipede policy (``models/centipede_gnn``, sampling, seed ``--seed``), whose
env pays Ant-v5's reward with every term; the recording turned into transitions with ``task="ant"``
(``protocol.transitions``: forward velocity, healthy reward and control cost from the topics; the contact
cost is on no topic). Per episode (``--steps`` at most, or until the centipede falls): the env's return, the
rebuilt return, and their difference; then the same recording with the env's contact cost switched off, where
only the forward term's reading differs (the odometry's x where the env reads the root's xpos, which MuJoCo
leaves one physics step behind: per step they differ, over an episode the sums meet at its ends).
"""

from __future__ import annotations

import argparse

import numpy as np

from morph_core.env.sim import SwimmerSim
from morph_core.policy.weights import load_checkpoint
from morph_core.protocol.loopback import LoopbackRecording, SamplingController
from morph_core.protocol.transitions import SkipCounts, TransitionAssembler, TransitionConfig


def shipped_centipede() -> str:
    from morph_policy_node.bringup import CENTIPEDE_MODEL
    from morph_policy_node.policy_node import SHIPPED_MODEL

    return str(SHIPPED_MODEL.with_name(CENTIPEDE_MODEL))


def returns(bodies: str, episodes: int, steps: int, seed: int, contact_cost: bool) -> tuple[np.ndarray, np.ndarray]:
    """(the env's return, the rebuilt return) of each episode recorded."""
    sim = SwimmerSim(bodies=bodies, seed=seed, effort_timeout=None)
    if not contact_cost:
        sim.robot._env._centipede.contact_cost_weight = 0.0
    loop = LoopbackRecording(sim, SamplingController(load_checkpoint(shipped_centipede()), seed=seed), describe=True)
    for i in range(episodes):
        if i:
            loop.new_episode()
        loop.run(steps)
    loop.finish()
    asm = TransitionAssembler(TransitionConfig(task="ant"))
    transitions = asm.push_many(loop.records) + asm.flush()
    if asm.skips != SkipCounts():
        raise SystemExit(f"steps skipped: {asm.skips}")
    paid = {s.stamp_ns: s.reward for s in loop.truth if s.reward is not None}
    env, ours = {}, {}
    for t in transitions:
        env[t.episode] = env.get(t.episode, 0.0) + paid[t.stamp_ns]
        ours[t.episode] = ours.get(t.episode, 0.0) + t.reward
    return np.array(list(env.values())), np.array(list(ours.values()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bodies", default="centipede:2-4")
    ap.add_argument("--episodes", type=int, default=12, help="episodes recorded (the loopback's runs)")
    ap.add_argument("--steps", type=int, default=200, help="control steps per run (a fall ends an episode early)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    for contact in (True, False):
        env, ours = returns(args.bodies, args.episodes, args.steps, args.seed, contact)
        gap = ours - env
        what = "Ant-v5's reward (contact cost on)" if contact else "contact cost off"
        print(f"{what}: {len(env)} episodes, env return {env.mean():.3f} (mean), rebuilt {ours.mean():.3f}; "
              f"rebuilt - env per episode: mean {gap.mean():+.4f}, max |.| {np.abs(gap).max():.4f}, "
              f"relative to |env| {np.abs(gap).sum() / np.abs(env).sum():.2%}")  # fmt: skip


if __name__ == "__main__":
    main()
