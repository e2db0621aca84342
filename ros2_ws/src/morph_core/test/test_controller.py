"""One controller: what the policy node answers, what the loopback records and what the transitions rebuild, equal to
the bit on the same recorded messages; the yaw unwrap's one reset rule; efforts in the robot's units.

The node's path is ``Controller`` fed each message in the order received, as ``MorphPolicyNode``'s callbacks
feed it (the node over DDS: ``tests/test_controller_node.py``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import random
import time
import types
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from morph_core.env.bodies import star_parents, swimmer_tree, y_parents
from morph_core.env.centipede_model import centipede_model
from morph_core.env.sim import SwimmerSim
from morph_core.env.urdf import robot_urdf, swimmer_urdf
from morph_core.msgs.joint_state import JointStateError, quaternion_from_yaw
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    PolicyInfoRecord,
)
from morph_core.policy.config import PolicyConfig
from morph_core.policy.joint_description import NUM_DESCRIPTION_FEATURES, urdf_descriptions
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import KinematicTree
from morph_core.policy.weights import untrained_weights
from morph_core.protocol.controller import (
    EFFORT_LIMIT,
    JOINT_DESCRIPTION,
    NO_DESCRIPTION,
    NO_EFFORT_LIMITS,
    Controller,
    EffortOrderError,
    PolicyOutputError,
    effort_limit_error,
    policy_error,
)
from morph_core.protocol.joint_map import JointMapError
from morph_core.protocol.loopback import LoopbackRecording, SamplingController, body_sim
from morph_core.protocol.robot_description import DESCRIPTION, PREVIOUS_DESCRIPTION
from morph_core.protocol.transitions import SkipCounts, TransitionAssembler, TransitionConfig, assemble

SEED = 5
SWIMMER = untrained_weights(seed=1)
LEGGED = untrained_weights(PolicyConfig(global_features=12), seed=1)
DESCRIBED = untrained_weights(PolicyConfig(global_features=12, joint_features=NUM_DESCRIPTION_FEATURES), seed=1)


def chains():
    return SwimmerSim(3, seed=SEED, effort_timeout=None), (None, 5, 4), {}


def trees():
    bodies = (swimmer_tree(star_parents(2, 2)), swimmer_tree(y_parents(1, 2)), swimmer_tree([-1, 0, 1, 0, -1]))
    return body_sim(bodies[0], SEED), (None, *bodies[1:]), dict(describe=True, shuffle_seed=4, name_efforts=True)


def centipedes():
    sim = SwimmerSim(bodies="centipede:2-3", seed=SEED, effort_timeout=None)
    return sim, (None, None, None), dict(describe=True, shuffle_seed=6, name_efforts=True)


def legged():
    sim = SwimmerSim(bodies="legged:4-6x2-3", seed=SEED, effort_timeout=None)
    return sim, (None, None, None), dict(describe=True, shuffle_seed=8, name_efforts=True)


CASES = {
    "chains": (chains, SWIMMER),
    "trees": (trees, SWIMMER),
    "centipedes": (centipedes, LEGGED),
    "legged, described": (legged, DESCRIBED),  # a policy that reads joint descriptions, on generated bodies
}


def recorded(case: str, steps: int = 25) -> tuple[LoopbackRecording, object]:
    make, weights = CASES[case]
    sim, bodies, options = make()
    loop = LoopbackRecording(sim, SamplingController(weights, seed=7), **options)
    for i, body in enumerate(bodies):
        if i:
            loop.new_episode(body)
        loop.run(steps)
    loop.finish()
    return loop, weights


def as_the_node(records, controller: Controller) -> list:
    """Each message to the controller as the policy node's callbacks hand it over; the answers, in order."""
    answers = []
    for r in records:
        if isinstance(r, DescriptionRecord):
            assert controller.description(r.text).outcome in ("adopted", "unchanged")
        elif isinstance(r, EpisodeStartRecord):
            controller.episode_start(r.stamp_ns)
        elif isinstance(r, OdometryRecord):
            answers += [controller.answer(ready) for ready in controller.odometry(r)]
        elif isinstance(r, JointStateRecord):
            answers += [controller.answer(ready) for ready in controller.state(r, 0.0)]
    return answers


