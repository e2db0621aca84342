"""Rollout workers (``algo.rollout_workers``): one worker with the run's generator is the one-process loop's
collection; a worker given the parameters as a vector collects what one sharing the policy does; the
config's checks."""

import numpy as np
import pytest
import torch

from morph_core.algo.rollout import Rollout, collect, rollout_layout
from morph_core.algo.rollout_workers import LocalPool, RolloutWorker, env_bounds, worker_seed
from morph_core.algo.train import TrainConfig, rollout_spec, train
from morph_core.env.vec_env import SwimmerVecEnv
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.numpy_actor import NumpyPolicy

CFG = TrainConfig(num_envs=3, num_steps=50, minibatch_size=50, bodies="2-6,y:2x1", seed=3, compile=False)


def _policy(seed: int = 0) -> GraphActorCritic:
    torch.manual_seed(seed)
    return GraphActorCritic(CFG.policy)


def _equal(a: Rollout, b: Rollout) -> None:
    for name in rollout_layout(1, 1, 1):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_one_local_worker_collects_what_the_one_process_loop_did():
    # The loop before rollout workers: every swimmer in one vector env seeded with the run's seed, the
    # noise from the run's generator, the observation carried from one rollout to the next.
    policy = _policy()
    envs = SwimmerVecEnv(CFG.num_envs, CFG.body_mix, seed=CFG.seed)
    before, gen = Rollout(CFG.num_steps, CFG.num_envs, envs.max_joints), torch.Generator().manual_seed(CFG.seed)
    worker = RolloutWorker(rollout_spec(CFG).worker(0, 1), policy, generator=torch.Generator().manual_seed(CFG.seed))
    pool = LocalPool(worker)
    obs = envs.observations()
    for _ in range(3):
        obs, episodes = collect(envs, NumpyPolicy(policy), before, obs, gen)
        pool.start(torch.zeros(1))
        assert pool.finish() == episodes
        _equal(pool.rollout, before)
        with torch.no_grad():  # the policy moves between rollouts, as an update moves it
            policy.log_std.add_(0.1)
    assert torch.equal(pool.worker.generator.get_state(), gen.get_state())
    pool.close()


def test_a_worker_given_the_parameters_collects_what_one_sharing_the_policy_does():
    spec = rollout_spec(CFG).worker(1, 2)
    assert (spec.lo, spec.hi) == tuple(env_bounds(3, 2)[1]) and spec.noise_seed == worker_seed(CFG.seed, 1)
    source = _policy(1)
    shared = RolloutWorker(spec, source)  # as in a helper process: its policy holds the parameters
    own = RolloutWorker(spec)  # as in a Ray actor: parameters sent as one vector
    theta = torch.nn.utils.parameters_to_vector(source.parameters()).detach().numpy()
    for _ in range(2):
        assert shared.collect() == own.collect(theta)
        _equal(shared.rollout, own.rollout)
    state = own.get_state()
    again = RolloutWorker(spec)
    again.set_state(state)  # a worker restored from a state goes on as the one it was taken from
    assert own.collect(theta) == again.collect(theta)
    _equal(own.rollout, again.rollout)
    with pytest.raises(ValueError, match="acts with a policy it was given"):
        shared.collect(theta)


def test_rollout_workers_are_checked():
    with pytest.raises(ValueError, match=r"rollout_workers must be in 1\.\.4 \(each needs a swimmer\), got 5"):
        TrainConfig(num_envs=4, rollout_workers=5)
    with pytest.raises(ValueError, match="rollout_workers > 1 and processes > 1 both share the swimmers out"):
        TrainConfig(num_envs=4, rollout_workers=2, processes=2)


def test_several_rollout_workers_need_a_pool(tmp_path):
    cfg = TrainConfig(num_envs=2, num_steps=16, minibatch_size=16, compile=False, rollout_workers=2)
    with pytest.raises(ValueError, match="rollout_workers > 1 needs a pool of workers"):
        train(cfg, tmp_path / "run")
