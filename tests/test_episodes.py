"""Episodes on the wire: the sim node's announcements, redraws, reset service and clock, over real DDS.

The test's own node plays the controller where the efforts must be known
exactly (to replay the recording in a fresh MorphSwimmerEnv), the policy node
where the point is that a real controller follows the episodes. Runs inside a
private network namespace (``scripts/test.sh``).
"""

from __future__ import annotations

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rcl_interfaces.srv import SetParameters
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Int64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.msgs.episode_start import EpisodeCause, pack_episode_start, unpack_episode_start
from morph_core.msgs.joint_state import quaternion_from_yaw
from morph_core.msgs.stamps import answer_tag, from_ns, to_ns
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.protocol.sim_wire import chain_lengths

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
PERIOD_NS = 40_000_000
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _ns(msg) -> int:
    return to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)


def _starts(announcements) -> dict:
    """{first state's stamp: record} of the announcements received."""
    records = [unpack_episode_start(0, m.layout.dim[0].label, m.data) for m in announcements]
    return {r.stamp_ns: r for r in records}


def _unique_states(states) -> list:
    """The states in stamp order, each once (a lockstep sim re-sends a state that waits too long)."""
    by_stamp = {}
    for s in states:
        by_stamp.setdefault(_ns(s), s)
    return [by_stamp[k] for k in sorted(by_stamp)]


class _Controller:
    """Answers every joint state with seeded random efforts tagged with its stamp (the same efforts
    again for a re-sent state), and remembers them for the replay."""

    def __init__(self, probe, seed: int):
        self.rng = np.random.default_rng(seed)
        self.pub = probe.node.create_publisher(Float64MultiArray, "effort_commands", 10)
        self.answers: dict[int, np.ndarray] = {}
        self.states: list[JointState] = []
        probe.node.create_subscription(JointState, "joint_states", self._on_state, DEEP)

    def _on_state(self, msg: JointState) -> None:
        self.states.append(msg)
        stamp = _ns(msg)
        if stamp not in self.answers:
            self.answers[stamp] = self.rng.uniform(-1, 1, len(msg.name))
        out = Float64MultiArray(data=self.answers[stamp].tolist())
        n = len(msg.name)
        out.layout.dim = [
            MultiArrayDimension(label=answer_tag(msg.header.stamp.sec, msg.header.stamp.nanosec), size=n, stride=n)
        ]
        self.pub.publish(out)


