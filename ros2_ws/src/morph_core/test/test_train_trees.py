"""Training on trees: parents travel from the swimmers through the rollout (shared memory included) into the
update; runs on a tree mix resume bit for bit, on one process and two; chains-only runs are what they were."""

import csv

import numpy as np
import pytest
import torch

from morph_core.algo.checkpoint import load_training_state
from morph_core.algo.rollout import Rollout, collect
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small
from morph_core.algo.train import TrainConfig, train
from morph_core.env.bodies import parse_bodies
from morph_core.env.vec_env import SwimmerVecEnv
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch
from morph_core.policy.index_plan import chain_parents
from morph_core.policy.numpy_actor import NumpyPolicy

SMALL = small(num_envs=4, minibatch_size=64, checkpoint_interval=256)
TREES = "2-4,random:3-6"


def _rows(run_dir):
    with RunDir(run_dir).progress.open() as f:
        return list(csv.DictReader(f))


def test_the_vector_env_writes_each_swimmers_tree_beside_its_state():
    envs = SwimmerVecEnv(6, TREES, seed=3)
    trees = 0
    for _ in range(300):  # episodes of 40 steps: several resets each, new bodies drawn
        obs = envs.observations()
        for i, env in enumerate(envs.envs):
            n = env.num_joints
            assert obs.num_joints[i] == n
            np.testing.assert_array_equal(obs.parents[i, :n], env.tree.parents)
            assert (obs.parents[i, n:] == -1).all()
            trees += not env.tree.is_chain
        envs.max_episode_steps = 40
        envs.step(np.zeros((6, envs.max_joints), np.float32))
    assert trees > 0
    envs.close()


def test_a_rollout_stores_the_parents_the_policy_acted_on():
    torch.manual_seed(0)
    policy = GraphActorCritic()
    envs = SwimmerVecEnv(4, TREES, seed=1, max_episode_steps=16)
    rollout = Rollout(48, 4, envs.max_joints)
    collect(envs, NumpyPolicy(policy), rollout, envs.observations(), torch.Generator().manual_seed(0))
    batch = rollout.batch(torch.zeros(48, 4), torch.zeros(48, 4))
    assert batch.parents is not None  # a tree among the bodies
    # Each stored step's action mean is the policy's on that step's own tree (not on a chain of its length).
    rows = torch.arange(0, 192, 7)
    chains, _ = batch.minibatch(rows)
    want = ChainBatch.from_padded(
        batch.joint_pos[rows], batch.joint_vel[rows], batch.global_feats[rows], batch.num_joints[rows],
        parents=torch.from_numpy(rollout.parents.reshape(192, -1)[rows.numpy()]),
    )  # fmt: skip
    with torch.no_grad():
        torch.testing.assert_close(policy(chains)[0], policy(want)[0])
    values = NumpyPolicy(policy).forward(
        *(getattr(rollout, k)[5] for k in ("joint_pos", "joint_vel", "global_feats", "num_joints")),
        parents=rollout.parents[5],
    )[1]
    np.testing.assert_allclose(rollout.values[5], values, rtol=1e-5, atol=1e-6)
    envs.close()


@pytest.mark.slow
@pytest.mark.parametrize("processes", [1, 2])
def test_a_run_on_trees_resumes_exactly_as_an_uninterrupted_run(tmp_path, processes):
    cfg = dict(SMALL, bodies=TREES, seed=4, processes=processes)
    straight = train(TrainConfig(total_timesteps=768, **cfg), tmp_path / "a")
    part = train(TrainConfig(total_timesteps=256, **cfg), tmp_path / "b")
    train(TrainConfig(total_timesteps=768, **cfg), part, resume=True)
    (wa, ma), (wb, mb) = (load_training_state(RunDir(run).state) for run in (straight, part))
    assert ma["sections"]["swimmers"] == mb["sections"]["swimmers"]  # the swimmers' bodies (a tree's parents), RNGs
    assert any("parents" in env for env in ma["sections"]["swimmers"]["envs"])  # a tree's state saved and restored
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    rows = _rows(straight)
    assert [r["policy_loss"] for r in rows] == [r["policy_loss"] for r in _rows(part)]
    assert "return_trees" in rows[0] and "return_chains" in rows[0]


def test_a_chain_spec_is_todays_run_bit_for_bit(tmp_path):
    chains = train(TrainConfig(total_timesteps=256, seed=2, **SMALL), tmp_path / "default")
    spelled = train(TrainConfig(total_timesteps=256, seed=2, bodies="2-10", **SMALL), tmp_path / "spelled")
    a, b = (load_training_state(RunDir(run).state)[0] for run in (chains, spelled))
    assert all(torch.equal(a[k], b[k]) for k in a)  # "2-10" is the default chains, bit for bit
    assert "return_trees" not in _rows(chains)[0]  # chains-only logs keep their columns


def test_a_bad_body_spec_is_refused_before_anything_runs(tmp_path):
    for spec in ("random:3-99", "2-1", "banana", "random:"):
        with pytest.raises(ValueError):
            TrainConfig(bodies=spec, **SMALL)
    assert not (tmp_path / "never").exists()
    # min_joints..max_joints follow the bodies (what every reader of config.json takes for the trained range)
    cfg = TrainConfig(bodies="3-5,star:3x2", **SMALL)
    assert (cfg.min_joints, cfg.max_joints, list(cfg.dims)) == (3, 6, [3, 4, 5, 6])
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg  # and a resumed run reads them back
    with pytest.raises(ValueError, match="disagree with bodies"):
        TrainConfig(bodies="3-5", min_joints=2, max_joints=8, **SMALL)


def test_chains_drawn_from_a_spec_carry_chain_parents():
    mix = parse_bodies("3-5")
    rng = np.random.default_rng(0)
    for _ in range(20):
        tree = mix.draw(rng)
        np.testing.assert_array_equal(tree.parents, chain_parents(tree.num_joints))