def bits(x) -> bytes:
    return np.asarray(x, dtype=np.float64).tobytes()


@pytest.mark.parametrize("case", list(CASES))
def test_the_node_the_loopback_and_the_transitions_agree_to_the_bit(case):
    loop, weights = recorded(case)
    records = loop.records
    width = NumpyPolicy(weights).global_features
    assert width == (4 if case in ("chains", "trees") else 12)

    # The node's answers to the recorded messages are the loopback's recorded answers, bit for bit.
    answers = as_the_node(records, SamplingController(weights, seed=7))
    efforts = [r for r in records if isinstance(r, EffortRecord)]
    infos = [r for r in records if isinstance(r, PolicyInfoRecord)]
    assert len(answers) == len(efforts) == len(infos) == len(loop.truth) > 70
    for answer, effort, info in zip(answers, efforts, infos, strict=True):
        assert effort.answers_ns == info.stamp_ns == answer.stamp_ns
        assert bits(answer.efforts) == bits(effort.effort)
        assert answer.names == info.names and effort.names in (None, answer.names)
        assert effort.layout in (None, answer.layout)
        assert bits(answer.info["positions"]) == bits(info.action)
        assert bits(answer.info["velocities"]) == bits(info.mean)
        assert bits(answer.info["effort"]) == bits(info.log_prob_per_joint)

    # The transitions rebuild the observation each answer was computed on, bit for bit, and its action.
    assembler = TransitionAssembler(TransitionConfig(control_period=loop.sim.dt), global_features=width)
    transitions = assembler.push_many(records) + assembler.flush()
    assert assembler.skips == SkipCounts()
    assert len(transitions) == len(answers) - len({t.episode for t in loop.truth})  # an episode's last state: none
    by_stamp = {a.stamp_ns: a for a in answers}
    info_of = {i.stamp_ns: i for i in infos}
    for t in transitions:
        answer = by_stamp[t.stamp_ns]
        seen = answer.observation
        assert t.names == seen.names
        assert bits(t.global_feats) == bits(seen.global_feats)
        assert bits(t.joint_pos) == bits(seen.joint_pos) and bits(t.joint_vel) == bits(seen.joint_vel)
        assert t.parents.tolist() == seen.parents.tolist()
        sampled = dict(zip(answer.names, answer.info["positions"], strict=True))
        assert bits(t.action) == bits([sampled[name] for name in seen.names])
        assert t.log_prob == info_of[t.stamp_ns].log_prob
        assert bits(t.next_global) == bits(by_stamp[_next(t, answers)].observation.global_feats)

    # And what the controller built is what the env had (rebuilt from odometry: to rounding); the joint
    # descriptions it read off each robot_description are the compiled body's (env and sim node's).
    for truth, answer in zip(loop.truth, answers, strict=True):
        np.testing.assert_allclose(answer.observation.global_feats, truth.observation["global"], rtol=0, atol=1e-9)
        if weights is DESCRIBED:
            expected = truth.observation["joint_desc"]  # the compiled model's (mujoco_descriptions)
            np.testing.assert_allclose(answer.observation.joint_desc, expected, rtol=0, atol=1e-9)
        else:
            assert answer.observation.joint_desc is None
    if weights is DESCRIBED:  # bodies of different descriptions, each read off its own robot_description
        assert len({t.observation["joint_desc"].tobytes() for t in loop.truth}) > 1


def _next(t, answers) -> int:
    stamps = [a.stamp_ns for a in answers]
    return stamps[stamps.index(t.stamp_ns) + 1]


# -- the reset rule ------------------------------------------------------------------------------------------
def odometry(stamp_ns: int, yaw: float) -> OdometryRecord:
    return OdometryRecord(0, stamp_ns, 0.0, 0.0, quaternion_from_yaw(yaw), (0.0, 0.0), 0.0)


def yaws(events, controller=None) -> list[float]:
    """The controller's yaw feature at each ("state", stamp, yaw, robot) after the ("announce", stamp) before it."""
    controller = controller or Controller()
    out = []
    for event in events:
        if event[0] == "announce":
            controller.episode_start(event[1])
        else:
            _, stamp, yaw, robot = event
            out.append(controller.observe(stamp, robot, odometry(stamp, yaw))[0])
    return out


