"""Rollout workers on Ray actors (``trainer.sim.ray_rollouts``), on a real local Ray: a run of two workers
resumes bit for bit from its checkpoint, and one whose worker is killed with SIGKILL goes on, the restart
logged with what went back."""

import csv
import logging
import os
import re
import signal
import time

import numpy as np
import pytest
import torch

ray = pytest.importorskip("ray")

from morph_core.algo.checkpoint import load_training_state  # noqa: E402
from morph_core.algo.rollout_workers import (  # noqa: E402
    RolloutWorker,
    RolloutWorkerError,  # noqa: E402
    worker_seed,
)
from morph_core.algo.run_dir import RunDir  # noqa: E402
from morph_core.algo.small_runs import small  # noqa: E402
from morph_core.algo.train import TrainConfig, rollout_spec, train  # noqa: E402
from morph_core.policy.actor_critic import GraphActorCritic  # noqa: E402
from trainer.cli import train as train_cli  # noqa: E402
from trainer.sim.ray_rollouts import RayRolloutPool, ray_rollout_pool  # noqa: E402

SMALL = small(num_envs=4, checkpoint_interval=256, rollout_workers=2)
TIMES = ("wall_time", "sps", "rollout_s", "update_s")


@pytest.fixture(scope="module")
def local_ray():
    """One small local Ray for the module (2 CPUs: one per worker; the learner is this process)."""
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=200 * 1024**2, log_to_driver=False)
    yield
    ray.shutdown()


def _rows(run_dir):
    with RunDir(run_dir).progress.open() as f:
        return [{k: v for k, v in row.items() if k not in TIMES} for row in csv.DictReader(f)]


@pytest.mark.slow
def test_a_two_worker_run_resumes_exactly_as_an_uninterrupted_run(local_ray, tmp_path):
    pools = []

    def make(spec, workers):
        pools.append(RayRolloutPool(spec, workers))
        return pools[-1]

    straight = train(TrainConfig(total_timesteps=768, seed=5, **SMALL), tmp_path / "a", rollout_pool=make)
    part = train(TrainConfig(total_timesteps=256, seed=5, **SMALL), tmp_path / "b", rollout_pool=make)
    train(TrainConfig(total_timesteps=768, seed=5, **SMALL), part, resume=True, rollout_pool=make)
    assert len(pools) == 3 and not any(pool.actors for pool in pools)  # each closed its actors
    assert pools[0].bounds == [(0, 2), (2, 4)]
    (wa, ma), (wb, mb) = (load_training_state(RunDir(run).state) for run in (straight, part))
    assert ma["counters"]["global_step"] == mb["counters"]["global_step"] == 768
    assert {"rng.worker0", "rng.worker1"} <= wa.keys() and len(ma["sections"]["swimmers"]["envs"]) == 4
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k  # weights, Adam, every worker's generator and swimmers
    assert len(_rows(straight)) == 3 and _rows(straight) == _rows(part)
    # Each worker draws its own noise, from worker_seed(seed, rank): not the run's generator, not each other's.
    g = torch.Generator().manual_seed(worker_seed(5, 1))
    fresh = train(TrainConfig(total_timesteps=256, seed=5, **SMALL), tmp_path / "c", rollout_pool=make)
    w1, _ = load_training_state(RunDir(fresh).state)
    for _ in range(64):
        torch.randn((2, 10), generator=g)  # what worker 1 drew over its 64 steps of 2 swimmers
    assert torch.equal(w1["rng.worker1"], g.get_state())
    assert not torch.equal(w1["rng.worker0"], w1["rng.worker1"])


@pytest.mark.slow
def test_a_worker_killed_mid_run_is_restarted_and_the_run_goes_on(local_ray, tmp_path, caplog):
    pools, killed = [], []

    def make(spec, workers):
        pools.append(RayRolloutPool(spec, workers))
        return pools[-1]

    def kill_worker_1(row, saved):
        if row["iteration"] == 1:  # a checkpoint was just taken, and the workers' next rollout started
            assert saved
            killed.append(pools[0].pids()[1])
            os.kill(killed[0], signal.SIGKILL)

    caplog.set_level(logging.WARNING, logger="trainer.sim.ray_rollouts")
    run = train(TrainConfig(total_timesteps=768, seed=5, **SMALL), tmp_path / "k", on_row=kill_worker_1,
                rollout_pool=make)  # fmt: skip
    rows = _rows(run)
    assert [int(r["global_step"]) for r in rows] == [256, 512, 768]
    pool = pools[0]
    assert pool.restarts == 1
    # What went back: worker 1's swimmers 2..3 to the checkpoint at step 256. The rollout of 64 steps it had
    # started was either in flight (then collected again) or finished before the kill (then undone, 64 steps
    # x 2 swimmers, found at the next call: the next checkpoint's get_state).
    (message,) = [r.getMessage() for r in caplog.records if "died" in r.getMessage()]
    during = re.match(r"rollout worker 1 \(swimmers 2\.\.3\) died during (\w+); Ray restarted it", message)
    lost = re.search(r"lost for them are the (\d) rollouts of 64 steps since then \((\d+) env-steps", message)
    assert during and lost, message
    assert (during[1], lost[1], lost[2]) in {("collect_columns", "0", "0"), ("get_state", "1", "128")}, message
    assert ("collected again" in message) == (during[1] == "collect_columns")
    assert pool.actors == [] and killed[0] > 0  # closed; the killed process was a worker's
    _, meta = load_training_state(RunDir(run).state)
    assert meta["counters"]["global_step"] == 768


