"""The variable-chain swimmer: Swimmer-v5 equivalence, chain sampling, bad input."""

import gymnasium
import mujoco
import numpy as np
import pytest

import morph_core.env.registration  # noqa: F401  (registers MorphSwimmer-v0)
from morph_core.constants import MAX_JOINTS
from morph_core.env.model import swimmer_mjcf, swimmer_model


@pytest.mark.parametrize("seed", [0, 123])
def test_two_joints_flat_is_swimmer_v5(seed):
    ref = gymnasium.make("Swimmer-v5")
    env = gymnasium.make("MorphSwimmer-v0", num_joints=2, observation_mode="flat")
    obs_ref, _ = ref.reset(seed=seed)
    obs, _ = env.reset(seed=seed)
    np.testing.assert_allclose(obs, obs_ref, rtol=0, atol=1e-9)
    actions = np.random.default_rng(seed).uniform(-1.5, 1.5, size=(1000, 2))  # beyond ctrlrange too
    for t, a in enumerate(actions):
        o_ref, r_ref, term_ref, trunc_ref, info_ref = ref.step(a)
        o, r, term, trunc, info = env.step(a)
        np.testing.assert_allclose(o, o_ref, rtol=0, atol=1e-9, err_msg=f"step {t}")
        assert abs(r - r_ref) <= 1e-9
        assert abs(info["x_velocity"] - info_ref["x_velocity"]) <= 1e-9
        assert (term, trunc) == (term_ref, trunc_ref)
    assert trunc and trunc_ref  # both end at the 1000-step limit


@pytest.mark.parametrize("n", [1, 2, 7, 20, MAX_JOINTS])
def test_chain_dimensions(n):
    env = gymnasium.make("MorphSwimmer-v0", num_joints=n)
    obs, info = env.reset(seed=0)
    m = env.unwrapped.model
    assert (m.nq, m.nv, m.nu) == (n + 3, n + 3, n)
    assert env.action_space.shape == (n,)
    assert obs["joint_pos"].shape == obs["joint_vel"].shape == (n,)
    assert obs["global"].shape == (4,)
    np.testing.assert_array_equal(obs["parents"], np.arange(n) - 1)  # a chain: joint j hangs off joint j - 1
    assert obs["parents"].dtype == np.int64
    assert info["num_joints"] == n
    obs, *_ = env.step(np.zeros(n))
    assert env.observation_space.contains(obs)
    flat = gymnasium.make("MorphSwimmer-v0", num_joints=n, observation_mode="flat")
    assert flat.reset(seed=0)[0].shape == (2 * n + 4,)


def test_segments_have_swimmer_v5_geometry():
    m = swimmer_model(9)
    # every segment weighs the same as Swimmer-v5's, and the torso frame sits at x = 0
    masses = m.body_mass[1:]
    np.testing.assert_allclose(masses, masses[0])
    np.testing.assert_allclose(m.body_mass[1], swimmer_model(2).body_mass[1])
    np.testing.assert_allclose(m.body_pos[1], 0.0)
    np.testing.assert_allclose(m.jnt_range[3:], np.tile(np.deg2rad([-100.0, 100.0]), (9, 1)))
    np.testing.assert_allclose(m.actuator_gear[:, 0], 150.0)
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4


@pytest.mark.parametrize("n", [2, 9])
def test_collision_detection_off_changes_no_trajectory(n):
    # The flag is only safe while no geom can collide; with detection back on,
    # the same controls must give the same states bit for bit.
    m = swimmer_model(n)
    assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert not m.geom_contype.any() and not m.geom_conaffinity.any()
    on = mujoco.MjModel.from_xml_string(swimmer_mjcf(n))
    on.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    states, limited = [], 0
    for model in (m, on):
        data = mujoco.MjData(model)
        for t in range(2000):
            data.ctrl[:] = np.sin(0.05 * t + np.arange(n))
            mujoco.mj_step(model, data)
            limited += data.nefc > 0
        states.append(np.concatenate([data.qpos, data.qvel]))
    assert limited > 0  # the joint limits were hit: the constraint solver ran with detection on and off
    np.testing.assert_array_equal(states[0], states[1])


def test_models_are_cached_and_built_from_strings():
    assert swimmer_model(5) is swimmer_model(5)
    assert "motor5_rot" in swimmer_mjcf(5) and "motor6_rot" not in swimmer_mjcf(5)


def test_chain_length_drawn_from_range_with_seeded_rng():
    def lengths(seed):
        env = gymnasium.make("MorphSwimmer-v0", num_joints=(2, 10))
        out = [env.reset(seed=seed)[1]["num_joints"]]
        out += [env.reset()[1]["num_joints"] for _ in range(199)]
        return out

    a, b = lengths(7), lengths(7)
    assert a == b  # reproducible from the seed
    assert set(a) == set(range(2, 11))  # every length in 2..10 (inclusive) appears
    assert lengths(8) != a