TURNED = math.pi - 0.1  # past +pi at the next state: unwrapped, pi + 0.1; restarted, -pi + 0.1


def test_the_unwrapping_restarts_for_a_new_episode_announced_before_its_state():
    events = [("state", 1, TURNED, "r"), ("announce", 2), ("state", 2, -TURNED, "r"), ("state", 3, -TURNED, "r")]
    assert yaws(events) == pytest.approx([TURNED, -TURNED, -TURNED])


def test_an_announcement_after_its_state_restarts_from_the_next_state():
    """The node answered the first state already: that answer stands, and the trainer rebuilds what it saw."""
    events = [("state", 1, TURNED, "r"), ("state", 2, -TURNED, "r"), ("announce", 2), ("state", 3, -TURNED, "r")]
    assert yaws(events) == pytest.approx([TURNED, 2 * math.pi - TURNED, -TURNED])


def test_the_unwrapping_restarts_for_another_robot_and_when_the_clock_goes_back_not_for_a_gap():
    another = [("state", 1, TURNED, (1, "a")), ("state", 2, -TURNED, (2, "a"))]  # a new description, one tree
    assert yaws(another) == pytest.approx([TURNED, -TURNED])
    restarted = [("state", 5, TURNED, "r"), ("state", 2, -TURNED, "r")]  # a restarted sim
    assert yaws(restarted) == pytest.approx([TURNED, -TURNED])
    gap = [("state", 1, TURNED, "r"), ("state", 9, -TURNED, "r")]  # states lost: nothing a controller sees
    assert yaws(gap) == pytest.approx([TURNED, 2 * math.pi - TURNED])


@pytest.mark.parametrize("late", [False, True])
def test_the_transitions_follow_the_nodes_rule_for_a_late_announcement(late):
    """The swimmer turned past +pi at an episode's first state; its announcement before or after the state: the
    transitions rebuild what the node saw, bit for bit, in either order."""
    weights = SWIMMER
    loop = LoopbackRecording(SwimmerSim(3, seed=SEED, effort_timeout=None), SamplingController(weights, seed=7))
    for i in range(3):  # one robot throughout: only the announcements restart the unwrapping
        if i:
            loop.new_episode()
        loop.run(15)
    loop.finish()
    states = [r.stamp_ns for r in loop.records if isinstance(r, JointStateRecord)]
    index = {stamp: i for i, stamp in enumerate(states)}

    def turned(r):
        if isinstance(r, OdometryRecord):
            return dataclasses.replace(r, orientation_xyzw=quaternion_from_yaw(3.0 + 0.05 * index[r.stamp_ns]))
        return r

    records = [turned(r) for r in loop.records]
    if late:  # each announcement after its episode's first state
        for i in [i for i, r in enumerate(records) if isinstance(r, EpisodeStartRecord)]:
            announcement = records.pop(i)
            j = next(j for j in range(i, len(records)) if isinstance(records[j], JointStateRecord))
            records.insert(j + 1, announcement)
    answers = as_the_node(records, SamplingController(weights, seed=7))
    firsts = [a for a in answers if a.stamp_ns in {r.stamp_ns for r in records if isinstance(r, EpisodeStartRecord)}]
    assert all(abs(a.observation.global_feats[0]) <= math.pi for a in firsts[:1])  # the very first: as it is
    assert any(a.observation.global_feats[0] > math.pi for a in firsts[1:]) == late  # a late one: unwrapped on
    batch = assemble(records).batch
    seen = {a.stamp_ns: a.observation.global_feats for a in answers}
    for k in range(len(batch)):
        assert bits(batch.global_feats[k]) == bits(seen[int(batch.stamp_ns[k])])


# -- efforts in the robot's units ------------------------------------------------------------------------------
def limited_urdf(limits) -> str:
    """A three-joint chain whose joints' ``<limit effort>`` are ``limits`` (None: the attribute left out)."""
    text = swimmer_urdf(3)
    out, start = [], 0
    for limit in limits:
        at = text.index("effort=", start)
        end = text.index('"', text.index('"', at) + 1) + 1
        out.append(text[start:at])
        out.append("" if limit is None else f'effort="{limit}"')
        start = end
    return "".join(out) + text[start:]


