"""A policy that reads joint descriptions (``PolicyConfig.joint_features``): torch, PyG, NumPy and ONNX answer alike,
every container carries the descriptions from the env to the update, training and evaluation run with them; and
with the default 0 every shipped checkpoint answers bit for bit as main's code does (side by side, one process)."""

from __future__ import annotations

import importlib.util
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from morph_core.algo.batch import RolloutBatch
from morph_core.algo.evaluate import evaluate_policy
from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig, train
from morph_core.env.legged_model import LeggedBody
from morph_core.env.vec_env import SwimmerVecEnv
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch
from morph_core.policy.config import PolicyConfig
from morph_core.policy.joint_description import NUM_DESCRIPTION_FEATURES, mujoco_descriptions
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import load_checkpoint

D = NUM_DESCRIPTION_FEATURES
ROOT = Path(__file__).resolve().parents[4]


def _batch(rng, b=6, j=10, g=12):
    n = rng.integers(1, j + 1, b)
    n[0] = j
    mask = np.arange(j) < n[:, None]
    pos = (rng.normal(0, 1, (b, j)) * mask).astype(np.float32)
    vel = (rng.normal(0, 2, (b, j)) * mask).astype(np.float32)
    glob = rng.normal(0, 1, (b, g)).astype(np.float32)
    parents = np.full((b, j), -1, np.int64)
    for row in range(b):
        for k in range(n[row]):
            parents[row, k] = rng.integers(-1, k)
    desc = (rng.uniform(-1, 1, (b, j, D)) * mask[..., None]).astype(np.float32)
    return pos, vel, glob, n, parents, desc


def test_the_config_takes_no_descriptions_or_the_full_vector():
    assert PolicyConfig().joint_features == 0 and PolicyConfig().edge_features == 2
    assert PolicyConfig(joint_features=D).edge_features == 2 + D
    assert PolicyConfig.from_dict({"conv1_channels": 24}).joint_features == 0  # a checkpoint from before
    for bad in (1, -1, D + 1, True, 2.0):
        with pytest.raises(ValueError, match="joint_features"):
            PolicyConfig(joint_features=bad)


@pytest.mark.parametrize("trees", [False, True])
def test_torch_pyg_and_numpy_answer_alike_with_descriptions(trees):
    torch.manual_seed(0)
    config = PolicyConfig(joint_features=D, global_features=12)
    policy = GraphActorCritic(config)
    pyg = GraphActorCritic(config, backend="pyg")
    pyg.load_state_dict(policy.state_dict())
    pos, vel, glob, n, parents, desc = _batch(np.random.default_rng(1))
    parents = parents if trees else None
    batch = ChainBatch.from_padded(pos, vel, glob, n, parents=parents, joint_desc=desc)
    with torch.no_grad():
        mean, _, value = policy(batch)
        np.testing.assert_allclose(pyg(batch)[0].numpy(), mean.numpy(), atol=1e-5)
    actor = NumpyPolicy(policy)
    m, v = actor.forward(pos, vel, glob, n, parents, desc)
    np.testing.assert_allclose(m, mean.numpy(), atol=1e-5)
    np.testing.assert_allclose(v, value.numpy(), atol=1e-5)
    k = int(n[0])
    one = actor.mean(pos[0, :k], vel[0, :k], glob[0], None if parents is None else parents[0, :k], desc[0, :k])
    np.testing.assert_allclose(one, mean[0, :k].numpy(), atol=1e-5)
    # the descriptions matter, and a policy without them refuses them (and the other way round)
    assert np.abs(actor.forward(pos, vel, glob, n, parents, desc * 0)[0] - m).max() > 1e-4
    with pytest.raises(ValueError, match="pass joint_desc"):
        actor.forward(pos, vel, glob, n, parents)
    with pytest.raises(ValueError, match="joint description"):
        policy(ChainBatch.from_padded(pos, vel, glob, n, parents=parents))
    with pytest.raises(ValueError, match="no joint descriptions"):
        NumpyPolicy(GraphActorCritic(PolicyConfig(global_features=12))).forward(pos, vel, glob, n, parents, desc)


@pytest.mark.slow
@pytest.mark.parametrize("tree", [False, True])
def test_onnx_takes_the_descriptions_and_answers_as_torch(tree):
    pytest.importorskip("onnxruntime")
    from morph_core.policy.onnx_export import TOLERANCE, check_against_policy, export_model, input_names

    torch.manual_seed(2)
    policy = GraphActorCritic(PolicyConfig(joint_features=D)).eval()  # the swimmer's 4 globals: the check's
    model = export_model(policy, with_value=True, tree=tree)
    assert [i.name for i in model.graph.input] == list(input_names(tree, D)) and input_names(tree, D)[
        -1
    ] == "joint_desc"
    assert check_against_policy(model.SerializeToString(), policy, lengths=(1, 3, 10), tree=tree) <= TOLERANCE


