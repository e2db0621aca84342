"""Sim node and policy node at topic level: real processes, real Fast DDS, matched endpoints, no sleeps.

Runs inside a private network namespace (``scripts/test.sh``).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray
from trajectory_msgs.msg import JointTrajectory

from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.msgs.policy_info import unpack_policy_info
from morph_core.msgs.stamps import to_ns
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_policy_node.policy_node import SHIPPED_MODEL

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0  # seconds for processes to start and match (torch import on a loaded 2-core machine)
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _stamp(msg) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def _state(names, pos, vel, sec=0):
    msg = JointState(name=list(names), position=[float(x) for x in pos], velocity=[float(x) for x in vel])
    msg.header.stamp.sec = sec
    return msg


# -- sim + policy --------------------------------------------------------------------------
@pytest.mark.timeout(120)
@pytest.mark.parametrize("joints", [2, 7, 20])
def test_efforts_have_one_value_per_joint(probe, launch, untrained_checkpoint, joints):
    states = probe.collect(JointState, "joint_states")
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    launch("swimmer_sim_node", num_joints=joints)
    launch("morph_policy_node", checkpoint=str(untrained_checkpoint))
    probe.spin_until(lambda: len(efforts) >= 10 and len(states) >= 3, STARTUP, "joint states and 10 effort commands")
    assert {len(s.name) for s in states} == {joints}
    assert {len(e.data) for e in efforts} == {joints}
    values = np.array([e.data for e in efforts])
    assert np.isfinite(values).all() and np.abs(values).max() <= 1.0
    assert np.abs(values).max() > 0  # a real policy output, not the silence fallback
    # The sim reports the efforts it applied: the policy's, once they arrive.
    probe.spin_until(
        lambda: any(tuple(e.data) in {tuple(s.effort) for s in states} for e in efforts), STARTUP,
        "a state reporting one of the policy's efforts as applied (it comes a step after the answer)",
    )  # fmt: skip


@pytest.mark.timeout(120)
def test_nodes_talk_over_udp_without_shared_memory(probe, launch, untrained_checkpoint):
    # The shipped Fast DDS profile turns shared memory off: a peer SIGKILLed mid-write could leave its port
    # so that the next publish to it blocks for seconds (docs/design.md). With it on, every participant
    # creates its segments in /dev/shm as it starts.
    before = set(Path("/dev/shm").glob("fastrtps_*"))
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    launch("swimmer_sim_node", num_joints=3)
    launch("morph_policy_node", checkpoint=str(untrained_checkpoint))
    probe.spin_until(lambda: len(efforts) >= 10, STARTUP, "10 effort commands")
    assert set(Path("/dev/shm").glob("fastrtps_*")) - before == set()


@pytest.mark.timeout(120)
def test_num_joints_changed_at_runtime(probe, launch, untrained_checkpoint, namespace):
    states = probe.collect(JointState, "joint_states")
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    launch("swimmer_sim_node", num_joints=6)
    launch("morph_policy_node", checkpoint=str(untrained_checkpoint))
    probe.spin_until(lambda: any(len(e.data) == 6 for e in efforts), STARTUP, "6 efforts")

    result = probe.set_parameter(f"{namespace}/swimmer_sim", "num_joints", 11)
    assert result.successful, result.reason
    n_before = len(states)
    probe.spin_until(
        lambda: any(len(e.data) == 11 for e in efforts) and any(len(s.name) == 11 for s in states[n_before:]),
        20.0,
        "11 joint states and 11 efforts after the rebuild",
    )
    # Once the chain has 11 joints, every later joint state has 11.
    lengths = [len(s.name) for s in states[n_before:]]
    first = lengths.index(11)
    assert set(lengths[first:]) == {11}

    refused = probe.set_parameter(f"{namespace}/swimmer_sim", "num_joints", 0)
    assert not refused.successful and "num_joints" in refused.reason
    refused = probe.set_parameter(f"{namespace}/swimmer_sim", "real_time_factor", -1.0)
    assert not refused.successful and refused.reason
    n = len(states)
    probe.spin_until(lambda: len(states) > n + 5, 20.0, "joint states after a refused change")
    assert {len(s.name) for s in states[n:]} == {11}


@pytest.mark.timeout(120)
def test_types_and_ranges_are_refused_from_the_parameter_tables(probe, launch, untrained_checkpoint, namespace):
    """The nodes' callbacks no longer check types and ranges: the descriptors declared from each node's table do
    (rclpy, before the callback). Each value outside them is refused by name; a value inside is taken."""
    launch("swimmer_sim_node", num_joints=3)
    launch("morph_policy_node", checkpoint=str(untrained_checkpoint))
    sim, policy = f"{namespace}/swimmer_sim", f"{namespace}/morph_policy"
    refused = [(sim, "effort_timeout", value) for value in (0.0, -1.0, math.nan, math.inf)]
    refused += [(sim, "real_time_factor", value) for value in (math.nan, 1e9)] + [(sim, "num_joints", 65)]
    refused += [(sim, "episode_steps", 2**31), (sim, "num_joints", 6.0), (sim, "lockstep", "yes")]
    refused += [(policy, "input_timeout", value) for value in (0.0, math.nan, -math.inf)]
    refused += [(policy, "checkpoint", 3), (policy, "deterministic", 1)]
    for node, name, value in refused:
        result = probe.set_parameter(node, name, value)
        assert not result.successful and (name in result.reason or "type" in result.reason), (name, value, result)
    assert probe.set_parameter(sim, "effort_timeout", 0.5).successful
    assert probe.set_parameter(policy, "input_timeout", 0.001).successful


@pytest.mark.timeout(120)
def test_joint_prefix_checked_and_applied_at_runtime(probe, launch, namespace):
    states = probe.collect(JointState, "joint_states")
    launch("swimmer_sim_node", num_joints=3)
    probe.spin_until(lambda: states, STARTUP, "joint states")
    node = f"{namespace}/swimmer_sim"
    for bad in ("x" * 300, "caf\u00e9/", "a\tb/"):  # too long, not ASCII, a control character
        result = probe.set_parameter(node, "joint_prefix", bad)
        assert not result.successful and "joint_prefix" in result.reason, (bad, result.reason)
    wrong_type = probe.set_parameter(node, "joint_prefix", 7)
    assert not wrong_type.successful
    n = len(states)
    probe.spin_until(lambda: len(states) > n + 3, 20.0, "joint states after the refusals")
    assert all(not name.startswith(("x", "caf", "a\t")) for s in states[n:] for name in s.name)
    assert probe.set_parameter(node, "joint_prefix", "left/").successful
    probe.spin_until(lambda: any(s.name[0].startswith("left/") for s in states[n:]), 20.0, "prefixed names")
    renamed = next(s for s in states[n:] if s.name[0].startswith("left/"))
    assert len(renamed.name) == 3 and all(name.startswith("left/") for name in renamed.name)


def _rollout(policy: GraphActorCritic, joints: int, seed: int, steps: int) -> list[tuple[float, float]]:
    """The same closed loop in-process, in the training env: torso (x, y) after each control step, index 0 = reset.

    Actions come from the node's own deterministic path (the NumPy batch-1 forward, equal to the
    torch policy to ~1e-6): over hundreds of steps the swimmer's dynamics would amplify even
    that difference."""
    mean_of = NumpyPolicy(policy)
    env = MorphSwimmerEnv(num_joints=joints)
    obs, _ = env.reset(seed=seed)
    xy = [(env.data.qpos[0], env.data.qpos[1])]
    for _ in range(steps):
        action = mean_of.mean(obs["joint_pos"], obs["joint_vel"], obs["global"])
        obs, *_ = env.step(np.clip(action, -1, 1).astype(np.float64))
        xy.append((env.data.qpos[0], env.data.qpos[1]))
    return xy


def _run_lockstep(probe, launch, checkpoint, joints, seed, sim_seconds):
    """Sim in lockstep + policy; returns {step: (x, y)} from odom up to ``sim_seconds``."""
    odoms = probe.collect(Odometry, "odom")
    # Listening to joint_states too makes the sim publish (and re-send) its reset state before the
    # policy is up, so the probe has surely matched the sim when the loop starts.
    probe.collect(JointState, "joint_states")
    launch(
        "swimmer_sim_node",
        num_joints=joints,
        seed=seed,
        lockstep=True,
        real_time_factor=0.0,
        effort_timeout=2.0,  # no re-publishing while a loaded machine is slow to answer
    )
    probe.spin_until(lambda: odoms, STARTUP, "the reset state")
    launch("morph_policy_node", checkpoint=str(checkpoint))
    probe.spin_until(
        lambda: odoms and _stamp(odoms[-1]) >= sim_seconds, STARTUP + 4 * sim_seconds, f"{sim_seconds} s of sim"
    )
    return {round(_stamp(o) / 0.04): (o.pose.pose.position.x, o.pose.pose.position.y) for o in odoms}


@pytest.mark.timeout(120)
def test_lockstep_sim_never_steps_on_a_controllers_silence_zeros(probe, launch):
    """A policy node whose input went quiet sends zeros labelled 'silence'; a slow (not dead) lockstep loop
    must not take them as the answer, or the run stops being the in-process one."""
    from std_msgs.msg import MultiArrayDimension

    from morph_core.msgs.stamps import SILENCE_TAG, answer_tag

    states = probe.collect(JointState, "joint_states")
    pub = probe.node.create_publisher(Float64MultiArray, "effort_commands", DEEP)
    launch("swimmer_sim_node", num_joints=2, lockstep=True, real_time_factor=0.0, effort_timeout=30.0)
    probe.spin_until(lambda: states and pub.get_subscription_count() > 0, STARTUP, "the first state")
    first = states[0].header.stamp

    def efforts(values, label):
        msg = Float64MultiArray(data=values)
        msg.layout.dim = [MultiArrayDimension(label=label, size=2, stride=2)]
        return msg

    for _ in range(3):
        pub.publish(efforts([0.0, 0.0], SILENCE_TAG))
    pub.publish(efforts([0.5, -0.5], answer_tag(first.sec, first.nanosec)))
    probe.spin_until(lambda: any(_stamp(s) > _stamp(states[0]) for s in states), 20.0, "the next state")
    nxt = next(s for s in states if _stamp(s) > _stamp(states[0]))
    assert _stamp(nxt) == pytest.approx(_stamp(states[0]) + 0.04)
    assert list(nxt.effort) == [0.5, -0.5]  # the tagged answer, not the zeros before it


@pytest.mark.timeout(180)
def test_lockstep_loop_is_the_in_process_rollout(probe, launch, untrained_checkpoint):
    """Over DDS, in lockstep, the closed loop is step for step the in-process one (nothing stale, nothing lost)."""
    steps = 150
    by_step = _run_lockstep(probe, launch, untrained_checkpoint, joints=4, seed=5, sim_seconds=steps * 0.04)
    want = _rollout(GraphActorCritic.load(untrained_checkpoint).eval(), 4, 5, steps)
    assert set(range(steps + 1)) <= set(by_step)
    got = np.array([by_step[k] for k in range(steps + 1)])
    np.testing.assert_allclose(got, np.array(want), atol=1e-6)
    assert np.abs(got[-1] - got[0]).max() > 1e-3  # the swimmer did move


@pytest.mark.timeout(240)
@pytest.mark.skipif(not SHIPPED_MODEL.is_file(), reason=f"no shipped policy yet at {SHIPPED_MODEL} (PPO issue)")
def test_trained_policy_swims_forward(probe, launch):
    steps = 500  # 20 s of sim time
    by_step = _run_lockstep(probe, launch, SHIPPED_MODEL, joints=6, seed=0, sim_seconds=steps * 0.04)
    advance = by_step[steps][0] - by_step[0][0]
    want = _rollout(GraphActorCritic.load(SHIPPED_MODEL).eval(), 6, 0, steps)
    assert advance == pytest.approx(want[steps][0] - want[0][0], abs=1e-3)
    assert advance > 1.0, f"torso advanced only {advance:.3f} m in 20 s"  # a PPO checkpoint here: ~7 m


# -- policy node alone ---------------------------------------------------------------------
def _policy_with_publisher(probe, launch, checkpoint, **params):
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    pub = probe.node.create_publisher(JointState, "joint_states", 10)
    proc = launch("morph_policy_node", checkpoint=str(checkpoint), **params)
    probe.spin_until(
        lambda: pub.get_subscription_count() > 0 and probe.node.count_subscribers("effort_commands") > 0,
        STARTUP,
        "the policy node's endpoints",
    )
    probe.spin_until(lambda: probe.node.count_publishers("effort_commands") > 0, STARTUP, "effort publisher")
    return proc, pub, efforts


def _answer(probe, pub, efforts, msg, joints):
    """Publish ``msg`` until an answer of ``joints`` values arrives (the policy's input is best effort)."""
    for _ in range(5):
        n = len(efforts)
        pub.publish(msg)
        try:
            probe.spin_until(lambda n=n: any(len(e.data) == joints for e in efforts[n:]), 2.0, "an answer")
            return [e for e in efforts[n:] if len(e.data) == joints][0]
        except AssertionError:
            continue
    raise AssertionError(f"no answer with {joints} efforts")


@pytest.mark.timeout(120)
def test_malformed_joint_states_are_rejected_and_good_ones_answered(probe, launch, untrained_checkpoint):
    proc, pub, efforts = _policy_with_publisher(probe, launch, untrained_checkpoint)
    bad = [
        _state(["a", "b"], [0.1], [0.0, 0.0]),  # length mismatch
        _state(["a", "b"], [0.1, 0.2], [0.0]),
        _state(["a", "b"], [0.1, math.nan], [0.0, 0.0]),
        _state(["a", "b"], [0.1, 0.2], [math.inf, 0.0]),
        _state([], [], []),
        _state([f"j{i}" for i in range(65)], [0.0] * 65, [0.0] * 65),
        _state(["a", "a"], [0.1, 0.2], [0.0, 0.0]),
    ]
    for i, msg in enumerate(bad):
        pub.publish(msg)
        joints = 3 + i  # a length no bad message has, so its answer is unambiguous
        good = _state([f"j{k}" for k in range(joints)], np.linspace(-0.3, 0.3, joints), np.zeros(joints))
        answer = _answer(probe, pub, efforts, good, joints)
        assert np.isfinite(answer.data).all()
    assert {len(e.data) for e in efforts} <= set(range(3, 3 + len(bad)))  # nothing answered the bad ones
    assert proc.alive()
    assert "rejected joint_states" in proc.log()
    assert "duplicate" in proc.log() or "length mismatch" in proc.log()


@pytest.mark.timeout(120)
def test_silent_input_gives_zero_efforts(probe, launch, untrained_checkpoint):
    proc, pub, efforts = _policy_with_publisher(probe, launch, untrained_checkpoint, input_timeout=0.3)
    good = _state([f"j{k}" for k in range(5)], [0.3, -0.2, 0.1, 0.0, 0.2], [0.0] * 5)
    answer = _answer(probe, pub, efforts, good, 5)
    assert np.abs(answer.data).max() > 0
    n = len(efforts)
    probe.spin_until(lambda: any(not any(e.data) for e in efforts[n:]), 10.0, "zero efforts after silence")
    zeros = [e for e in efforts[n:] if not any(e.data)]
    assert len(zeros[0].data) == 5
    # New input ends the silence: real efforts again.
    answer = _answer(probe, pub, efforts, good, 5)
    assert np.abs(answer.data).max() > 0
    assert "publishing zero efforts" in proc.log()


@pytest.mark.timeout(120)
def test_sampling_publishes_policy_info(probe, launch, untrained_checkpoint):
    infos = probe.collect(JointTrajectory, "policy_info")
    proc, pub, efforts = _policy_with_publisher(probe, launch, untrained_checkpoint, deterministic=False)
    good = _state(["x", "y", "z", "w"], [0.3, -0.2, 0.1, 0.0], [0.1] * 4, sec=42)
    answer = _answer(probe, pub, efforts, good, 4)
    probe.spin_until(lambda: infos, 10.0, "policy_info")
    msg, point = infos[0], infos[0].points[0]
    stamp_ns = to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)
    fields = (point.positions, point.velocities, point.accelerations, point.effort)
    info = unpack_policy_info(0, stamp_ns, msg.joint_names, *fields)
    assert info.names == ("x", "y", "z", "w") and info.stamp_ns == 42 * 10**9
    assert answer.layout.dim[0].label == "joints@42.000000000"  # the answer names the state it answers
    np.testing.assert_allclose(np.clip(info.action, -1, 1), answer.data, atol=1e-12)
    # The log-prob is the Gaussian's, recomputed here from the published mean and log-std.
    log_std = float(GraphActorCritic.load(untrained_checkpoint).log_std.detach())
    np.testing.assert_allclose(info.log_std, log_std, atol=1e-7)
    z = (info.action - info.mean) / math.exp(log_std)
    want = float(np.sum(-0.5 * z**2 - log_std - 0.5 * math.log(2 * math.pi)))
    assert info.log_prob == pytest.approx(want, abs=1e-6)
    assert not np.allclose(info.action, info.mean)  # it sampled