def test_action_space_follows_chain():
    env = gymnasium.make("MorphSwimmer-v0", num_joints=(3, 4))
    for _ in range(20):
        obs, info = env.reset()
        n = info["num_joints"]
        assert env.action_space.shape == (n,) and obs["joint_pos"].shape == (n,)
        env.step(env.action_space.sample())


def test_reset_option_forces_chain_length():
    env = gymnasium.make("MorphSwimmer-v0", num_joints=(2, 10))
    _, info = env.reset(seed=0, options={"num_joints": 15})
    assert info["num_joints"] == 15 and env.unwrapped.model.nu == 15


def test_travelling_wave_swims_forward():
    # An open-loop travelling wave must move every chain forward: checks the
    # physics (viscous thrust) end to end, not just shapes.
    from morph_core.env.gait import TravellingWave, run_gait

    for n in (2, 5, 10):
        speed = run_gait(n, TravellingWave(), seconds=20.0, seed=0)
        assert speed > 0.02, (n, speed)


@pytest.mark.parametrize(
    "kwargs, error",
    [
        ({"num_joints": 0}, ValueError),
        ({"num_joints": 65}, ValueError),
        ({"num_joints": (5, 3)}, ValueError),
        ({"num_joints": (0, 3)}, ValueError),
        ({"num_joints": 2.5}, TypeError),
        ({"num_joints": "six"}, TypeError),
        ({"observation_mode": "pixels"}, ValueError),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, error):
    from morph_core.env.swimmer_env import MorphSwimmerEnv

    with pytest.raises(error, match="num_joints|observation_mode"):
        MorphSwimmerEnv(**kwargs)


def test_bad_actions_raise_and_leave_state_untouched():
    from morph_core.env.swimmer_env import MorphSwimmerEnv

    env = MorphSwimmerEnv(num_joints=3)
    env.reset(seed=0)
    qpos = env.data.qpos.copy()
    for bad in (np.zeros(2), np.zeros(4), np.zeros((3, 1)), np.array([0.0, np.nan, 0.0]), np.array([np.inf, 0, 0])):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    np.testing.assert_array_equal(env.data.qpos, qpos)


def test_diverging_physics_ends_the_episode_instead_of_silently_resetting():
    from morph_core.env.swimmer_env import MorphSwimmerEnv

    env = MorphSwimmerEnv(num_joints=64)
    env.reset(seed=0)
    # Huge joint speeds make the explicit integrator blow up within a step or two.
    env.data.qvel[3:] = 1e6
    terminated = info = None
    for _ in range(3):
        _, _, terminated, _, info = env.step(np.zeros(64))
        if terminated:
            break
    assert terminated and info["physics_unstable"]


# -- kinematic trees ---------------------------------------------------------------------------------------
TREE_SPECS = ["star:2-4x1-3", "y:1-3x1-3", "comb:3-6"]


def _tree_bodies():
    from morph_core.env.bodies import parse_bodies

    named = [tree for spec in TREE_SPECS for tree in parse_bodies(spec).members()]
    rng = np.random.default_rng(5)
    random = [parse_bodies(f"random:2-20:b{b}").draw(rng) for b in (2, 3) for _ in range(15)]
    return named + random


def test_tree_models_read_back_as_the_tree_they_were_built_from():
    from morph_core.policy.tree import KinematicTree

    for tree in _tree_bodies():
        m = swimmer_model(tree)
        assert KinematicTree.from_mujoco(m) == tree  # joint order = qpos order = the tree's order
        assert swimmer_model(list(tree.parents)) is m  # cached by shape
        n = tree.num_joints
        assert (m.nq, m.nv, m.nu, m.nbody) == (n + 3, n + 3, n, n + 2)
        # Swimmer-v5's torso frame and segments, whatever the shape
        np.testing.assert_allclose(m.body_pos[1], 0.0)
        np.testing.assert_allclose(m.body_mass[2:], swimmer_model(2).body_mass[2])
        np.testing.assert_allclose(m.jnt_range[3:], np.tile(np.deg2rad([-100.0, 100.0]), (n, 1)))
        np.testing.assert_allclose(m.actuator_gear[:, 0], 150.0)
    assert swimmer_model(KinematicTree.chain(6)) is swimmer_model(6)
    assert swimmer_mjcf(KinematicTree.chain(2)) == swimmer_mjcf(2)  # a chain given as a tree is the chain


def test_siblings_rest_in_distinct_directions():
    for tree in _tree_bodies():
        m = swimmer_model(tree)
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)  # qpos0: every hinge at its rest angle
        axes = d.xmat[2:].reshape(-1, 3, 3)[:, :2, 0]  # each segment's x axis in the plane
        for parent in np.unique(tree.parents):
            kids = np.flatnonzero(tree.parents == parent)
            for a in kids:
                for b in kids[kids > a]:
                    assert axes[a] @ axes[b] < np.cos(np.deg2rad(25)), (tree.parents, a, b)
            # no rest direction points forward: within 60 degrees of the parent segment's axis
            parent_axis = np.array([1.0, 0.0]) if parent < 0 else axes[parent]
            assert (axes[kids] @ parent_axis > np.cos(np.deg2rad(60)) - 1e-9).all()


