"""Training on two processes: the split update equals the one-process update; runs resume bit for bit;
a helper that dies stops training with a clear error."""

import csv
import os
import signal

import numpy as np
import pytest
import torch

from morph_core.algo.checkpoint import load_training_state
from morph_core.algo.data_parallel import HelperError, Helpers, env_bounds
from morph_core.algo.learner import Learner
from morph_core.algo.minibatches import part_sizes
from morph_core.algo.ppo import compute_gae
from morph_core.algo.rollout import collect
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small
from morph_core.algo.train import TrainConfig, helper_spec, train
from morph_core.algo.trust_region import get_rule
from morph_core.algo.update import update
from morph_core.env.vec_env import SwimmerVecEnv, merge_env_states, split_env_state
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy


def _learner(cfg: TrainConfig) -> Learner:
    torch.manual_seed(cfg.seed)
    return Learner.create(GraphActorCritic(PolicyConfig()), cfg.learning_rate, cfg.adam_eps, cfg.compile)


def _shared_rollout(cfg: TrainConfig, helpers: Helpers, learner: Learner):
    """A real rollout (real swimmers) by ``learner``'s policy written into the helpers' shared rollout, with
    its advantages; its batch."""
    envs = SwimmerVecEnv(cfg.num_envs, (cfg.min_joints, cfg.max_joints), seed=cfg.seed)
    rollout = helpers.rollout
    collect(envs, NumpyPolicy(learner.policy), rollout, envs.observations(), torch.Generator().manual_seed(0))
    arrays = ("rewards", "values", "terminated", "truncated", "final_values", "last_value")
    adv, ret = compute_gae(*(torch.from_numpy(getattr(rollout, k)) for k in arrays), cfg.gamma, cfg.gae_lambda)
    helpers.publish_advantages(adv, ret)
    return rollout.batch(adv, ret)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("rule", "compiled"),
    [(rule, False) for rule in ("compensated", "per-joint-clip", "kl-penalty", "kl-stop")] + [("compensated", True)],
)
def test_the_two_process_update_equals_the_one_process_update(rule, compiled):
    # A real rollout (real swimmers, an odd minibatch size so the parts differ in size and the last
    # minibatch is short), written into the shared rollout the helper reads.
    cfg = TrainConfig(clip_mode=rule, num_envs=3, num_steps=100, minibatch_size=61, update_epochs=3, seed=4,
                      compile=compiled, kl_target=1e-4, progress_bar=False, processes=2)  # fmt: skip
    one, two = _learner(cfg), _learner(cfg)
    helpers = Helpers(helper_spec(cfg, two), two)
    try:
        batch = _shared_rollout(cfg, helpers, one)
        for _ in range(2):  # twice: the second update starts from the rule state the first one left
            stats_one = update(one, batch, cfg.update_config(), torch.Generator().manual_seed(7))
            stats_two = update(two, batch, cfg.update_config(), torch.Generator().manual_seed(7), peers=helpers)
            assert stats_one.epochs == stats_two.epochs
            torch.testing.assert_close(two.params.theta, one.params.theta, rtol=1e-4, atol=1e-5)
            # The theta moved: the equality is not that of two updates that did nothing.
            assert not torch.equal(two.params.theta, _learner(cfg).params.theta)
            for name in ("policy_loss", "value_loss", "entropy"):
                assert getattr(stats_two, name) == pytest.approx(getattr(stats_one, name), rel=1e-4, abs=1e-6)
            row_one, row_two = stats_one.row(cfg.dims), stats_two.row(cfg.dims)
            assert row_one.keys() == row_two.keys()
            for key in row_one:
                assert row_two[key] == pytest.approx(row_one[key], rel=1e-3, abs=1e-5, nan_ok=True), key
            assert one.rule_state.keys() == two.rule_state.keys()
            for key in one.rule_state:
                torch.testing.assert_close(two.rule_state[key], one.rule_state[key])
        assert not (compiled and (one.minibatch_gradient(get_rule(rule)).fell_back))
        if rule == "kl-stop":
            assert stats_one.epochs < cfg.update_epochs  # the stop was reached, on statistics from both parts
    finally:
        helpers.close()


SMALL = small(num_envs=4, checkpoint_interval=256, processes=2)


def _rows(run_dir):
    with RunDir(run_dir).progress.open() as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_a_two_process_run_resumes_exactly_as_an_uninterrupted_run(tmp_path):
    straight = train(TrainConfig(total_timesteps=768, seed=5, **SMALL), tmp_path / "a")
    part = train(TrainConfig(total_timesteps=256, seed=5, **SMALL), tmp_path / "b")
    train(TrainConfig(total_timesteps=768, seed=5, **SMALL), part, resume=True)
    (wa, ma), (wb, mb) = (load_training_state(RunDir(run).state) for run in (straight, part))
    assert ma["counters"]["global_step"] == mb["counters"]["global_step"] == 768
    assert "rng.helper1" in wa and len(ma["sections"]["swimmers"]["envs"]) == 4
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k  # weights, Adam, both processes' generators and swimmers
    assert [r["policy_loss"] for r in _rows(straight)] == [r["policy_loss"] for r in _rows(part)]