@pytest.mark.timeout(180)
def test_lockstep_episodes_are_announced_redrawn_and_replay_in_a_fresh_env(probe, launch):
    lo, hi, steps, seed, wanted = 2, 9, 6, 4, 60
    announcements = probe.collect(Int64MultiArray, "episode_start", LATCHED)
    clocks = probe.collect(Clock, "/clock")
    controller = _Controller(probe, seed=0)
    launch(
        "swimmer_sim_node",
        min_joints=lo,
        max_joints=hi,
        episode_steps=steps,
        seed=seed,
        lockstep=True,
        real_time_factor=0.0,
        effort_timeout=2.0,
    )
    probe.spin_until(lambda: len({_ns(s) for s in controller.states}) >= wanted, STARTUP + 60, f"{wanted} states")
    episodes = -(-wanted // (steps + 1))
    probe.spin_until(lambda: len(_starts(announcements)) >= episodes, 10.0, f"{episodes} announcements")
    states = _unique_states(controller.states)[:wanted]
    starts = _starts(announcements)

    # One state per control period, resets included; /clock never goes back.
    stamps = np.array([_ns(s) for s in states])
    np.testing.assert_array_equal(np.diff(stamps), PERIOD_NS)
    clock_ns = [to_ns(c.clock.sec, c.clock.nanosec) for c in clocks]
    assert clock_ns == sorted(clock_ns) and clock_ns[-1] >= stamps[-1]

    # An announcement for the first state and then for every (steps + 1)-th: steps, then the next first state.
    announced = [i for i, s in enumerate(states) if _ns(s) in starts]
    assert announced == list(range(0, wanted, steps + 1))
    records = [starts[_ns(states[i])] for i in announced]
    assert [r.episode for r in records] == list(range(len(records)))
    assert [r.cause for r in records] == ["start"] + ["steps"] * (len(records) - 1)
    for i, r in zip(announced, records, strict=True):
        assert r.num_joints == len(states[i].name)
        assert not any(states[i].effort)  # nothing applied yet in a new episode
    lengths = [r.num_joints for r in records]
    assert lo <= min(lengths) and max(lengths) <= hi and len(set(lengths)) >= 3  # redrawn

    # The recording replays exactly: reset(seed) once, reset() at each announcement, the answers stepped.
    env = MorphSwimmerEnv(num_joints=(lo, hi))
    env.reset(seed=seed)
    for k, s in enumerate(states):
        if k > 0:
            if _ns(s) in starts:
                env.reset()
            else:
                env.step(controller.answers[_ns(states[k - 1])])
                np.testing.assert_array_equal(s.effort, controller.answers[_ns(states[k - 1])])
        assert len(s.name) == env.num_joints
        np.testing.assert_array_equal(s.position, env.data.qpos[3:])
        np.testing.assert_array_equal(s.velocity, env.data.qvel[3:])


@pytest.mark.timeout(180)
def test_reset_service_starts_an_announced_episode_the_policy_follows(probe, launch, namespace, untrained_checkpoint):
    announcements = probe.collect(Int64MultiArray, "episode_start", LATCHED)
    states = probe.collect(JointState, "joint_states")
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    clocks = probe.collect(Clock, "/clock")
    launch("swimmer_sim_node", num_joints=5, lockstep=True, real_time_factor=0.0, effort_timeout=2.0)
    launch("morph_policy_node", checkpoint=str(untrained_checkpoint))
    probe.spin_until(lambda: len(states) > 20, STARTUP, "the loop running")

    client = probe.node.create_client(Trigger, f"{namespace}/swimmer_sim/reset")
    probe.spin_until(client.service_is_ready, STARTUP, "the reset service")
    future = client.call_async(Trigger.Request())
    probe.spin_until(future.done, 10.0, "the reset response")
    assert future.result().success and "episode 1" in future.result().message
    probe.spin_until(lambda: len(_starts(announcements)) >= 2, 10.0, "the new episode's announcement")
    start = max(_starts(announcements).values(), key=lambda r: r.episode)
    assert (start.episode, start.num_joints, start.cause) == (1, 5, "reset")
    # The loop goes on in the new episode: its first state and later ones are answered.
    probe.spin_until(
        lambda: any(_ns(s) > start.stamp_ns + 10 * PERIOD_NS for s in states), 30.0, "the new episode running"
    )
    answered = {e.layout.dim[0].label for e in efforts}
    first = next(s for s in states if _ns(s) == start.stamp_ns)
    assert answer_tag(first.header.stamp.sec, first.header.stamp.nanosec) in answered
    assert not any(first.effort)

    unique = _unique_states(states)
    np.testing.assert_array_equal(np.diff([_ns(s) for s in unique]), PERIOD_NS)  # no gap, no going back
    clock_ns = [to_ns(c.clock.sec, c.clock.nanosec) for c in clocks]
    assert clock_ns == sorted(clock_ns)
    # The new episode's swimmer is a fresh one: back near the origin.
    assert np.abs(first.position).max() < 0.2

    # A subscriber that comes late still learns where the current episode began (latched), and only that.
    late = probe.collect(Int64MultiArray, "episode_start", LATCHED)
    probe.spin_until(lambda: late, 10.0, "the latched announcement")
    probe.spin_for(0.3)
    assert [unpack_episode_start(0, m.layout.dim[0].label, m.data).episode for m in late] == [1]


@pytest.mark.timeout(120)
def test_episode_steps_set_at_runtime(probe, launch, namespace):
    announcements = probe.collect(Int64MultiArray, "episode_start", LATCHED)
    controller = _Controller(probe, seed=1)
    launch("swimmer_sim_node", num_joints=3, lockstep=True, real_time_factor=0.0, effort_timeout=2.0)
    probe.spin_until(lambda: len(controller.states) > 10, STARTUP, "the loop running")
    assert len(_starts(announcements)) == 1  # episode_steps 0: no resets

    client = probe.node.create_client(SetParameters, f"{namespace}/swimmer_sim/set_parameters")
    probe.spin_until(client.service_is_ready, STARTUP, "set_parameters")

    def set_steps(value):
        request = SetParameters.Request(parameters=[Parameter("episode_steps", value=value).to_parameter_msg()])
        future = client.call_async(request)
        probe.spin_until(future.done, 10.0, "set_parameters response")
        return future.result().results[0]

    assert not set_steps(-1).successful
    assert set_steps(4).successful
    probe.spin_until(lambda: len(_starts(announcements)) >= 4, 30.0, "episodes every 4 steps")
    starts = sorted(_starts(announcements))
    assert all(b - a == 5 * PERIOD_NS for a, b in zip(starts[1:], starts[2:], strict=False))
    assert {r.cause for r in _starts(announcements).values()} == {"start", "steps"}
    assert {r.num_joints for r in _starts(announcements).values()} == {3}


@pytest.mark.timeout(60)
def test_a_bad_joint_range_stops_the_node_with_a_clear_error(launch):
    proc = launch("swimmer_sim_node", min_joints=7, max_joints=3)
    proc.proc.wait(timeout=STARTUP)
    assert proc.proc.returncode != 0
    assert "min_joints and max_joints" in proc.log()


@pytest.mark.parametrize(
    "args, want",
    [((6, 0, 0), 6), ((6, 2, 10), (2, 10)), ((6, 4, 4), (4, 4))],
)
def test_chain_lengths_from_parameters(args, want):
    assert chain_lengths(*args) == want


@pytest.mark.parametrize("args", [(6, 0, 5), (6, 5, 0), (6, 9, 3), (6, 2, 65)])
def test_chain_lengths_refuses_half_or_empty_ranges(args):
    with pytest.raises(ValueError, match="min_joints and max_joints"):
        chain_lengths(*args)


@pytest.mark.timeout(120)
def test_policy_restarts_yaw_unwrapping_with_each_announced_episode(probe, launch, untrained_checkpoint):
    """A swimmer that turned past pi, then a new episode with the same chain: the policy must see the new
    swimmer's yaw (near 0), not the old one's branch (2 pi + it); only the announcement tells it."""
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    state_pub = probe.node.create_publisher(JointState, "joint_states", 10)
    odom_pub = probe.node.create_publisher(Odometry, "odom", 10)
    episode_pub = probe.node.create_publisher(Int64MultiArray, "episode_start", 10)
    launch("morph_policy_node", checkpoint=str(untrained_checkpoint))
    probe.spin_until(
        lambda: (
            all(p.get_subscription_count() > 0 for p in (state_pub, odom_pub, episode_pub))
            and probe.node.count_publishers("effort_commands") > 0
        ),
        STARTUP,
        "the policy node's endpoints",
    )
    mean_of = NumpyPolicy(GraphActorCritic.load(untrained_checkpoint).eval())
    names, pos, vel = ["a", "b", "c"], np.array([0.1, -0.2, 0.3]), np.zeros(3)

    def want(yaw):
        return np.clip(mean_of.mean(pos, vel, np.array([yaw, 0.0, 0.0, 0.0])), -1, 1)

    def ask(stamp_ns, yaw):
        sec, nanosec = from_ns(stamp_ns)
        odom = Odometry()
        odom.header.stamp.sec, odom.header.stamp.nanosec = sec, nanosec
        q = odom.pose.pose.orientation
        q.x, q.y, q.z, q.w = quaternion_from_yaw(yaw)
        state = JointState(name=names, position=pos.tolist(), velocity=vel.tolist())
        state.header.stamp = odom.header.stamp
        tag = answer_tag(sec, nanosec)
        for _ in range(5):  # the policy reads best effort: ask again if a message was lost
            odom_pub.publish(odom)
            state_pub.publish(state)
            try:
                probe.spin_until(
                    lambda: any(e.layout.dim and e.layout.dim[0].label == tag for e in efforts), 2.0, "an answer"
                )
            except AssertionError:
                continue
            return np.array(next(e.data for e in efforts if e.layout.dim and e.layout.dim[0].label == tag))
        raise AssertionError(f"no answer for {tag}")

    for k, yaw in enumerate(np.arange(0.0, 4.01, 0.5)):  # turning past pi, 0.5 rad per state
        answer = ask(k * PERIOD_NS, yaw)
    np.testing.assert_allclose(answer, want(4.0), atol=1e-9)  # unwrapped: 4.0, not 4.0 - 2 pi
    assert np.abs(want(4.0) - want(4.0 - 2 * np.pi)).max() > 1e-6  # the check can tell the branches apart

    start = (k + 1) * PERIOD_NS
    label, data = pack_episode_start(1, start, 3, EpisodeCause.STEPS)
    announcement = Int64MultiArray(data=data)
    announcement.layout.dim = [MultiArrayDimension(label=label, size=len(data), stride=len(data))]
    episode_pub.publish(announcement)
    answer = ask(start, 0.05)
    np.testing.assert_allclose(answer, want(0.05), atol=1e-9)
    assert np.abs(answer - want(0.05 + 2 * np.pi)).max() > 1e-6  # not the old swimmer's branch
    np.testing.assert_allclose(ask(start + PERIOD_NS, 0.3), want(0.3), atol=1e-9)