def test_tree_observations_carry_parents_and_info_names_the_body():
    from morph_core.env.bodies import body_label
    from morph_core.env.swimmer_env import MorphSwimmerEnv

    env = MorphSwimmerEnv(bodies="star:3x2,y:1x2,random:4-9:b3")
    seen = set()
    obs, info = env.reset(seed=0)
    for _ in range(30):
        tree, n = env.tree, env.num_joints
        np.testing.assert_array_equal(obs["parents"], tree.parents)
        assert obs["parents"].dtype == np.int64 and obs["joint_pos"].shape == (n,)
        assert not env.parents.flags.writeable
        assert info["body"] == body_label(tree) and info["topology_hash"] == tree.topology_hash
        assert env.observation_space.contains(obs) and env.action_space.shape == (n,)
        obs, _, terminated, _, info = env.step(env.action_space.sample())
        assert not terminated and info["body"] == body_label(tree)
        assert env.observation_space.contains(obs)
        seen.add(info["body"])
        obs, info = env.reset()
    assert {"star-3x2", "y-1x2"} <= seen and any(label.startswith(("tree-", "chain-")) for label in seen)


def test_tree_draws_are_reproducible_from_the_seed():
    from morph_core.env.swimmer_env import MorphSwimmerEnv

    def run(seed):
        env, out = MorphSwimmerEnv(bodies="2-6,random:3-10:b2"), []
        for k in range(15):
            obs, info = env.reset(seed=seed if k == 0 else None)
            obs, *_ = env.step(np.full(env.num_joints, 0.5))
            out.append((info["topology_hash"], obs["joint_pos"].tobytes()))
        return out

    assert run(4) == run(4) != run(5)


def test_reset_options_force_a_tree():
    from morph_core.env.swimmer_env import MorphSwimmerEnv
    from morph_core.policy.tree import KinematicTree

    env = MorphSwimmerEnv(bodies="2-10")
    other = KinematicTree(["a", "b", "c"], [-1, 0, 0], root_link="base")  # names are the swimmer's once built
    _, info = env.reset(seed=0, options={"tree": other})
    assert info["body"] == "y-1x1" and env.tree.names == ("motor1_rot", "motor2_rot", "motor3_rot")
    np.testing.assert_array_equal(env.parents, [-1, 0, 0])
    assert env.tree == KinematicTree.from_mujoco(env.model)
    _, info = env.reset(options={"parents": [-1, -1, 1, 1]})
    assert info["body"] == "tree-" + env.tree.topology_hash[:8] and env.model.nu == 4
    _, info = env.reset(options={"num_joints": 3})
    assert info["body"] == "chain-3"
    with pytest.raises(ValueError, match="pre-order"):
        env.reset(options={"parents": [-1, -1, 0]})  # joint 2 under joint 0 after joint 0's subtree was left
    with pytest.raises(ValueError, match="twice"):
        env.reset(options={"parents": [-1], "num_joints": 1})
    with pytest.raises(TypeError, match="KinematicTree"):
        env.reset(options={"tree": [-1, 0]})


def test_a_fixed_tree_swims_with_a_travelling_wave():
    # Physics end to end on a tree: a wave down every branch moves the swimmer.
    from morph_core.env.bodies import parse_bodies
    from morph_core.env.gait import TravellingWave, run_gait
    from morph_core.env.swimmer_env import MorphSwimmerEnv
    from morph_core.policy.index_plan import joint_depths

    for spec in ("y:2x2", "star:3x2", "comb:4"):
        env = MorphSwimmerEnv(bodies=spec)
        env.reset(seed=0)
        depth = joint_depths(env.parents)
        x0 = env.data.qpos[0]
        for t in range(500):  # 20 s of the travelling wave, by depth
            env.step(TravellingWave()(t * env.dt, env.num_joints, depth))
        speed = (env.data.qpos[0] - x0) / 20.0
        assert speed > 0.05, spec  # 0.08..0.13 m/s (a 3-chain: 0.17)
        assert run_gait(env.tree, TravellingWave(), seconds=20.0, seed=0) == pytest.approx(speed, abs=0.02)
        assert str(parse_bodies(spec)) == spec
