"""Joint descriptions: the same numbers from a URDF and from the compiled model it describes, sensible values,
refusals and documented defaults for bad descriptions, and a fuzz of garbled ones (never NaN)."""

from __future__ import annotations

import os
import random
import xml.etree.ElementTree as ET

import gymnasium
import mujoco
import numpy as np
import pytest

from morph_core.env.centipede_model import ant_model, centipede_model
from morph_core.env.model import swimmer_model
from morph_core.env.sim import SwimmerSim
from morph_core.env.urdf import robot_urdf, swimmer_urdf
from morph_core.policy.joint_description import (
    NUM_DESCRIPTION_FEATURES,
    mujoco_descriptions,
    urdf_descriptions,
)
from morph_core.policy.tree import KinematicTree, TreeError

ANT_XML = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets", "ant.xml")
AGREE = 1e-9  # the URDF holds every number as repr of the double; rpy round trips leave ~1e-16


def gymnasium_ant() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(ANT_XML)


def assert_valid(desc: np.ndarray, joints: int) -> None:
    assert desc.shape == (joints, NUM_DESCRIPTION_FEATURES)
    assert np.isfinite(desc).all()
    assert np.allclose(np.linalg.norm(desc[:, 3:6], axis=1), 1.0)
    assert (np.abs(desc[:, :3]) <= 1 + 1e-12).all() and (desc[:, 9] >= 0).all() and (desc[:, 9] <= 1 + 1e-12).all()
    assert (np.abs(desc[:, 6:9]) <= 1).all() and (desc[:, 10] >= 0).all() and (desc[:, 10] <= 1).all()


@pytest.mark.parametrize(
    "name, model",
    [
        ("chain-1", lambda: swimmer_model(np.array([-1]))),
        ("chain-7", lambda: swimmer_model(np.arange(7) - 1)),
        ("y-1x2", lambda: swimmer_model(np.array([-1, 0, 1, 0, 3]))),
        ("star-3x2", lambda: swimmer_model(np.array([-1, 0, -1, 2, -1, 4]))),
        ("centipede-2", lambda: centipede_model(2)),
        ("centipede-7", lambda: centipede_model(7)),
        ("ant (this project's writer)", ant_model),
        ("Ant-v5's ant.xml", gymnasium_ant),
    ],
)
def test_a_urdf_and_its_model_give_the_same_descriptions(name, model):
    m = model()
    want = mujoco_descriptions(m)
    tree = KinematicTree.from_mujoco(m)
    assert_valid(want, tree.num_joints)
    for prefix in ("", "robot1/"):
        text = robot_urdf(m, prefix)
        assert KinematicTree.from_urdf(text).parents.tolist() == tree.parents.tolist()
        np.testing.assert_allclose(urdf_descriptions(text), want, rtol=0, atol=AGREE, err_msg=name)


def test_the_sim_nodes_published_urdf_agrees_with_its_mjcf():
    for bodies in ("star:3x2", "5", "centipede:3"):
        sim = SwimmerSim(bodies=bodies)
        model = sim._env.model  # the model it steps
        np.testing.assert_allclose(urdf_descriptions(sim.urdf("s/")), mujoco_descriptions(model), atol=AGREE)


def test_ant_reads_as_an_ant():
    d = mujoco_descriptions(gymnasium_ant())
    hips, ankles = d[0::2], d[1::2]
    # four hips about z at the torso's four diagonals, ankles across the leg, twice as far out
    np.testing.assert_allclose(np.abs(hips[:, 5]), 1.0)
    np.testing.assert_allclose(ankles[:, 5], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(ankles[:, :3], axis=1), 2 * np.linalg.norm(hips[:, :3], axis=1))
    assert set(np.sign(hips[:, 0] * hips[:, 1]).tolist()) == {-1.0, 1.0}
    np.testing.assert_allclose(hips[:, 7], np.radians(30) / np.pi)  # +-30 degrees
    np.testing.assert_allclose(ankles[:, 9], 2 * hips[:, 9])  # the shin is twice the thigh
    assert (d[:, 8] > 0).all()  # 150 N m lifts a 1 kg ant by far more than its size


def test_size_and_units_do_not_change_a_description():
    """The same ant in millimetres and grams (scaled lengths, masses and torques by consistent units) reads the
    same; a twice-as-large ant with the same proportions too."""
    base = robot_urdf(gymnasium_ant())
    want = urdf_descriptions(base)
    for length, mass in ((2.0, 8.0), (0.5, 0.125)):
        robot = ET.fromstring(base)
        for element in robot.iter():
            for attribute in ("xyz",):
                if attribute in element.attrib and element.tag in ("origin",):
                    element.set(attribute, " ".join(repr(float(x) * length) for x in element.get(attribute).split()))
            if element.tag == "mass":
                element.set("value", repr(float(element.get("value")) * mass))
            if element.tag == "limit":
                element.set("effort", repr(float(element.get("effort")) * mass * length))
        got = urdf_descriptions(ET.tostring(robot, encoding="unicode"))
        np.testing.assert_allclose(got, want, atol=1e-9)


# -- bad input: refusals and documented defaults -----------------------------------------------------------------
def _ant_robot() -> ET.Element:
    return ET.fromstring(robot_urdf(gymnasium_ant()))


def _joint(robot: ET.Element, name: str) -> ET.Element:
    return next(j for j in robot.findall("joint") if j.get("name") == name)