# -- sim node alone ------------------------------------------------------------------------
@pytest.mark.timeout(120)
def test_sim_rejects_malformed_commands_and_keeps_running(probe, launch):
    states = probe.collect(JointState, "joint_states")
    odoms = probe.collect(Odometry, "odom")
    pub = probe.node.create_publisher(Float64MultiArray, "effort_commands", 10)
    proc = launch("swimmer_sim_node", num_joints=3, real_time_factor=2.0, effort_timeout=5.0)
    probe.spin_until(lambda: pub.get_subscription_count() > 0 and states, STARTUP, "the sim")
    for bad in ([0.5, 0.5], [0.5, math.nan, 0.5], [0.1] * 4):
        pub.publish(Float64MultiArray(data=bad))
    pub.publish(Float64MultiArray(data=[0.7, -0.4, 2.0]))
    probe.spin_until(lambda: states[-1].effort.tolist() == [0.7, -0.4, 1.0], 10.0, "the good command applied")
    n = len(states)
    probe.spin_until(lambda: len(states) > n + 10, 10.0, "the sim still publishing")
    assert proc.alive() and "rejected effort command" in proc.log()
    stamps = [_stamp(s) for s in states]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    # One state per control period (a slow probe may miss some of the sim's keep-last history).
    periods = np.diff(stamps) / 0.04
    np.testing.assert_allclose(periods, np.round(periods), atol=1e-6)
    assert np.median(np.round(periods)) == 1
    # Odometry goes out with every joint state, same stamp.
    assert len({_stamp(o) for o in odoms} & set(stamps)) > len(stamps) // 2