def state(stamp_ns: int, names=("motor1_rot", "motor2_rot", "motor3_rot"), pos=(0.3, -0.2, 0.1)) -> JointStateRecord:
    n = len(names)
    return JointStateRecord(0, stamp_ns, tuple(names), np.array(pos[:n]), np.full(n, 0.5), np.empty(0))


def test_urdf_units_scale_each_joint_by_its_limit():
    names = ("motor1_rot", "motor2_rot", "motor3_rot")
    shuffled = (names[2], names[0], names[1])
    for order in ("state", "description"):
        for deterministic in (True, False):
            normalized = Controller(NumpyPolicy(SWIMMER), deterministic=deterministic, effort_order=order)
            urdf = Controller(NumpyPolicy(SWIMMER), deterministic=deterministic, effort_order=order,
                              effort_units="urdf")  # fmt: skip
            for c in (normalized, urdf):
                assert c.description(limited_urdf([2.5, 0.5, 40])).outcome == "adopted"
                c.odometry(odometry(1, 0.2))
            a = normalized.answer(*normalized.state(state(1, shuffled), 0.0))
            b = urdf.answer(*urdf.state(state(1, shuffled), 0.0))
            scale = {"motor1_rot": 2.5, "motor2_rot": 0.5, "motor3_rot": 40.0}
            assert a.names == b.names == (shuffled if order == "state" else names)
            np.testing.assert_array_equal(b.efforts, a.efforts * [scale[n] for n in a.names])
            assert bits(b.action) == bits(a.action) and (b.info is None) == deterministic
            if b.info is not None:  # policy_info stays in the policy's units
                assert bits(b.info["positions"]) == bits(a.info["positions"])


@pytest.mark.parametrize("limit", [None, 0, -3, "nan", "inf", "heavy"])
def test_urdf_units_refuse_a_description_without_a_usable_limit(limit):
    c = Controller(NumpyPolicy(SWIMMER), effort_units="urdf")
    with pytest.raises(JointMapError) as refused:
        c.state(state(1), 0.0)  # no description: nothing to scale by
    assert refused.value.code == NO_EFFORT_LIMITS and "robot_description" in str(refused.value)
    offer = c.description(limited_urdf([1.0, limit, 2.0]))
    assert offer.outcome == "rejected" and offer.code == EFFORT_LIMIT and "'motor2_rot'" in offer.reason
    assert c.descriptions.is_fallback
    good = limited_urdf([1.0, 1.0, 2.0])
    assert c.description(good).outcome == "adopted"
    assert c.description(limited_urdf([1.0, limit, 2.0])).outcome == "rejected"  # the good one kept
    assert len(c.state(state(2), 0.0)) == 1
    # Normalized units take the same description: the limits are not read.
    assert Controller(effort_units="normalized").description(limited_urdf([1.0, limit, 2.0])).outcome == "adopted"


def test_effort_units_and_order_are_checked():
    for bad in ("URDF", "", None, 3):
        with pytest.raises(EffortOrderError, match="effort_units must be one of normalized, urdf"):
            Controller(effort_units=bad)
        with pytest.raises(EffortOrderError, match="effort_order must be one of state, description"):
            Controller(effort_order=bad)


