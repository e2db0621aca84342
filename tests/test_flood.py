"""No peer can wedge a node: every input of both nodes flooded with legal traffic, over real DDS.

The trigger of the Fast DDS 2.14 wedge (one huge message followed at once by ten small valid ones,
repeated for 5 s) against each subscription and each parameter service, from this test's own
process: the node keeps publishing, acts only on the valid messages, and exits within 2 s of
SIGTERM. Runs inside a private network namespace (``scripts/test.sh``).
"""

from __future__ import annotations

import array
import signal
import time

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Int64MultiArray, UInt8MultiArray

from morph_core.msgs.stream_chunk import MAX_CHUNK_BYTES, unpack_stream_chunk
from morph_core.msgs.stream_chunk import TOPIC as CHUNK_TOPIC

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
FLOOD_SECONDS = 5.0
HUGE = 100_000
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _collect(probe, msg_type, topic):
    got: list = []
    stamps: list[float] = []

    def on_msg(msg):
        got.append(msg)
        stamps.append(time.monotonic())

    probe.node.create_subscription(msg_type, topic, on_msg, DEEP)
    return got, stamps


def _flood(probe, send_huge, send_small, seconds=FLOOD_SECONDS) -> int:
    """One huge message then ten small ones, again and again for ``seconds``; the probe keeps spinning."""
    rounds = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        send_huge()
        for _ in range(10):
            send_small()
        rounds += 1
        probe.executor.spin_once(timeout_sec=0.002)
    return rounds


MAX_GAP = 3.0
"""longest silence [s] allowed while flooded: a wedge is forever, a loaded 2-core machine can pause a second"""


def _longest_gap(stamps: list[float], start: float, end: float) -> float:
    inside = [start] + [t for t in stamps if start <= t <= end] + [end]
    return float(np.max(np.diff(inside)))


def _stops_on_sigterm(proc, within: float = 2.0) -> float:
    t = time.monotonic()
    proc.proc.send_signal(signal.SIGTERM)
    try:
        proc.proc.wait(timeout=10.0)
    except Exception:
        proc.proc.kill()
        raise AssertionError(f"ignored SIGTERM\n{proc.log()}") from None
    took = time.monotonic() - t
    assert took < within, f"took {took:.2f} s to exit after SIGTERM"
    assert proc.proc.returncode == 0, proc.log()
    return took


def _huge_string_request(name: str) -> SetParameters.Request:
    value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value="x" * (8 * HUGE))
    return SetParameters.Request(parameters=[ParameterMsg(name=name, value=value)])


def _flood_parameter_service(probe, node_path: str, seconds=FLOOD_SECONDS) -> None:
    """Huge SetParameters requests (an 800 kB string) then ten small ones, without waiting for answers."""
    client = probe.node.create_client(SetParameters, f"{node_path}/set_parameters")
    probe.spin_until(client.service_is_ready, STARTUP, f"{node_path}/set_parameters")
    huge = _huge_string_request("not_a_parameter")
    small = SetParameters.Request(
        parameters=[ParameterMsg(name="not_a_parameter", value=ParameterValue(type=ParameterType.PARAMETER_BOOL))]
    )
    _flood(probe, lambda: client.call_async(huge), lambda: client.call_async(small), seconds)
    # The service still answers afterwards.
    future = client.call_async(small)
    probe.spin_until(future.done, 20.0, "a set_parameters answer after the flood")
    assert not future.result().results[0].successful  # undeclared: refused, as it should be