@pytest.mark.timeout(180)
def test_the_hand_over_between_bodies_is_not_logged_as_a_fault(probe, launch, untrained_checkpoint):
    """A lockstep sim drawing a new chain length at every reset (as live.sh's sims do): the new body's first
    states may reach the policy before its description. That hand-over is counted, logged as info, and so is the
    silence it causes; it used to warn 'rejected joint_states ... lacks 2 of robot_description's 9 actuated
    joints' and 'no state answered for 0.5 s' at every change."""
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    launch("swimmer_sim_node", min_joints=2, max_joints=9, episode_steps=15, lockstep=True, real_time_factor=0.0,
           effort_timeout=2.0, seed=3)  # fmt: skip
    policy = launch("morph_policy_node", checkpoint=str(untrained_checkpoint))
    probe.spin_until(lambda: len({len(e.data) for e in efforts}) >= 5, 120.0, "efforts for 5 chain lengths")
    warnings = [line for line in policy.log().splitlines() if "[WARN]" in line and "UNTRAINED" not in line]
    assert [w for w in warnings if "joint_states" in w or "no state answered" in w] == [], policy.log()[-3000:]
    # A state that never fits warns from the same place that logged the hand-over as info: the node goes on
    # (rclpy refuses a call site whose severity changes; one shared call ended the node here).
    pub = probe.node.create_publisher(JointState, "joint_states", 10)
    probe.spin_until(lambda: pub.get_subscription_count() > 0, STARTUP, "the policy node subscribed")
    bad = _state(["motor1_rot", "motor2_rot"], [float("nan"), 0.0], [0.0, 0.0], sec=10**6)

    def rejected_with_a_warning() -> bool:
        pub.publish(bad)
        return any("[WARN]" in line and "rejected joint_states" in line for line in policy.log().splitlines())

    probe.spin_until(rejected_with_a_warning, 30.0, "the malformed state rejected with a warning")
    seen = len(efforts)
    probe.spin_until(lambda: len(efforts) > seen + 20, 60.0, "efforts after the warning")
    assert policy.alive() and "Logger severity" not in policy.log(), policy.log()[-3000:]