def _rss_kb() -> int:
    with open(f"/proc/{os.getpid()}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))


def _measured(fuzz, warmup: int) -> tuple[int, int, float]:
    """``fuzz(n, stamp) -> stamp`` run ``warmup`` times (caches and allocator pools grown), then ``FUZZ_COUNT``
    times: RSS before and after the measured part [kB], and its seconds."""
    stamp = fuzz(warmup, 0)
    before, t0 = _rss_kb(), time.monotonic()
    fuzz(FUZZ_COUNT, stamp)
    return before, _rss_kb(), time.monotonic() - t0


FUZZ_COUNT = int(os.environ.get("FUZZ_COUNT", "2000"))
"""descriptions fuzzed (2,000 in CI; ``scripts/fuzz_nodes.sh`` runs 10,000)"""


@pytest.mark.slow
def test_urdf_units_under_fuzzed_descriptions_and_states():
    """``FUZZ_COUNT`` descriptions with damaged limits, each with states: every one adopted or refused
    with a reason (a limit that is a number > 0 everywhere, or not), every state answered in the right units or
    refused by code, no other exception, RSS flat."""
    rng = random.Random(3)
    choices = [None, "0", "-1", "nan", "inf", "-inf", "1e400", "1e-300", "abc", "", " 2 ", "0x10", "1_0", "٣",
               "3" * 5000, "7.5", "120", "0.001"]  # fmt: skip
    c = Controller(NumpyPolicy(SWIMMER), deterministic=False, effort_units="urdf")
    c.odometry(odometry(0, 0.1))
    counts = {"adopted": 0, "rejected": 0, "unchanged": 0, "answered": 0, "refused": 0}

    def fuzz(count: int, stamp: int) -> int:
        for _ in range(count):
            limits = [rng.choice(choices) for _ in range(3)]
            offer = c.description(limited_urdf(limits))
            counts[offer.outcome] += 1
            usable = all(_usable(x) for x in limits)
            assert (offer.outcome != "rejected") == usable, (limits, offer)
            if offer.outcome == "rejected":
                assert offer.code == EFFORT_LIMIT and offer.reason.startswith("effort_units:=urdf and joint")
            for _ in range(2):
                stamp += 1
                c.odometry(odometry(stamp, 0.1))
                try:
                    (ready,) = c.state(state(stamp), 0.0)
                except JointMapError as err:
                    assert err.code == NO_EFFORT_LIMITS
                    counts["refused"] += 1
                    continue
                answer = c.answer(ready)
                robot = c.descriptions.map.robot
                assert effort_limit_error(robot) is None
                scale = np.array([robot.effort_limits[n] for n in answer.names])
                assert bits(answer.efforts) == bits(np.clip(answer.action, -1, 1) * scale)
                counts["answered"] += 1
        return stamp

    before, after, elapsed = _measured(fuzz, 500)
    print(f"effort_units:=urdf fuzz: {FUZZ_COUNT} descriptions (+500 warm-up), {counts}, {elapsed:.1f} s, "
          f"RSS {before / 1024:.1f} -> {after / 1024:.1f} MB")  # fmt: skip
    assert counts["adopted"] > 100 and counts["rejected"] > FUZZ_COUNT // 2 and counts["refused"] > 0
    assert after - before < 20_000, (before, after)


def _usable(text) -> bool:
    if text is None:
        return False
    try:
        value = float(text)
    except ValueError:
        return False
    return math.isfinite(value) and value > 0


def test_a_state_the_controller_cannot_read_raises_by_kind():
    c = Controller(NumpyPolicy(SWIMMER))
    with pytest.raises(JointStateError):
        c.state(state(1, names=("a", "a", "b")), 0.0)
    with pytest.raises(JointStateError):
        c.odometry(OdometryRecord(0, 1, 0.0, 0.0, (0.0, 0.0, 0.0, 0.0), (0.0, 0.0), 0.0))
    assert c.odom is None


def test_a_policy_whose_inputs_no_controller_builds_is_refused_with_its_reason():
    # A node refuses such a checkpoint (or pushed weights) in one line rather than failing at its first state.
    assert policy_error(PolicyConfig()) is None and policy_error(PolicyConfig(global_features=12)) is None
    assert "reads 7 global features; a controller builds 4 or 12" in policy_error(PolicyConfig(global_features=7))
    assert policy_error(PolicyConfig(global_features=12, joint_features=11)) is None  # built off robot_description
    other = policy_error(types.SimpleNamespace(global_features=12, joint_features=5))  # a config from elsewhere
    assert other == (
        "reads 5 description features per joint; a controller builds 11 from robot_description "
        "(policy.joint_description) or none"
    )


# -- joint descriptions read off robot_description -------------------------------------------------------------
def _legged_urdf(scale: float = 1.0) -> str:
    """A two-pair centipede's URDF (``env.urdf.robot_urdf``, the sim node's), every length times ``scale``."""
    robot = ET.fromstring(robot_urdf(centipede_model(2)))
    if scale != 1.0:
        for origin in robot.iter("origin"):
            origin.set("xyz", " ".join(repr(float(v) * scale) for v in origin.get("xyz", "0 0 0").split()))
    return ET.tostring(robot, encoding="unicode")


def _legged_state(stamp: int, names: tuple[str, ...]) -> JointStateRecord:
    n = len(names)
    return JointStateRecord(0, stamp, names, np.linspace(-0.3, 0.3, n), np.full(n, 0.2), np.empty(0))


def legged_odometry(stamp: int) -> OdometryRecord:
    return OdometryRecord(0, stamp, 0.1, 0.0, (0.0, 0.0, 0.0, 1.0), (0.2, 0.0), 0.0, 0.55, 0.0, (0.0, 0.0))


def test_a_policy_reading_descriptions_waits_for_one_and_keeps_the_last_good_one():
    """No chain fallback: a state before any description is refused (``NO_DESCRIPTION``); a description whose joint
    descriptions cannot be built (a body of 0.1 mm) is a counted refusal (``JOINT_DESCRIPTION``), waiting goes on,
    and once one is adopted a bad one leaves it in force; the answers read its vectors (``urdf_descriptions``)."""
    good, tiny = _legged_urdf(), _legged_urdf(1e-4)
    names = KinematicTree.from_urdf(good).names
    policy = NumpyPolicy(DESCRIBED)
    c = Controller(policy)
    assert c.joint_features == NUM_DESCRIPTION_FEATURES
    c.odometry(legged_odometry(1))
    with pytest.raises(JointMapError) as refused:
        c.state(_legged_state(1, names), 0.0)
    assert refused.value.code == NO_DESCRIPTION
    offer = c.description(tiny)
    assert (offer.outcome, offer.code) == ("rejected", JOINT_DESCRIPTION) and "outside 0.001..1000 m" in offer.reason
    assert c.descriptions.rejected == 1 and c.descriptions.is_fallback
    with pytest.raises(JointMapError, match="waiting for one"):
        c.state(_legged_state(1, names), 0.0)

    assert c.description(good).outcome == "adopted"
    first = c.answer(*c.state(_legged_state(1, names), 0.0))
    want = urdf_descriptions(good)
    assert bits(first.observation.joint_desc) == bits(want)
    s = _legged_state(1, names)
    direct = policy.mean(s.position, s.velocity, first.observation.global_feats, first.observation.parents, want)
    assert bits(first.action) == bits(direct.astype(np.float64))  # the vectors reach the policy, in tree order

    assert c.description(tiny).code == JOINT_DESCRIPTION and c.descriptions.rejected == 2
    c.odometry(legged_odometry(2))
    again = c.answer(*c.state(_legged_state(2, names), 0.0))
    assert bits(again.observation.joint_desc) == bits(want)  # the last good description still answers

    # A policy that reads none: the same body description is adopted as before, and no vector is built.
    plain = Controller(NumpyPolicy(LEGGED))
    assert plain.joint_features == 0 and plain.description(tiny).outcome == "adopted"
    plain.odometry(legged_odometry(1))
    assert plain.answer(*plain.state(_legged_state(1, names), 0.0)).observation.joint_desc is None


_GARBAGE = ("nan", "inf", "-inf", "1e400", "0", "-1", "", "abc", "1e-300", "1 2", "1e12")


def _garbled(text: str, rng: random.Random) -> str:
    """A description with one to three numbers replaced by garbage, scaled wildly, or an element taken out."""
    robot = ET.fromstring(text)
    for _ in range(rng.randrange(1, 4)):
        e = rng.choice([e for e in robot.iter() if e.attrib])
        attribute = rng.choice(sorted(e.attrib))
        op = rng.randrange(4)
        if op == 0:
            e.set(attribute, rng.choice(_GARBAGE))
        elif op == 1:
            with contextlib.suppress(ValueError):
                e.set(
                    attribute, " ".join(repr(float(v) * 10.0 ** rng.uniform(-9, 9)) for v in e.get(attribute).split())
                )
        elif op == 2:
            del e.attrib[attribute]
        else:
            parent = rng.choice([p for p in robot.iter() if len(p)])
            parent.remove(rng.choice(list(parent)))
    return ET.tostring(robot, encoding="unicode")


@pytest.mark.slow
def test_joint_descriptions_under_fuzzed_descriptions_and_states():
    """``FUZZ_COUNT`` garbled descriptions, each with states: every one adopted, unchanged or refused with a code,
    every answer finite and read on the vectors of the description in force, no other exception, RSS flat."""
    rng = random.Random(51)
    good = _legged_urdf()
    names = KinematicTree.from_urdf(good).names
    c = Controller(NumpyPolicy(DESCRIBED), deterministic=False)
    counts = {"adopted": 0, "rejected": 0, "unchanged": 0, "answered": 0, "refused": 0}
    current = None

    def fuzz(count: int, stamp: int) -> int:
        nonlocal current
        for i in range(count):
            text = good if i % 10 == 0 else _garbled(good, rng)  # the good one now and then: back to a robot
            offer = c.description(text)
            counts[offer.outcome] += 1
            if offer.outcome == "rejected":
                assert offer.code in (DESCRIPTION, JOINT_DESCRIPTION) and offer.reason and "\n" not in offer.reason
            elif offer.outcome == "adopted":
                current = text
            for _ in range(2):
                stamp += 1
                c.odometry(legged_odometry(stamp))
                try:
                    (ready,) = c.state(_legged_state(stamp, names), 0.0)
                except JointMapError as err:
                    assert err.code in ("unknown_joint", "missing_joint", PREVIOUS_DESCRIPTION, NO_DESCRIPTION)
                    counts["refused"] += 1
                    continue
                answer = c.answer(ready)
                assert np.isfinite(answer.efforts).all() and np.isfinite(answer.observation.joint_desc).all()
                assert bits(answer.observation.joint_desc) == bits(urdf_descriptions(current))
                counts["answered"] += 1
        return stamp

    before, after, elapsed = _measured(fuzz, 300)
    print(f"joint descriptions fuzz: {FUZZ_COUNT} descriptions (+300 warm-up), {counts}, {elapsed:.1f} s, "
          f"RSS {before / 1024:.1f} -> {after / 1024:.1f} MB")  # fmt: skip
    assert counts["adopted"] > 100 and counts["rejected"] > FUZZ_COUNT // 4 and counts["answered"] > FUZZ_COUNT
    assert c.descriptions.rejected == counts["rejected"]
    assert after - before < 20_000, (before, after)


def test_weights_that_begin_to_read_descriptions_build_them_from_the_description_in_force():
    """A node's policy replaced (a checkpoint parameter, pushed weights) by one that reads descriptions: the current
    description's vectors are built then; if they cannot be, its states are refused (``JOINT_DESCRIPTION``) until a
    good description comes; a state read for the other policy is not answered with the wrong inputs."""
    good, tiny = _legged_urdf(), _legged_urdf(1e-4)
    names = KinematicTree.from_urdf(good).names
    c = Controller(NumpyPolicy(LEGGED))
    assert c.description(good).outcome == "adopted"
    c.odometry(legged_odometry(1))
    (pending,) = c.state(_legged_state(1, names), 0.0)  # read for a policy without descriptions
    c.policy = NumpyPolicy(DESCRIBED)
    with pytest.raises(PolicyOutputError):
        c.answer(pending)
    c.odometry(legged_odometry(2))
    answer = c.answer(*c.state(_legged_state(2, names), 0.0))
    assert bits(answer.observation.joint_desc) == bits(urdf_descriptions(good))

    c = Controller(NumpyPolicy(LEGGED))
    assert c.description(tiny).outcome == "adopted"  # nothing reads descriptions yet
    c.policy = NumpyPolicy(DESCRIBED)
    c.odometry(legged_odometry(1))
    with pytest.raises(JointMapError) as refused:
        c.state(_legged_state(1, names), 0.0)
    assert refused.value.code == JOINT_DESCRIPTION and "outside 0.001..1000 m" in str(refused.value)
    assert c.description(good).outcome == "adopted"
    c.odometry(legged_odometry(2))
    assert c.answer(*c.state(_legged_state(2, names), 0.0)).observation.joint_desc is not None
