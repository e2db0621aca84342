"""``trainer.reports.gym_eval``: Gymnasium's own Ant-v5 stepped through the policy node's controller. What the
controller builds from the env's MjData (as the sim node publishes it) is what the project's own env of the same
model (``mjcf:<ant.xml>``) observes on the same state, joint descriptions included."""

from __future__ import annotations

import io
import os

import gymnasium
import mujoco
import numpy as np
import pytest

from morph_core.env.bodies import parse_bodies
from morph_core.env.vec_env import BodyEnv
from morph_core.msgs.joint_state import LEGGED_GLOBAL_FEATURES
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.config import PolicyConfig
from morph_core.policy.joint_description import mujoco_descriptions
from morph_core.policy.weights import load_checkpoint
from trainer.reports.gym_eval import GymEvalConfig, GymRun, main, run

ANT_XML = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets", "ant.xml")


def policy(tmp_path, joint_features: int, global_features: int = LEGGED_GLOBAL_FEATURES) -> str:
    path = tmp_path / f"policy-{global_features}-{joint_features}.safetensors"
    GraphActorCritic(PolicyConfig(global_features=global_features, joint_features=joint_features)).save(path)
    return str(path)


@pytest.mark.parametrize("joint_features", [0, 11])
def test_the_controller_sees_what_the_projects_env_of_the_same_model_sees(tmp_path, joint_features):
    gym = GymRun(load_checkpoint(policy(tmp_path, joint_features)), "Ant-v5")
    ours = BodyEnv(parse_bodies(f"mjcf:{ANT_XML}"))
    ours.reset(seed=0)
    env = ours.env
    n = env.num_joints
    joint_pos, joint_vel, glob = np.empty(n), np.empty(n), np.empty(LEGGED_GLOBAL_FEATURES)
    data = gym.env.unwrapped.data
    gym.env.reset(seed=3)
    for _ in range(25):
        action = gym.act()
        seen = gym.answers[-1].observation
        env.data.qpos[:], env.data.qvel[:] = data.qpos, data.qvel  # the same state in the project's env
        mujoco.mj_forward(env.model, env.data)
        env.write_observation(joint_pos, joint_vel, glob)
        assert seen.names == env.tree.names and seen.parents.tolist() == env.tree.parents.tolist()
        np.testing.assert_allclose(seen.joint_pos, joint_pos, rtol=0, atol=1e-12)
        np.testing.assert_allclose(seen.joint_vel, joint_vel, rtol=0, atol=1e-12)
        np.testing.assert_allclose(seen.global_feats, glob, rtol=0, atol=1e-9)  # rebuilt from odometry: rounding
        if joint_features:
            np.testing.assert_allclose(seen.joint_desc, mujoco_descriptions(env.model), rtol=0, atol=1e-9)
        else:
            assert seen.joint_desc is None
        assert action.shape == gym.env.action_space.shape and np.abs(action).max() <= 1.0
        if gym.env.step(action)[2]:
            break
    assert len({a.observation.global_feats.tobytes() for a in gym.answers}) == len(gym.answers)  # it moved


def test_a_short_evaluation_prints_each_episode_and_the_median(tmp_path):
    out = io.StringIO()
    cfg = GymEvalConfig(policy=policy(tmp_path, 11), episodes=2, seed=10000, max_steps=20)
    episodes = run(cfg, out)
    lines = out.getvalue().splitlines()
    assert len(episodes) == 2 and all(e.length == 20 and np.isfinite(e.forward) for e in episodes)
    assert lines[1].startswith("episode 0 (seed 10000): return ") and lines[2].startswith("episode 1 (seed 10001)")
    assert lines[3].startswith("median over 2: return ") and "joint descriptions from its URDF" in lines[0]
    again = run(cfg, io.StringIO())
    assert again == episodes  # deterministic actions, seeded resets


def test_a_swimmers_policy_and_a_missing_file_are_refused_in_one_line(tmp_path, capsys):
    assert main(["--policy", policy(tmp_path, 0, global_features=4), "--episodes", "1"]) == 1
    err = capsys.readouterr().err
    assert (
        err == "gym_eval: error: the policy reads 4 global features; Ant-v5's body is a walker's (a free root): "
        "its policy reads 12\n"
    )
    assert main(["--policy", str(tmp_path / "none.safetensors")]) == 1
    assert len(capsys.readouterr().err.splitlines()) == 1