@pytest.mark.slow
def test_the_cli_runs_on_ray_workers_and_refuses_bad_combinations(local_ray, tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["--out", str(out), "--num-envs", "4", "--num-steps", "64", "--minibatch-size", "64",
            "--update-epochs", "1", "--total-timesteps", "256", "--compile", "false", "--progress-bar", "false",
            "--tensorboard", "false"]  # fmt: skip
    assert train_cli.main([*args, "--rollout-workers", "2"]) == 0
    assert len(_rows(out)) == 1
    with pytest.raises(SystemExit) as exit_info:
        train_cli.main([*args[2:], "--out", str(tmp_path / "x"), "--rollout-workers", "2", "--processes", "2"])
    assert exit_info.value.code == 2
    assert "rollout_workers > 1 and processes > 1 both share the swimmers out: choose one" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        train_cli.main([*args[2:], "--out", str(tmp_path / "y"), "--ray-address", "auto"])
    assert "--ray-address: only with --rollout-workers > 1" in capsys.readouterr().err


@pytest.mark.slow
def test_the_pool_factory_uses_a_running_ray_and_leaves_it_running(local_ray):
    cfg = TrainConfig(**SMALL)
    pool = ray_rollout_pool()(rollout_spec(cfg), 2)
    try:
        assert len(set(pool.pids())) == 2 and os.getpid() not in pool.pids()
    finally:
        pool.close()
    assert ray.is_initialized()


@pytest.mark.slow
def test_more_workers_than_the_cluster_has_cpus_is_refused_not_a_hang(local_ray):
    """Each worker actor takes a CPU: 3 workers on the 2-CPU Ray would wait forever for the third."""
    cfg = TrainConfig(**{**SMALL, "rollout_workers": 3})
    with pytest.raises(RolloutWorkerError, match="3 rollout workers need 3 CPUs; the Ray cluster has 2"):
        ray_rollout_pool()(rollout_spec(cfg), 3)
    assert ray.is_initialized()  # a Ray it did not start is left running


@pytest.mark.slow
def test_a_worker_killed_while_collecting_collects_again_from_its_restored_state(local_ray, caplog):
    # 600 steps take a worker ~0.3 s or more: the kill lands while it collects.
    cfg = TrainConfig(**{**SMALL, "num_steps": 600, "minibatch_size": 64})
    spec = rollout_spec(cfg)
    pool = RayRolloutPool(spec, 2)
    try:
        theta = torch.nn.utils.parameters_to_vector(GraphActorCritic(cfg.policy).parameters()).detach()
        pid = pool.pids()[0]
        caplog.set_level(logging.WARNING, logger="trainer.sim.ray_rollouts")
        pool.start(theta)
        time.sleep(0.1)
        os.kill(pid, signal.SIGKILL)
        pool.finish()
        assert pool.restarts == 1 and pool.pids()[0] != pid
        (message,) = [r.getMessage() for r in caplog.records if "died" in r.getMessage()]
        assert "died during collect_columns" in message and "the rollout in flight, collected again" in message
        # Restored to its starting state and given the same parameters, it collected what it would have.
        alone = RolloutWorker(spec.worker(0, 2), GraphActorCritic(cfg.policy))
        torch.nn.utils.vector_to_parameters(theta, alone.policy.parameters())
        alone.collect()
        mine = pool.rollout.columns(0, 2)
        for name in ("actions", "rewards", "values", "joint_pos", "last_value"):
            assert np.array_equal(getattr(mine, name), getattr(alone.rollout, name)), name
    finally:
        pool.close()


@pytest.mark.slow
def test_centipedes_on_two_ray_workers_train_a_twelve_feature_policy(local_ray, tmp_path):
    from morph_core.policy.weights import load_checkpoint

    legged = {**SMALL, "bodies": "centipede:2-3"}
    run = train(TrainConfig(total_timesteps=512, seed=6, **legged), tmp_path / "a", rollout_pool=RayRolloutPool)
    assert load_checkpoint(RunDir(run).checkpoints / "policy_00000512.safetensors").config.global_features == 12
    weights, meta = load_training_state(RunDir(run).state)
    assert {"rng.worker0", "rng.worker1"} <= weights.keys() and meta["counters"]["global_step"] == 512
    envs = meta["sections"]["swimmers"]["envs"]  # each worker's centipedes, saved for a resume
    assert len(envs) == 4 and all(e["leg_pairs"] in (2, 3) for e in envs)
    assert {"return_d8", "return_d12"} <= _rows(run)[0].keys()
