"""``mjcf:PATH`` bodies: a user's MJCF under the legged task (free root) or the swimmer's (planar root), the same
physics as the project's own Ant and swimmer, the sim node's refusals, vectorised and restored exactly."""

from __future__ import annotations

import os
import random

import gymnasium
import numpy as np
import pytest

from morph_core.env.bodies import is_walker, parse_bodies
from morph_core.env.centipede import MorphCentipedeEnv
from morph_core.env.mjcf_body import MjcfBody
from morph_core.env.mjcf_robot import RobotModelError
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.env.urdf import swimmer_urdf
from morph_core.env.vec_env import SwimmerVecEnv

ASSETS = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets")
ANT, SWIMMER = os.path.join(ASSETS, "ant.xml"), os.path.join(ASSETS, "swimmer.xml")


def test_the_spec_reads_a_walker_and_a_swimmer():
    ant, swimmer = parse_bodies(f"mjcf:{ANT}"), parse_bodies(f"mjcf:{SWIMMER}")
    assert ant.has_walkers and ant.global_features == 12 and ant.joint_range == (8, 8)
    assert swimmer.swimmers_only and swimmer.global_features == 4 and swimmer.joint_range == (2, 2)
    (body,) = ant.members()
    assert body == MjcfBody(ANT) and body.label == "mjcf-ant" and is_walker(body) and body.task == "walker"
    assert str(ant) == f"mjcf:{ANT}"
    assert body.healthy_z_range == pytest.approx((0.2, 1.0), abs=2e-3)  # Ant-v5's, from its standing height


def test_gymnasiums_ant_as_mjcf_steps_as_the_ant_layout():
    a = MorphCentipedeEnv(body=MjcfBody(ANT))
    b = MorphCentipedeEnv(layout="ant")
    oa, _ = a.reset(seed=4)
    ob, _ = b.reset(seed=4)
    rng = np.random.default_rng(0)
    for _ in range(60):
        act = rng.uniform(-1, 1, 8)
        oa, ra, ta, _, _ = a.step(act)
        ob, rb, tb, _, _ = b.step(act)
        np.testing.assert_array_equal(oa["joint_pos"], ob["joint_pos"])
        assert ra == pytest.approx(rb, abs=1e-9) and ta == tb
        if ta:
            break


def test_gymnasiums_swimmer_as_mjcf_swims_as_the_two_joint_chain():
    a, b = MorphSwimmerEnv(), MorphSwimmerEnv(num_joints=2)
    oa, _ = a.reset(seed=2, options={"body": MjcfBody(SWIMMER)})
    ob, _ = b.reset(seed=2)
    assert a.body_label == "mjcf-swimmer" and a.num_joints == 2
    rng = np.random.default_rng(1)
    for _ in range(50):
        act = rng.uniform(-1, 1, 2)
        oa, ra, *_ = a.step(act)
        ob, rb, *_ = b.step(act)
        np.testing.assert_array_equal(oa["joint_pos"], ob["joint_pos"])
        np.testing.assert_array_equal(oa["global"], ob["global"])
        assert ra == rb


def _write(tmp_path, name: str, text: str) -> str:
    path = tmp_path / name
    path.write_text(text)
    return str(path)


ARM = """<mujoco model="arm"><worldbody><body name="base"><geom size="0.1"/>
<body name="link"><joint name="j" type="hinge" axis="0 0 1"/><geom size="0.05" fromto="0 0 0 0.3 0 0" type="capsule"/>
</body></body></worldbody><actuator><motor joint="j"/></actuator></mujoco>"""


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda t: str(t / "missing.xml"), "no such file"),
        (lambda t: _write(t, "r.urdf", swimmer_urdf(2)), "a URDF"),
        (lambda t: _write(t, "bad.xml", "<mujoco><worldbody>"), "malformed XML"),
        (lambda t: _write(t, "arm.xml", ARM), "neither a free joint"),
    ],
)
def test_bad_files_are_refused_in_one_line(tmp_path, make, match):
    mix = parse_bodies(f"mjcf:{make(tmp_path)}")  # the file is read when first needed
    with pytest.raises(RobotModelError, match=match) as err:
        SwimmerVecEnv(2, mix, seed=0)
    assert "\n" not in str(err.value)


def test_garbled_paths_are_refused_or_read():
    rng = random.Random(52)
    for _ in range(200):
        path = "".join(rng.choice("ab/.:\\x -_~*?\0\n") for _ in range(rng.randrange(0, 30)))
        try:
            mix = parse_bodies(f"mjcf:{path}")
            _ = mix.has_walkers  # loads the file
        except ValueError as err:  # RobotModelError is one
            assert str(err)
        else:
            raise AssertionError(f"{path!r} was read")


@pytest.mark.parametrize("spec", [f"mjcf:{ANT},centipede:2", f"mjcf:{SWIMMER},3"])
def test_mjcf_bodies_step_vectorised_and_restore_exactly(spec):
    env = SwimmerVecEnv(3, spec, seed=1)
    rng = np.random.default_rng(0)
    for _ in range(30):
        env.step(rng.uniform(-1, 1, (3, env.max_joints)).astype(np.float32))
    meta, arrays = env.get_state()
    other = SwimmerVecEnv(3, spec, seed=7)
    other.set_state(meta, arrays)
    act = rng.uniform(-1, 1, (3, env.max_joints)).astype(np.float32)
    a, b = env.step(act), other.step(act)
    assert np.array_equal(a.obs.joint_pos, b.obs.joint_pos) and np.array_equal(a.reward, b.reward)


def test_walkers_take_the_legged_ppo_settings_unless_given_and_swimmers_keep_theirs():
    # The legged family and a free-rooted MJCF learn with the centipede results' settings, as centipedes do;
    # a planar MJCF is a swimmer and keeps the paper's.
    from morph_core.algo.ppo_config import LEGGED_DEFAULTS, family_defaults

    for walkers in ("legged:4-6x2", f"mjcf:{ANT}", "centipede:2-3", f"2-4,mjcf:{ANT}"):
        assert family_defaults(walkers, set()) == LEGGED_DEFAULTS, walkers
        assert "learning_rate" not in family_defaults(walkers, {"learning_rate"}), walkers
    for swimmers in ("", "2-10", f"mjcf:{SWIMMER}", "y:2x2"):
        assert family_defaults(swimmers, set()) == {}, swimmers