def _read(robot: ET.Element) -> np.ndarray:
    return urdf_descriptions(ET.tostring(robot, encoding="unicode"))


def test_missing_or_empty_limits_give_the_continuous_range_and_an_unknown_effort():
    robot = _ant_robot()
    _joint(robot, "hip_1").remove(_joint(robot, "hip_1").find("limit"))
    limit = _joint(robot, "ankle_1").find("limit")
    limit.set("lower", "0"), limit.set("upper", "0"), limit.set("effort", "0")
    d = _read(robot)
    assert d[0, 6:9].tolist() == [0.0, 1.0, 0.0] and d[1, 6:9].tolist() == [0.0, 1.0, 0.0]
    assert d[2, 7] == pytest.approx(np.radians(30) / np.pi)  # the others untouched


def test_a_joint_without_axis_turns_about_x_and_a_zero_axis_is_refused():
    robot = _ant_robot()
    hip = _joint(robot, "hip_1")
    hip.remove(hip.find("axis"))
    np.testing.assert_allclose(_read(robot)[0, 3:6], [1.0, 0.0, 0.0], atol=1e-12)
    ET.SubElement(hip, "axis", {"xyz": "0 0 0"})
    with pytest.raises(TreeError, match="zero axis"):
        _read(robot)


@pytest.mark.parametrize("value", ["nan 0 0", "0 inf 0", "1e400 0 0", "0 0", "a b c"])
def test_bad_origins_are_refused(value):
    robot = _ant_robot()
    _joint(robot, "ankle_2").find("origin").set("xyz", value)
    with pytest.raises(TreeError) as err:
        _read(robot)
    assert "ankle_2" in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("scale, ok", [(1e-5, False), (100.0, True), (1e4, False)])
def test_absurd_sizes_are_refused(scale, ok):
    robot = _ant_robot()
    for origin in robot.iter("origin"):
        origin.set("xyz", " ".join(repr(float(x) * scale) for x in origin.get("xyz").split()))
    if ok:
        assert np.isfinite(_read(robot)).all()
    else:
        with pytest.raises(TreeError, match="size"):
            _read(robot)


@pytest.mark.parametrize("tag, attribute, value", [("mass", "value", "-1"), ("mass", "value", "nan"),
                                                   ("limit", "effort", "-5"), ("limit", "lower", "nan")])  # fmt: skip
def test_bad_numbers_are_refused(tag, attribute, value):
    robot = _ant_robot()
    next(e for e in robot.iter(tag) if attribute in e.attrib).set(attribute, value)
    with pytest.raises(TreeError):
        _read(robot)


def test_a_body_without_masses_has_unknown_efforts_and_zero_masses():
    robot = _ant_robot()
    for link in robot.findall("link"):
        for inertial in link.findall("inertial"):
            link.remove(inertial)
    d = _read(robot)
    assert (d[:, 8] == 0).all() and (d[:, 10] == 0).all() and np.isfinite(d).all()


# -- fuzz ----------------------------------------------------------------------------------------------------------
_GARBAGE = ["nan", "inf", "-inf", "1e308", "-1e308", "0", "-0", "1e-300", "", " ", "x", "1 2", "1e999", "NaN NaN NaN",
            "0 0 0", "1 1 1 1", "-1", "3.5e38", "0x10"]  # fmt: skip


def _garble(robot: ET.Element, rng: random.Random) -> None:
    elements = [e for e in robot.iter() if e.attrib]
    e = rng.choice(elements)
    attribute = rng.choice(sorted(e.attrib))
    op = rng.randrange(5)
    if op == 0:
        e.set(attribute, rng.choice(_GARBAGE))
    elif op == 1:
        values = e.get(attribute).split()
        e.set(attribute, " ".join(rng.choice([v, rng.choice(_GARBAGE), repr(rng.uniform(-1e6, 1e6))]) for v in values))
    elif op == 2:
        del e.attrib[attribute]
    elif op == 3:  # an element gone
        parents = [p for p in robot.iter() if len(p)]
        p = rng.choice(parents)
        p.remove(rng.choice(list(p)))
    else:  # scaled wildly
        try:
            factor = 10.0 ** rng.uniform(-12, 12)
            e.set(attribute, " ".join(repr(float(v) * factor) for v in e.get(attribute).split()))
        except ValueError:
            pass


@pytest.mark.slow
def test_fuzzed_descriptions_give_finite_vectors_or_a_tree_error():
    rng = random.Random(51)
    bases = [robot_urdf(gymnasium_ant()), robot_urdf(centipede_model(3)), swimmer_urdf(np.array([-1, 0, 1, 0, 3]))]
    outcomes = {"read": 0, "refused": 0}
    for _ in range(1500):
        robot = ET.fromstring(rng.choice(bases))
        for _ in range(rng.randrange(1, 4)):
            _garble(robot, rng)
        text = ET.tostring(robot, encoding="unicode")
        try:
            desc = urdf_descriptions(text)
        except TreeError as err:
            assert str(err) and "\n" not in str(err)
            outcomes["refused"] += 1
            continue
        tree = KinematicTree.from_urdf(text)
        assert desc.shape == (tree.num_joints, NUM_DESCRIPTION_FEATURES)
        assert np.isfinite(desc).all() and (np.abs(desc) <= 1 + 1e-9).all()
        outcomes["read"] += 1
    assert min(outcomes.values()) > 300, outcomes
