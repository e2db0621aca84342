"""Fail-safe checkpoints on real policy node processes over real DDS.

A bad checkpoint stops the node at start-up (non-zero exit, one line naming the file and the reason,
no traceback) and is refused at runtime (the reason in the SetParametersResult, the old policy goes on);
an untrained policy runs only when asked for and marks its efforts; a policy whose output overflows
never puts a non-finite effort on the wire. Runs inside a private network namespace (``scripts/test.sh``).
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from morph_core.msgs.effort_names import names_label, tree_label
from morph_core.msgs.stamps import SILENCE_TAG
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import KinematicTree
from morph_core.policy.weights import load_checkpoint
from morph_policy_node.policy_choice import UNTRAINED_LABEL

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _state(names, pos, vel):
    return JointState(name=list(names), position=[float(x) for x in pos], velocity=[float(x) for x in vel])


def _policy_with_publisher(probe, launch, **params):
    efforts = []
    probe.node.create_subscription(Float64MultiArray, "effort_commands", efforts.append, DEEP)
    pub = probe.node.create_publisher(JointState, "joint_states", 10)
    proc = launch("morph_policy_node", **params)
    probe.spin_until(
        lambda: pub.get_subscription_count() > 0 and probe.node.count_publishers("effort_commands") > 0,
        STARTUP,
        "the policy node's endpoints",
    )
    return proc, pub, efforts


def _is_answer(effort, joints) -> bool:
    """An answer to a state (tagged), not the watchdog's zeros."""
    return len(effort.data) == joints and bool(effort.layout.dim) and bool(effort.layout.dim[0].label)


def _answer(probe, pub, efforts, msg, joints):
    """Publish ``msg`` until an answer of ``joints`` values arrives (the policy's input is best effort)."""
    for _ in range(5):
        n = len(efforts)
        pub.publish(msg)
        try:
            probe.spin_until(lambda n=n: any(_is_answer(e, joints) for e in efforts[n:]), 2.0, "an answer")
        except AssertionError:
            continue
        return next(e for e in efforts[n:] if _is_answer(e, joints))
    raise AssertionError(f"no answer with {joints} efforts")


def _wait_exit(proc, timeout):
    deadline = time.monotonic() + timeout
    while proc.alive() and time.monotonic() < deadline:
        time.sleep(0.05)
    return proc.proc.poll()


@pytest.mark.timeout(240)
def test_every_bad_checkpoint_stops_the_node_at_start_up_with_one_line(launch, bad_checkpoints):
    cases = {
        name: (launch("morph_policy_node", checkpoint=str(path)), path, words)
        for name, (path, words) in bad_checkpoints.items()
    }
    cases["none_given"] = (launch("morph_policy_node", checkpoint=""), None, ("allow_untrained",))
    for name, (proc, path, words) in cases.items():
        code = _wait_exit(proc, STARTUP)
        log = proc.log()
        assert code is not None and code != 0, f"{name}: still running or exit 0\n{log}"
        assert "Traceback" not in log, f"{name}:\n{log}"
        lines = [line for line in log.splitlines() if "cannot start" in line]
        assert len(lines) == 1, f"{name}:\n{log}"
        if path is not None:
            assert str(path) in lines[0], f"{name}: {lines[0]}"
        assert all(w in lines[0] for w in words), f"{name}: {lines[0]}"


