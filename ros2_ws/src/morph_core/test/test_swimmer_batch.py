"""SwimmerBatch: swimmers of one body (chain or tree) in one MuJoCo call, bit for bit the env's steps, rewards and
observations."""

import numpy as np
import pytest

from morph_core.env.bodies import parse_bodies
from morph_core.env.swimmer_batch import SwimmerBatch
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.policy.tree import KinematicTree

Y_TREE = parse_bodies("y:2x2").first()
RANDOM_TREE = parse_bodies("random:9:b3").draw(np.random.default_rng(3))


def _envs(body, seeds: list[int]) -> list[MorphSwimmerEnv]:
    """One env per swimmer, each reset alone: a chain by its length, a tree forced by ``options``."""
    tree = isinstance(body, KinematicTree)
    envs = [MorphSwimmerEnv(num_joints=body.num_joints if tree else body) for _ in seeds]
    for env, seed in zip(envs, seeds, strict=True):
        env.reset(seed=seed, options={"tree": body} if tree else None)
    return envs


def _observations(rows: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.full((rows, width), 7.0), np.full((rows, width), 7.0), np.full((rows, 4), 7.0)  # 7: stale padding


@pytest.mark.parametrize(("body", "threads"), [(2, 1), (7, 1), (7, 2), (Y_TREE, 1), (RANDOM_TREE, 2)])
def test_the_batch_steps_as_one_env_per_swimmer_bit_for_bit(body, threads):
    seeds = [5, 6, 7, 8]
    batch, envs = SwimmerBatch(body, seeds, num_threads=threads), _envs(body, seeds)
    n = batch.num_joints
    np.testing.assert_array_equal(batch.parents, envs[0].parents)
    assert batch.tree == envs[0].tree and batch.tree.is_chain == (not isinstance(body, KinematicTree))
    width = n + 3  # padded rows, as the evaluation's
    got, want = _observations(len(seeds), width), _observations(len(seeds), width)
    rng = np.random.default_rng(0)
    for step in range(40):
        actions = rng.uniform(-1.0, 1.0, (len(seeds), n))
        ids = None if step % 3 else np.array([1, 3])  # every third step only some swimmers move
        moving = range(len(seeds)) if ids is None else ids
        reward, diverged = batch.advance(actions if ids is None else actions[ids], ids)
        expected = [envs[k].advance(actions[k]) for k in moving]
        np.testing.assert_array_equal(reward, [r for r, _ in expected])
        np.testing.assert_array_equal(diverged, [d for _, d in expected])
        batch.write_observation(*got)
        for k, env in enumerate(envs):
            env.write_observation(want[0][k], want[1][k], want[2][k])
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
    assert not np.array_equal(got[0][0], got[0][1])  # the swimmers went their own ways


def test_a_diverging_swimmer_is_reported_as_the_env_reports_it():
    # +-1 on all 64 joints from rest: the swimmer reset with seed 10_002 diverges at its first step (test_eval)
    seeds = [10_000, 10_001, 10_002]
    batch, envs = SwimmerBatch(64, seeds), _envs(64, seeds)
    bang = np.where(np.arange(64) % 2 == 0, 1.0, -1.0)
    reward, diverged = batch.advance(np.tile(bang, (3, 1)))
    expected = [env.advance(bang) for env in envs]
    assert diverged.tolist() == [d for _, d in expected] == [False, False, True]
    np.testing.assert_array_equal(reward, [r for r, _ in expected])


def test_bad_actions_and_thread_counts_are_refused():
    batch = SwimmerBatch(3, [1, 2])
    with pytest.raises(ValueError, match="NaN or inf"):
        batch.advance(np.array([[0.0, np.nan, 0.0], [0.0, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="num_threads"):
        SwimmerBatch(3, [1], num_threads=0)
    with pytest.raises(ValueError, match="at least one"):
        SwimmerBatch(3, [])
