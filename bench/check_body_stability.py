"""Do the body families swim without MuJoCo diverging? A sweep over the shapes ``env.bodies`` can draw.

Every shape is stepped for ``--steps`` control steps (Swimmer-v5's 1000 by default) from the env's reset
(seeds 0..``--seeds``-1) under each action pattern below, all swimmers of a shape in one ``SwimmerBatch``:

    random   uniform in [-1, 1] on every joint, redrawn every step
    bang     every joint at +1, then every joint at -1, switching every 10 steps (0.4 s)
    alt      +1 / -1 alternating along the joints, the signs switching every 10 steps
    flip     every joint at +1 / -1, switching at every step (25 Hz): the hardest jerk the motors allow

A swimmer fails when MuJoCo's divergence warning (``swimmer_env.DIVERGENCE_WARNING``) fires or its state
is not finite at the end. Shapes: chains 1..64 (for reference: chains are not capped), every named shape
(star, y, comb) up to ``MAX_TREE_JOINTS``, and random trees of each branching limit: ``--random-draws`` per
size for 1..12 joints, and ``--random-large`` per size at 16, 20, ..., ``MAX_TREE_JOINTS`` joints.

    python bench/check_body_stability.py              # the full sweep quoted in docs/bodies.md
    python bench/check_body_stability.py --quick      # a few shapes, a few seconds
    python bench/check_body_stability.py --legged 3   # the legged family instead (docs/bodies.md)

``--legged N`` sweeps every legged kind (4, 6, 8 legs x 2, 3 joints x round, long, wide torsos) at body
seeds 0..N-1 (and, with ``--held-out``, as many from 1000 on) under Ant-v5's task with termination off:
the same four patterns (a body fails when MuJoCo resets a state that blew up or its state is not finite),
and also zero action (a body fails when it falls below its healthy height: it cannot stand on its joint
limits); under random actions it reports the median steps before the first unhealthy state, beside Ant's.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import defaultdict

import numpy as np

from morph_core.constants import MAX_JOINTS
from morph_core.env.bodies import (
    MAX_TREE_JOINTS,
    RANDOM_MAX_BRANCHING,
    STAR_MAX_ARMS,
    CombFamily,
    RandomTreeFamily,
    StarFamily,
    YFamily,
    body_label,
)
from morph_core.env.swimmer_batch import SwimmerBatch
from morph_core.policy.tree import KinematicTree, swimmer_joint_names

PATTERNS = ("random", "bang", "alt", "flip")


def actions(pattern: str, step: int, rows: int, n: int, rng: np.random.Generator) -> np.ndarray:
    if pattern == "random":
        return rng.uniform(-1.0, 1.0, (rows, n))
    if pattern == "flip":
        return np.full((rows, n), 1.0 if step % 2 == 0 else -1.0)
    sign = 1.0 if (step // 10) % 2 == 0 else -1.0
    if pattern == "bang":
        return np.full((rows, n), sign)
    return np.tile(sign * np.where(np.arange(n) % 2 == 0, 1.0, -1.0), (rows, 1))  # alt


def check(tree: KinematicTree, steps: int, seeds: int) -> dict[str, int]:
    """Pattern -> number of the ``seeds`` swimmers that diverged or ended with a non-finite state."""
    failed = {}
    rng = np.random.default_rng(0)
    for pattern in PATTERNS:
        batch = SwimmerBatch(tree, list(range(seeds)))
        diverged = np.zeros(seeds, dtype=bool)
        for step in range(steps):
            _, d = batch.advance(actions(pattern, step, seeds, tree.num_joints, rng))
            diverged |= d
        finite = np.isfinite(batch._qpos).all(axis=1) & np.isfinite(batch._qvel).all(axis=1)
        failed[pattern] = int((diverged | ~finite).sum())
    return failed


def shapes(quick: bool, random_draws: int, random_large: int, chains: int) -> list[tuple[str, KinematicTree]]:
    """(family, tree) of every shape swept."""
    out: list[tuple[str, KinematicTree]] = []
    chain_sizes = (1, 2, 5, 10) if quick else range(1, chains + 1)
    out += [("chain", KinematicTree.chain(n)) for n in chain_sizes]
    named = (
        [StarFamily((2, 3), (1, 3)), YFamily((1, 2), (1, 3)), CombFamily((3, 5))]
        if quick
        else [
            StarFamily((2, STAR_MAX_ARMS), (1, MAX_TREE_JOINTS // 2)),
            YFamily((1, MAX_TREE_JOINTS - 2), (1, (MAX_TREE_JOINTS - 1) // 2)),
            CombFamily((3, (MAX_TREE_JOINTS + 1) // 2)),
        ]
    )
    for family in named:
        kind = type(family).__name__.removesuffix("Family").lower()
        shapes_ = [p for _, p in family.shapes() if len(p) <= MAX_TREE_JOINTS]  # a range may pass the limit
        trees = [KinematicTree(swimmer_joint_names(len(p)), p, "torso") for p in shapes_]
        out += [(kind, tree) for tree in trees]
    rng = np.random.default_rng(12345)
    small = range(2, 7) if quick else range(1, 13)
    large = () if quick else range(16, MAX_TREE_JOINTS + 1, 4)
    for b in range(1, RANDOM_MAX_BRANCHING + 1):
        for n in small:
            out += [(f"random:b{b}", RandomTreeFamily(n, n, b).draw(rng)) for _ in range(2 if quick else random_draws)]
        for n in large:
            out += [(f"random:b{b}", RandomTreeFamily(n, n, b).draw(rng)) for _ in range(random_large)]
    return out


def check_walker(body, steps: int, seeds: int) -> tuple[dict[str, int], int, list[int]]:
    """(pattern -> episodes of ``seeds`` that blew up or ended non-finite, episodes that fell at zero action,
    steps each random-action episode stayed healthy)."""
    from morph_core.env.centipede import MorphCentipedeEnv

    env = MorphCentipedeEnv(layout="ant", terminate_when_unhealthy=False) if body == "ant" else (
        MorphCentipedeEnv(body=body, terminate_when_unhealthy=False))  # fmt: skip
    failed, fell, healthy_steps = {}, 0, []
    rng = np.random.default_rng(0)
    for pattern in (*PATTERNS, "zero"):
        failed[pattern] = 0
        for seed in range(seeds):
            env.reset(seed=seed)
            bad, first_fall = False, None
            for step in range(steps):
                a = np.zeros(env.num_joints) if pattern == "zero" else actions(pattern, step, 1, env.num_joints, rng)[0]
                env.step(a)
                bad |= env.unstable
                if first_fall is None and not env.is_healthy:
                    first_fall = step
            bad |= not (np.isfinite(env.data.qpos).all() and np.isfinite(env.data.qvel).all())
            failed[pattern] += int(bad)
            if pattern == "zero":
                fell += int(first_fall is not None)
            if pattern == "random":
                healthy_steps.append(steps if first_fall is None else first_fall)
    return failed, fell, healthy_steps


def legged_sweep(seeds: int, held_out: bool, steps: int, episodes: int) -> int:
    from morph_core.env.legged_model import LEGGED_JOINTS_PER_LEG, LEGGED_LEGS, TORSOS, LeggedBody

    started = time.monotonic()
    body_seeds = list(range(seeds)) + (list(range(1000, 1000 + seeds)) if held_out else [])
    print(f"{steps} steps per episode, {episodes} episodes per pattern, patterns {', '.join(PATTERNS)}, zero")
    print(
        f"{'kind':<16} {'bodies':>6} {'episodes':>8} {'diverged':>8} {'fell at zero':>12} "
        f"{'random: median healthy steps':>28}"
    )
    bad = 0
    kinds = [("ant", ["ant"])] + [
        (f"legged-{n}x{j}-{t}", [LeggedBody(n, j, t, s) for s in body_seeds])
        for n in LEGGED_LEGS for j in LEGGED_JOINTS_PER_LEG for t in TORSOS
    ]  # fmt: skip
    for kind, bodies in kinds:
        diverged = fell = 0
        lengths: list[int] = []
        for body in bodies:
            failed, f, h = check_walker(body, steps, episodes)
            diverged += sum(failed.values())
            fell += f
            lengths += h
            if any(failed.values()) or f:
                print(
                    f"  {getattr(body, 'label', body)}: diverged {failed}, fell at zero {f}",
                    file=sys.stderr,
                    flush=True,
                )
        if kind != "ant":
            bad += diverged
        count = len(bodies) * episodes
        print(f"{kind:<16} {len(bodies):>6} {count * (len(PATTERNS) + 1):>8} {diverged:>8} {fell:>5}/{count:<6} "
              f"{float(np.median(lengths)):>28.0f}", flush=True)  # fmt: skip
    print(f"{time.monotonic() - started:.0f} s")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--random-draws", type=int, default=10, help="random trees per size, 1..12 joints")
    parser.add_argument("--random-large", type=int, default=4, help="random trees per size, 16..32 joints")
    parser.add_argument("--chains", type=int, default=MAX_JOINTS, help="sweep chains of 1..CHAINS joints")
    parser.add_argument("--quick", action="store_true", help="a few small shapes, 200 steps")
    parser.add_argument("--legged", type=int, default=0, help="sweep the legged family at body seeds 0..N-1 instead")
    parser.add_argument("--held-out", action="store_true", help="with --legged: N more seeds from 1000 on")
    args = parser.parse_args(argv)
    steps = 200 if args.quick else args.steps
    if args.legged:
        return legged_sweep(args.legged, args.held_out, steps, args.seeds)
    started = time.monotonic()
    swept = shapes(args.quick, args.random_draws, args.random_large, args.chains)
    totals: dict[str, list[int]] = defaultdict(lambda: [0, 0, 0, 0])  # shapes, episodes, failed, max joints
    failures = []
    for family, tree in swept:
        failed = check(tree, steps, args.seeds)
        done = len([1 for t in totals.values() for _ in range(t[0])]) + 1
        if done % 50 == 0:
            print(f"  ... {done}/{len(swept)} shapes, {time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)
        t = totals[family]
        t[0] += 1
        t[1] += len(PATTERNS) * args.seeds
        t[2] += sum(failed.values())
        t[3] = max(t[3], tree.num_joints)
        if any(failed.values()):
            bad = ", ".join(f"{p} {k}/{args.seeds}" for p, k in failed.items() if k)
            failures.append(f"  {body_label(tree)} ({tree.num_joints} joints, parents {tree.parents.tolist()}): {bad}")
            print(failures[-1], file=sys.stderr, flush=True)
    print(f"{steps} steps per episode, seeds 0..{args.seeds - 1}, patterns {', '.join(PATTERNS)}")
    print(f"{'family':<10} {'shapes':>6} {'joints':>6} {'episodes':>8} {'diverged':>8}")
    for family, (count, episodes, failed, most) in totals.items():
        print(f"{family:<10} {count:>6} {'<=' + str(most):>6} {episodes:>8} {failed:>8}")
    print("failures:" if failures else "no divergence, every state finite")
    print("\n".join(failures))
    print(f"{time.monotonic() - started:.0f} s")
    return 1 if any(not f.startswith("  chain-") for f in failures) else 0


if __name__ == "__main__":
    sys.exit(main())