def test_a_checkpoint_with_descriptions_loads_as_it_was_saved(tmp_path):
    policy = GraphActorCritic(PolicyConfig(joint_features=D, global_features=12))
    policy.save(tmp_path / "p.safetensors")
    weights = load_checkpoint(tmp_path / "p.safetensors")
    assert weights.config.joint_features == D
    assert weights.arrays["features.conv1.fwd.nn.weight"].shape[1] == 2 + D
    pos, vel, glob, n, parents, desc = _batch(np.random.default_rng(3))
    np.testing.assert_array_equal(
        NumpyPolicy(weights).forward(pos, vel, glob, n, parents, desc)[0],
        NumpyPolicy(policy).forward(pos, vel, glob, n, parents, desc)[0],
    )


def test_the_vector_env_writes_each_bodys_descriptions_and_the_rollout_batch_carries_them():
    envs = SwimmerVecEnv(4, "legged:4-6x2-3,centipede:2,2-3", seed=5, max_episode_steps=20, joint_descriptions=True)
    assert SwimmerVecEnv(2, "2-3", seed=0).observations().joint_desc is None  # not asked: not computed
    rng = np.random.default_rng(0)
    finals = 0
    for _ in range(80):
        obs = envs.observations()
        for i, env in enumerate(envs.envs):
            k = env.num_joints
            np.testing.assert_allclose(obs.joint_desc[i, :k], mujoco_descriptions(env.model), atol=1e-6)
            assert (obs.joint_desc[i, k:] == 0).all()
        step = envs.step(rng.uniform(-1, 1, (4, envs.max_joints)).astype(np.float32))
        for final in step.final_obs.values():
            assert final["joint_desc"].shape == (len(final["joint_pos"]), D)
            finals += 1
    assert finals > 0
    n = torch.from_numpy(obs.num_joints)
    z = torch.zeros(4)
    t = torch.from_numpy
    batch = RolloutBatch(n, t(obs.joint_pos), t(obs.joint_vel), t(obs.global_feats), torch.zeros(4, envs.max_joints),
                         z, z, z, z, parents=t(obs.parents), joint_desc=t(obs.joint_desc))  # fmt: skip
    chains, _ = batch.minibatch(torch.tensor([2, 0]))
    width = chains.max_joints
    np.testing.assert_array_equal(chains.joint_desc.numpy(), obs.joint_desc[[2, 0], :width])
    bad = obs.joint_desc.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="joint_desc"):
        RolloutBatch(n, batch.joint_pos, batch.joint_vel, batch.global_feats, batch.actions, z, z, z, z,
                     joint_desc=torch.from_numpy(bad))  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("processes", [1, 2])
def test_a_run_with_descriptions_trains_resumes_bit_for_bit_and_evaluates(tmp_path, processes):
    cfg = dict(num_envs=4, num_steps=32, minibatch_size=64, update_epochs=1, checkpoint_interval=128,
               tensorboard=False, progress_bar=False, compile=False, bodies="legged:4x2,centipede:2", seed=3,
               processes=processes, policy=PolicyConfig(joint_features=D))  # fmt: skip
    straight = train(TrainConfig(total_timesteps=384, **cfg), tmp_path / "a")
    part = train(TrainConfig(total_timesteps=128, **cfg), tmp_path / "b")
    train(TrainConfig(total_timesteps=384, **cfg), part, resume=True)
    a, b = (load_checkpoint(sorted(RunDir(d).checkpoints.glob("*.safetensors"))[-1]) for d in (straight, part))
    assert a.config.joint_features == D and a.config.global_features == 12
    for key in a.arrays:
        np.testing.assert_array_equal(a.arrays[key], b.arrays[key])
    results = evaluate_policy(a, [LeggedBody(6, 3, "round", 1001), 3], episodes=2, max_steps=30)
    assert all(np.isfinite(r).all() for r in results.values())


def _bench(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


BEFORE_DESCRIPTIONS = "770332d"
"""the last commit before joint descriptions existed: its code is what the shipped checkpoints answered with"""


def test_shipped_checkpoints_answer_bit_for_bit_as_before_descriptions():
    """Side by side in this process: the morph_core of the commit before descriptions (``git archive``) and this
    tree's, the same questions: exact, both computed here."""
    known = subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", f"{BEFORE_DESCRIPTIONS}^{{commit}}"])
    if known.returncode != 0:
        pytest.skip(f"this checkout has no commit {BEFORE_DESCRIPTIONS} (a shallow clone)")
    assert _bench("check_checkpoints_unchanged").compare(BEFORE_DESCRIPTIONS) == []