def test_the_process_count_is_checked():
    with pytest.raises(ValueError, match="processes must be in 1..4"):
        TrainConfig(num_envs=4, processes=5)
    with pytest.raises(ValueError, match="processes must be in 1..2"):  # the last minibatch holds 2 samples
        TrainConfig(num_envs=4, num_steps=33, minibatch_size=65, processes=3)


@pytest.mark.parametrize("world", [2, 3, 4])
def test_every_process_gets_a_part_of_every_minibatch_and_process_0_the_smallest(world):
    for n in range(world, 600):  # TrainConfig allows as many processes as the smallest minibatch has samples
        sizes = part_sizes(n, world)
        assert sum(sizes) == n and min(sizes) >= 1, (n, sizes)
        assert sizes[0] <= min(sizes[1:]), (n, sizes)
    assert part_sizes(256, 2)[0] < 128  # the paper's minibatch: process 0 takes fewer than half


def test_env_states_split_and_merge_back():
    envs = SwimmerVecEnv(5, (2, 10), seed=9)
    for _ in range(30):
        envs.step(np.random.default_rng(0).uniform(-1, 1, (5, 10)).astype(np.float32))
    meta, arrays = envs.get_state()
    bounds = env_bounds(5, 2)
    assert bounds == [(0, 2), (2, 5)]
    merged_meta, merged = merge_env_states(split_env_state(meta, arrays, bounds))
    assert merged_meta == meta and merged.keys() == arrays.keys()
    for k in arrays:
        assert np.array_equal(merged[k], arrays[k]), k


@pytest.mark.slow
def test_a_helper_that_dies_stops_training_with_a_clear_error():
    cfg = TrainConfig(num_envs=2, num_steps=16, minibatch_size=16, compile=False, processes=2)
    learner = _learner(cfg)
    helpers = Helpers(helper_spec(cfg, learner), learner)
    try:
        pid = helpers._procs[0].pid
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(HelperError, match=rf"helper 1 \(pid {pid}\) died"):
            helpers.start_collect()
            helpers.finish_collect()
    finally:
        helpers.close()


def _helpers_in_an_epoch(cfg: TrainConfig) -> tuple[Helpers, int]:
    """Helpers started on a real rollout and told the first epoch of an update; its minibatch count."""
    learner = _learner(cfg)
    helpers = Helpers(helper_spec(cfg, learner), learner)
    try:
        _shared_rollout(cfg, helpers, learner)
        helpers.begin(None)
        n = cfg.num_envs * cfg.num_steps
        cuts = list(range(0, n + 1, cfg.minibatch_size))
        helpers.epoch(torch.randperm(n), cuts, torch.randn(n))
    except BaseException:
        helpers.close()
        raise
    return helpers, len(cuts) - 1


@pytest.mark.slow
def test_a_helper_that_dies_within_an_epoch_stops_training_with_a_clear_error():
    # Within an epoch process 0 waits on a semaphore, not a pipe: the helper's death must still end the wait.
    cfg = TrainConfig(num_envs=2, num_steps=64, minibatch_size=16, compile=False, processes=2)
    helpers, steps = _helpers_in_an_epoch(cfg)
    try:
        pid = helpers._procs[0].pid
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(HelperError, match=rf"helper 1 \(pid {pid}\) died"):
            for _ in range(steps):  # it may have finished a part before it was killed, not all of them
                helpers.gather(torch.zeros_like(helpers.theta))
                helpers.stepped()
    finally:
        helpers.close()


@pytest.mark.slow
def test_a_helper_waiting_within_an_epoch_leaves_when_closed():
    cfg = TrainConfig(num_envs=2, num_steps=64, minibatch_size=16, compile=False, processes=2)
    helpers, _ = _helpers_in_an_epoch(cfg)
    proc = helpers._procs[0]
    helpers.gather(torch.zeros_like(helpers.theta))  # the helper now waits for the new parameters
    helpers.close()
    assert proc.exitcode == 0  # it read "close" while waiting and left; killed, it would read -9


@pytest.mark.slow
def test_a_failing_helper_reports_its_error():
    cfg = TrainConfig(num_envs=2, num_steps=16, minibatch_size=16, compile=False, processes=2)
    learner = _learner(cfg)
    helpers = Helpers(helper_spec(cfg, learner), learner)
    try:
        with pytest.raises(HelperError, match="unknown command 'nonsense'"):
            helpers._call_all(("nonsense",))
    finally:
        helpers.close()