@pytest.mark.timeout(120)
def test_an_untrained_policy_runs_only_when_asked_and_marks_every_effort(probe, launch, untrained_checkpoint):
    proc, pub, efforts = _policy_with_publisher(probe, launch, checkpoint="", allow_untrained=True, input_timeout=0.3)
    good = _state(["a", "b", "c"], [0.2, -0.1, 0.3], [0.0] * 3)
    reply = _answer(probe, pub, efforts, good, 3)
    # The joints' names (msgs.effort_names), then the mark.
    chain = tree_label(KinematicTree.chain(3, ("a", "b", "c")).layout_hash)  # no description: a chain
    assert [d.label for d in reply.layout.dim][1:] == [names_label(("a", "b", "c")), chain, UNTRAINED_LABEL]
    assert reply.layout.dim[0].label.startswith("joints@")  # still the answer tag a sim reads
    n = len(efforts)
    probe.spin_until(lambda: any(not any(e.data) for e in efforts[n:]), 10.0, "zero efforts after silence")
    assert all(e.layout.dim and e.layout.dim[-1].label == UNTRAINED_LABEL for e in efforts)  # the zeros too
    zeros = next(e for e in efforts[n:] if not any(e.data))
    assert [d.label for d in zeros.layout.dim] == [SILENCE_TAG, names_label(("a", "b", "c")), chain, UNTRAINED_LABEL]
    assert "UNTRAINED" in proc.log()


@pytest.mark.timeout(120)
def test_a_trained_policy_is_not_marked(probe, launch, untrained_checkpoint):
    _, pub, efforts = _policy_with_publisher(probe, launch, checkpoint=str(untrained_checkpoint))
    reply = _answer(probe, pub, efforts, _state(["a", "b"], [0.1, 0.2], [0.0, 0.0]), 2)
    layout = tree_label(KinematicTree.chain(2, ("a", "b")).layout_hash)
    assert [d.label for d in reply.layout.dim][1:] == [names_label(("a", "b")), layout]  # the joints alone
    assert UNTRAINED_LABEL not in {d.label for e in efforts for d in e.layout.dim}


@pytest.mark.timeout(300)
def test_a_bad_checkpoint_at_runtime_is_refused_and_the_old_policy_goes_on(
    probe, launch, namespace, untrained_checkpoint, bad_checkpoints
):
    proc, pub, efforts = _policy_with_publisher(probe, launch, checkpoint=str(untrained_checkpoint))
    pos, vel, glob = np.array([0.3, -0.2, 0.1, 0.25]), np.array([0.5, 0.0, -0.5, 0.1]), np.zeros(4)
    want = np.clip(NumpyPolicy(load_checkpoint(untrained_checkpoint)).mean(pos, vel, glob), -1, 1)
    msg = _state(["w", "x", "y", "z"], pos, vel)
    np.testing.assert_allclose(_answer(probe, pub, efforts, msg, 4).data, want, atol=1e-9)
    cases = dict(bad_checkpoints, none_given=("", ("allow_untrained",)))
    for name, (path, words) in cases.items():
        result = probe.set_parameter(f"{namespace}/morph_policy", "checkpoint", str(path))
        assert not result.successful, name
        assert str(path) in result.reason and all(w in result.reason for w in words), (name, result.reason)
        assert proc.alive(), f"{name}:\n{proc.log()}"
        np.testing.assert_allclose(_answer(probe, pub, efforts, msg, 4).data, want, atol=1e-9, err_msg=name)
    assert "Traceback" not in proc.log()


@pytest.mark.timeout(120)
@pytest.mark.parametrize("deterministic", [True, False])
def test_an_overflowing_policy_never_publishes_a_non_finite_effort(
    probe, launch, overflowing_checkpoint, deterministic
):
    proc, pub, efforts = _policy_with_publisher(
        probe, launch, checkpoint=str(overflowing_checkpoint), deterministic=deterministic, input_timeout=0.3
    )
    msg = _state(["a", "b", "c"], [0.2, -0.1, 0.3], [0.0] * 3)
    deadline = time.monotonic() + 20.0
    while not any(len(e.data) == 3 for e in efforts):  # the watchdog's zeros for the chain it saw
        assert time.monotonic() < deadline, f"no zero efforts\n{proc.log()}"
        pub.publish(msg)
        probe.spin_for(0.2)
    for _ in range(10):
        pub.publish(msg)
        probe.spin_for(0.05)
    assert all(math.isfinite(v) for e in efforts for v in e.data)
    assert all(not any(e.data) for e in efforts)  # a clip would have made inf a full-scale +1
    assert all(e.layout.dim[0].label == SILENCE_TAG for e in efforts)  # no state was answered
    assert proc.alive() and "not finite" in proc.log()