# -- sim node ----------------------------------------------------------------------------------------------
@pytest.mark.timeout(180)
def test_sim_survives_huge_effort_commands(probe, launch):
    states, stamps = _collect(probe, JointState, "joint_states")
    pub = probe.node.create_publisher(Float64MultiArray, "effort_commands", 10)
    proc = launch("swimmer_sim_node", num_joints=3, real_time_factor=2.0, effort_timeout=5.0)
    probe.spin_until(lambda: pub.get_subscription_count() > 0 and states, STARTUP, "the sim")
    huge = Float64MultiArray(data=array.array("d", bytes(8 * HUGE)))
    valid = [[0.5, -0.25, 0.75], [-0.5, 0.25, 0.125]]
    k = iter(range(10**9))
    start = time.monotonic()
    rounds = _flood(probe, lambda: pub.publish(huge), lambda: pub.publish(Float64MultiArray(data=valid[next(k) % 2])))
    n = len(states)
    probe.spin_until(lambda: len(states) > n + 10, 10.0, "joint states after the flood")
    assert rounds > 20
    assert _longest_gap(stamps, start, time.monotonic()) < MAX_GAP, "the sim stopped publishing"
    applied = {tuple(s.effort) for s in states}
    assert applied <= {(0.0, 0.0, 0.0), *map(tuple, valid)}, "an effort nobody sent valid was applied"
    assert set(map(tuple, valid)) & applied, "no valid command was applied"
    assert proc.alive() and "rejected effort command" in proc.log()
    _stops_on_sigterm(proc)


@pytest.mark.timeout(180)
def test_sim_survives_huge_parameter_requests(probe, launch, namespace):
    states, stamps = _collect(probe, JointState, "joint_states")
    proc = launch("swimmer_sim_node", num_joints=2, real_time_factor=2.0)
    probe.spin_until(lambda: states, STARTUP, "the sim")
    start = time.monotonic()
    _flood_parameter_service(probe, f"{namespace}/swimmer_sim")
    n = len(states)
    probe.spin_until(lambda: len(states) > n + 10, 10.0, "joint states after the flood")
    assert _longest_gap(stamps, start, time.monotonic()) < MAX_GAP, "the sim stopped publishing"
    _stops_on_sigterm(proc)


# -- policy node -------------------------------------------------------------------------------------------
def _policy_answering(probe, launch, untrained_checkpoint, **params):
    efforts, stamps = _collect(probe, Float64MultiArray, "effort_commands")
    chunks, _ = _collect(probe, UInt8MultiArray, CHUNK_TOPIC)  # the node streams too while flooded
    state_pub = probe.node.create_publisher(JointState, "joint_states", 10)
    proc = launch("morph_policy_node", checkpoint=str(untrained_checkpoint), input_timeout=30.0, **params)
    probe.spin_until(
        lambda: state_pub.get_subscription_count() > 0 and probe.node.count_publishers("effort_commands") > 0,
        STARTUP,
        "the policy node",
    )
    return proc, state_pub, efforts, stamps, chunks


def _valid_state(k: int) -> JointState:
    msg = JointState(name=["a", "b", "c"], position=[0.1 * (k % 7), -0.2, 0.3], velocity=[0.0, 0.1, 0.0])
    msg.header.stamp.sec = 1 + k // 25
    msg.header.stamp.nanosec = (k % 25) * 40_000_000
    return msg


def _flood_policy(probe, proc, state_pub, efforts, stamps, chunks, send_huge) -> None:
    k = iter(range(10**9))
    start = time.monotonic()
    _flood(probe, send_huge, lambda: state_pub.publish(_valid_state(next(k))))
    n = len(efforts)
    for i in range(50):  # still answering afterwards
        state_pub.publish(_valid_state(10**6 + i))
        probe.spin_for(0.02)
    probe.spin_until(lambda: len(efforts) > n, 10.0, "answers after the flood")
    assert _longest_gap(stamps, start, time.monotonic()) < MAX_GAP, "the policy stopped answering"
    assert {len(e.data) for e in efforts} == {3}, "something answered the huge message"
    # Streamed throughout, each chunk within its bound (a huge message is left out, not split).
    probe.spin_until(lambda: len(chunks) > 0, 10.0, "stream chunks")
    assert all(len(c.data) <= MAX_CHUNK_BYTES and unpack_stream_chunk(c.data)[1] for c in chunks)
    assert proc.alive()
    _stops_on_sigterm(proc)


