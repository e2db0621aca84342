"""Joint state -> policy input: validation reasons, frame conversions, equality with the env's observation."""

import math

import numpy as np
import pytest
import torch

from morph_core.env.sim import SwimmerSim
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.msgs.joint_state import (
    JointStateError,
    YawUnwrapper,
    body_to_world,
    global_features,
    quaternion_from_yaw,
    validate_joint_state,
    world_to_body,
    yaw_from_quaternion,
)
from morph_core.policy.chains import ChainBatch, chain_batch


def test_valid_state_keeps_message_order():
    pos, vel = validate_joint_state(["b", "a", "c"], [3.0, 1.0, 2.0], [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(pos, [3.0, 1.0, 2.0])
    np.testing.assert_array_equal(vel, [0.1, 0.2, 0.3])


@pytest.mark.parametrize(
    "names, pos, vel, reason",
    [
        ([], [], [], "empty"),
        (["a", "b"], [0.0], [0.0, 0.0], "length mismatch"),
        (["a", "b"], [0.0, 0.0], [], "length mismatch"),
        (["a", "a"], [0.0, 0.0], [0.0, 0.0], "duplicate joint names: ['a']"),
        (["a", "b"], [0.0, math.nan], [0.0, 0.0], "NaN or inf"),
        (["a", "b"], [0.0, 0.0], [math.inf, 0.0], "NaN or inf"),
        ([f"j{i}" for i in range(65)], [0.0] * 65, [0.0] * 65, "more than the maximum of 64"),
    ],
)
def test_invalid_states_are_refused_with_a_reason(names, pos, vel, reason):
    with pytest.raises(JointStateError, match=reason.replace("[", r"\[").replace("]", r"\]")):
        validate_joint_state(names, pos, vel)


def test_64_joints_is_allowed():
    validate_joint_state([f"j{i}" for i in range(64)], [0.0] * 64, [0.0] * 64)


@pytest.mark.parametrize("yaw", [0.0, 0.3, -2.0, math.pi - 1e-9, -math.pi + 1e-9])
def test_quaternion_round_trip(yaw):
    assert yaw_from_quaternion(*quaternion_from_yaw(yaw)) == pytest.approx(yaw, abs=1e-12)


def test_body_world_round_trip():
    for yaw in (0.0, 0.7, -2.5, 4.0):
        vb = world_to_body(yaw, 0.3, -0.2)
        np.testing.assert_allclose(body_to_world(yaw, *vb), (0.3, -0.2), atol=1e-15)
    # A torso heading +y that swims forward has world velocity +y and body velocity +x.
    np.testing.assert_allclose(world_to_body(math.pi / 2, 0.0, 1.0), (1.0, 0.0), atol=1e-15)


def test_unwrapper_follows_the_hinge_across_pi():
    unwrap = YawUnwrapper()
    true_yaw = np.linspace(0.0, 3 * math.pi, 200)  # turning 1.5 times around, small steps
    got = [unwrap(math.remainder(y, math.tau)) for y in true_yaw]
    np.testing.assert_allclose(got, true_yaw, atol=1e-12)
    unwrap.reset()
    assert unwrap(0.1) == pytest.approx(0.1)


def test_global_features_refuse_bad_odometry():
    with pytest.raises(JointStateError, match="NaN"):
        global_features((0, 0, 0, 1), (math.nan, 0), 0.0)
    with pytest.raises(JointStateError, match="zero quaternion"):
        global_features((0, 0, 0, 0), (0, 0), 0.0)


def test_wire_round_trip_equals_env_observation():
    """What the sim node puts on the wire, decoded here, is the training env's graph observation."""
    sim = SwimmerSim(num_joints=5, seed=3, effort_timeout=None)
    env = MorphSwimmerEnv(num_joints=5)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    unwrap = YawUnwrapper()
    for t in range(60):
        a = rng.uniform(-1, 1, 5)
        sim.command(a, now=t)
        sim.step(now=t)
        obs, *_ = env.step(a)
        torso = sim.torso()
        quat = quaternion_from_yaw(torso.yaw)
        body = world_to_body(torso.yaw, torso.vx, torso.vy)
        glob = global_features(quat, body, torso.yaw_rate, unwrap)
        np.testing.assert_allclose(glob, obs["global"], rtol=1e-12, atol=1e-12)
        pos, vel = validate_joint_state(sim.joint_names(), sim.joint_positions, sim.joint_velocities)
        got = chain_batch(pos, vel, glob)
        want = ChainBatch.from_observations([obs])
        for a, b in zip(
            (got.joint_pos, got.joint_vel, got.global_feats, got.num_joints, got.mask),
            (want.joint_pos, want.joint_vel, want.global_feats, want.num_joints, want.mask),
            strict=True,
        ):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-7)


@pytest.mark.parametrize(
    "names, reason",
    [
        (["a", ""], "joint name 1 has 0 characters"),
        (["a", "x" * 1_000_000], "joint name 1 has 1000000 characters"),
        (["gelenk_ä", "b"], "not printable ASCII"),
        (["a\nb", "c"], "not printable ASCII"),
    ],
)
def test_names_that_are_no_joint_names_are_refused(names, reason):
    with pytest.raises(JointStateError, match=reason):
        validate_joint_state(names, [0.0] * len(names), [0.0] * len(names))


def test_names_of_the_longest_allowed_length_pass():
    from morph_core.constants import MAX_NAME_CHARS

    validate_joint_state(["a" * MAX_NAME_CHARS, "b"], [0.0, 0.0], [0.0, 0.0])


@pytest.mark.parametrize("quat", [(0, 0, 0, 2.0), (0, 0, 0.1, 0.9), (0.5, 0.5, 0.5, 0.6)])
def test_non_unit_quaternions_are_refused(quat):
    with pytest.raises(JointStateError, match="not a unit quaternion"):
        global_features(quat, (0, 0), 0.0)


def test_unit_quaternions_within_float32_rounding_pass():
    x, y, z, w = (np.float32(v) for v in quaternion_from_yaw(0.7))  # an estimator publishing float32
    assert global_features((x, y, z, w), (0, 0), 0.0)[0] == pytest.approx(0.7, abs=1e-6)
