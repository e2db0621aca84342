"""The sim serves centipedes (``SwimmerSim(bodies="centipede:...")``), and the 12 global features a controller
builds from its odometry (``msgs.joint_state.legged_global_features``) are the env's own observation."""

from __future__ import annotations

import numpy as np
import pytest

from morph_core.env.centipede import MorphCentipedeEnv
from morph_core.env.sim import SwimmerSim
from morph_core.env.urdf import robot_urdf
from morph_core.msgs.episode_start import EpisodeCause
from morph_core.msgs.joint_state import JointStateError, legged_global_features
from morph_core.policy.tree import read_urdf


def _globals_from_odometry(sim: SwimmerSim) -> np.ndarray:
    odom = sim.odometry()
    return legged_global_features(odom.orientation, odom.position, odom.linear, odom.angular)


def test_the_sim_replays_the_centipede_env_and_its_odometry_gives_the_envs_globals():
    sim = SwimmerSim(bodies="centipede:2-3", seed=4, effort_timeout=None, episode_steps=30)
    env = MorphCentipedeEnv(leg_pairs=(2, 3))
    obs, info = env.reset(seed=4)
    assert sim.num_joints == 4 * info["leg_pairs"] and sim.tree == env.tree and sim.dt == env.dt == 0.05
    rng = np.random.default_rng(0)
    tilted = steps = falls = 0
    terminated = False
    for _ in range(60):
        assert np.array_equal(sim.joint_positions, obs["joint_pos"])
        np.testing.assert_allclose(_globals_from_odometry(sim), obs["global"], rtol=0, atol=1e-12)
        tilted += abs(obs["global"][8] + 1) > 1e-3  # gravity not straight down: the test saw a tilted root
        # The sim's episode ends where the env's does: at its terminated (a fall), or after episode_steps.
        assert sim.episode_over == (terminated or steps == 30) and sim.fell == terminated
        if sim.episode_over:
            sim.advance(0.0)
            assert sim.episode_cause is (EpisodeCause.FELL if terminated else EpisodeCause.STEPS)
            obs, _ = env.reset()
            steps, terminated = 0, False
            continue
        a = rng.uniform(-1, 1, sim.num_joints)
        sim.command(a, 0.0)
        sim.advance(0.0)
        obs, reward, terminated, _, _ = env.step(a)
        assert sim.robot.reward == reward
        steps += 1
        falls += terminated
    assert sim.episode >= 2 and falls >= 1 and tilted > 10
    odom = sim.odometry()
    assert odom.frame == "torso_0" and len(odom.position) == 3 and odom.position[2] > 0


def test_its_urdf_is_the_compiled_models_tree():
    sim = SwimmerSim(bodies="centipede:3", seed=0)
    assert sim.urdf() == robot_urdf(sim.robot.model)
    tree = read_urdf(sim.urdf()).tree
    assert tree.names == sim.tree.names and tree.root_link == "torso_0" and sim.bodies is not None


def test_mixed_families_and_bad_odometry_are_refused():
    with pytest.raises(ValueError, match="mixes swimmers and walkers"):
        SwimmerSim(bodies="2,centipede:2")
    with pytest.raises(JointStateError, match="unit quaternion"):
        legged_global_features((0, 0, 0, 2), (0, 0, 0.5), (0, 0, 0), (0, 0, 0))
    with pytest.raises(JointStateError, match="NaN"):
        legged_global_features((0, 0, 0, 1), (0, 0, float("nan")), (0, 0, 0), (0, 0, 0))