@pytest.mark.timeout(180)
def test_policy_survives_huge_joint_states(probe, launch, untrained_checkpoint):
    proc, state_pub, efforts, stamps, chunks = _policy_answering(probe, launch, untrained_checkpoint)
    names = [f"j{i}" for i in range(HUGE)]
    zeros = array.array("d", bytes(8 * HUGE))
    huge = JointState(name=names, position=zeros, velocity=zeros)
    _flood_policy(probe, proc, state_pub, efforts, stamps, chunks, lambda: state_pub.publish(huge))
    assert "more than the maximum" in proc.log()
    assert "not streamed" in proc.log()


@pytest.mark.timeout(180)
def test_policy_survives_huge_odometry(probe, launch, untrained_checkpoint):
    proc, state_pub, efforts, stamps, chunks = _policy_answering(probe, launch, untrained_checkpoint)
    odom_pub = probe.node.create_publisher(Odometry, "odom", 10)
    probe.spin_until(lambda: odom_pub.get_subscription_count() > 0, STARTUP, "the odom subscription")
    huge = Odometry()
    huge.header.frame_id = "o" * (8 * HUGE)
    huge.pose.pose.orientation.w = 1.0
    _flood_policy(probe, proc, state_pub, efforts, stamps, chunks, lambda: odom_pub.publish(huge))


@pytest.mark.timeout(180)
def test_policy_survives_huge_episode_announcements(probe, launch, untrained_checkpoint):
    proc, state_pub, efforts, stamps, chunks = _policy_answering(probe, launch, untrained_checkpoint)
    episode_pub = probe.node.create_publisher(Int64MultiArray, "episode_start", 10)
    probe.spin_until(lambda: episode_pub.get_subscription_count() > 0, STARTUP, "the episode_start subscription")
    huge = Int64MultiArray(data=array.array("q", bytes(8 * HUGE)))
    _flood_policy(probe, proc, state_pub, efforts, stamps, chunks, lambda: episode_pub.publish(huge))
    assert "rejected episode_start" in proc.log()


@pytest.mark.timeout(180)
def test_policy_survives_huge_parameter_requests(probe, launch, namespace, untrained_checkpoint):
    proc, state_pub, efforts, stamps, _ = _policy_answering(probe, launch, untrained_checkpoint)
    k = iter(range(10**9))

    def answer_some():
        for _ in range(3):
            state_pub.publish(_valid_state(next(k)))

    client = probe.node.create_client(SetParameters, f"{namespace}/morph_policy/set_parameters")
    probe.spin_until(client.service_is_ready, STARTUP, "set_parameters")
    huge = _huge_string_request("checkpoint")  # a huge path: refused as a checkpoint, never a crash
    start = time.monotonic()
    _flood(probe, lambda: client.call_async(huge), answer_some)
    n = len(efforts)
    probe.spin_until(lambda: len(efforts) > n or answer_some(), 10.0, "answers after the flood")
    assert _longest_gap(stamps, start, time.monotonic()) < MAX_GAP, "the policy stopped answering"
    future = client.call_async(huge)
    probe.spin_until(future.done, 20.0, "an answer to a huge request")
    assert not future.result().results[0].successful
    assert proc.alive() and "Traceback" not in proc.log()
    _stops_on_sigterm(proc)


@pytest.mark.timeout(180)
def test_policy_survives_huge_weights(probe, launch, untrained_checkpoint, trainer_key):
    from std_msgs.msg import MultiArrayDimension

    # A node that trusts a trainer reads the weights topic (one that trusts none does not even subscribe).
    proc, state_pub, efforts, stamps, chunks = _policy_answering(probe, launch, untrained_checkpoint,
                                                                 trusted_keys=trainer_key.trusted)  # fmt: skip
    weights_pub = probe.node.create_publisher(UInt8MultiArray, "policy_weights", 10)
    probe.spin_until(lambda: weights_pub.get_subscription_count() > 0, STARTUP, "the policy_weights subscription")
    huge = UInt8MultiArray(data=bytes(8 * HUGE))  # fragmented on the wire; not a policy
    huge.layout.dim = [MultiArrayDimension(label="safetensors", size=8 * HUGE, stride=8 * HUGE)]
    _flood_policy(probe, proc, state_pub, efforts, stamps, chunks, lambda: weights_pub.publish(huge))
    assert "rejected policy_weights" in proc.log()
