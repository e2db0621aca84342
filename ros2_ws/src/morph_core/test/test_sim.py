"""SwimmerSim: same physics as the env, effort validation and timeout, rebuild in place, monotonic clock.

Episodes: test_sim_episodes.py."""

import math

import numpy as np
import pytest

from morph_core.env.sim import EffortError, SwimmerSim
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.env.urdf import swimmer_urdf
from morph_core.msgs.joint_state import quaternion_from_yaw, world_to_body


def _global(sim: SwimmerSim) -> list[float]:
    t = sim.torso()
    return [t.yaw, t.yaw_rate, t.vx, t.vy]


def test_steps_like_the_env_with_the_same_seed():
    sim = SwimmerSim(num_joints=4, seed=7, effort_timeout=None)
    env = MorphSwimmerEnv(num_joints=4)
    obs, _ = env.reset(seed=7)
    np.testing.assert_array_equal(_global(sim), obs["global"])
    rng = np.random.default_rng(1)
    for t in range(50):
        a = rng.uniform(-1, 1, 4)
        sim.command(a, now=t)
        sim.step(now=t)
        obs, *_ = env.step(a)
        np.testing.assert_array_equal(sim.joint_positions, obs["joint_pos"])
        np.testing.assert_array_equal(sim.joint_velocities, obs["joint_vel"])
        np.testing.assert_array_equal(_global(sim), obs["global"])
        np.testing.assert_array_equal(sim.applied, a)
    assert sim.time == pytest.approx(50 * 0.04)


@pytest.mark.parametrize("bad, reason", [([0.0] * 3, "expected 4 efforts, got 3"), ([0, 0, math.nan, 0], "NaN")])
def test_bad_commands_are_refused_counted_and_the_old_one_stays(bad, reason):
    sim = SwimmerSim(num_joints=4, effort_timeout=None)
    sim.command([0.5, 0, 0, 0], now=0.0)
    with pytest.raises(EffortError, match=reason):
        sim.command(bad, now=0.1)
    assert sim.rejected == 1
    sim.step(now=0.2)
    np.testing.assert_array_equal(sim.applied, [0.5, 0, 0, 0])


def test_efforts_are_clipped_to_the_ctrl_range():
    sim = SwimmerSim(num_joints=2)
    np.testing.assert_array_equal(sim.command([3.0, -7.0], now=0.0), [1.0, -1.0])


def test_effort_timeout_zeroes_the_efforts():
    sim = SwimmerSim(num_joints=3, effort_timeout=0.25)
    sim.step(now=0.0)
    assert sim.timed_out  # nothing ever commanded
    sim.command([1.0, 1.0, 1.0], now=1.0)
    sim.step(now=1.2)
    assert not sim.timed_out and sim.applied.tolist() == [1.0, 1.0, 1.0]
    sim.step(now=1.3)
    assert sim.timed_out and sim.applied.tolist() == [0.0, 0.0, 0.0]


def test_rebuild_changes_length_resets_efforts_and_the_clock_counts_on():
    sim = SwimmerSim(num_joints=6, effort_timeout=None)
    sim.command([1.0] * 6, now=0)
    for _ in range(10):
        sim.step(now=0)
    t = sim.time
    sim.rebuild(20)
    assert sim.num_joints == 20
    assert len(sim.joint_names()) == len(sim.joint_positions) == len(sim.joint_velocities) == 20
    assert sim.time == pytest.approx(t + sim.dt)  # the new chain's first state is the next period's
    assert abs(sim.torso().x) < 0.2  # fresh chain at the origin (reset noise only)
    sim.step(now=0)
    np.testing.assert_array_equal(sim.applied, np.zeros(20))  # the 6-joint command does not carry over
    assert sim.time == pytest.approx(t + 2 * sim.dt)
    with pytest.raises(ValueError, match="1..64"):
        sim.rebuild(0)
    assert sim.num_joints == 20


def test_joint_names_with_prefix():
    assert SwimmerSim(num_joints=2).joint_names("left_") == ["left_motor1_rot", "left_motor2_rot"]


def test_torso_moves_under_a_travelling_wave():
    sim = SwimmerSim(num_joints=6, seed=0, effort_timeout=None)
    for k in range(250):
        t = k * sim.dt
        sim.command(np.sin(2 * np.pi * (0.5 * t - np.arange(6) / 6)), now=t)
        sim.step(now=t)
    assert math.hypot(sim.torso().x, sim.torso().y) > 0.1


def test_odometry_is_the_torso_in_the_plane():
    """What the sim node puts in odom for a swimmer: x, y, z = 0; yaw about z; the world-frame velocity turned
    into the torso frame; the yaw rate about z."""
    sim = SwimmerSim(num_joints=4, seed=2, effort_timeout=None)
    for k in range(40):
        sim.command(np.sin(0.3 * k + np.arange(4)), now=k)
        sim.step(now=k)
    t, odom = sim.torso(), sim.odometry()
    assert odom.frame == "torso"
    assert odom.position == (t.x, t.y, 0.0)
    assert odom.orientation == quaternion_from_yaw(t.yaw)
    assert odom.linear == (*world_to_body(t.yaw, t.vx, t.vy), 0.0)
    assert odom.angular == (0.0, 0.0, t.yaw_rate)
    assert abs(t.yaw) > 1e-3 and abs(t.vx) > 1e-3  # a state that turned and moved


def test_a_trees_joints_are_its_mjcf_names_in_tree_order_and_its_urdf_the_swimmers():
    sim = SwimmerSim(bodies="y:1x2", seed=0)
    assert sim.tree.parents.tolist() == [-1, 0, 1, 0, 3]
    assert sim.joint_names("p/") == [f"p/motor{k}_rot" for k in range(1, 6)]
    assert sim.urdf("p/") == swimmer_urdf(sim.tree, "p/")
    np.testing.assert_array_equal(sim.joint_positions, sim._env.data.qpos[3:])
    assert SwimmerSim(num_joints=3).urdf() == swimmer_urdf(3)
