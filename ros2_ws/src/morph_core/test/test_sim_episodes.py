"""SwimmerSim episodes: a run replays exactly in a fresh MorphSwimmerEnv reset at the same boundaries.

The rule a recording is replayed by: ``env = MorphSwimmerEnv(num_joints)``
(``MorphSwimmerEnv(bodies=spec)`` for a sim of a body spec),
``env.reset(seed=seed)`` for the first episode, ``env.reset()`` for each next
one (``env.reset(options={"num_joints": n})`` after a rebuild to n), the
recorded efforts stepped in between.
"""

import numpy as np
import pytest

from morph_core.env.bodies import parse_bodies, star_parents, swimmer_tree
from morph_core.env.sim import SwimmerSim
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.msgs.episode_start import EpisodeCause

PERIOD_NS = 40_000_000


def _snapshot(sim: SwimmerSim) -> dict:
    t = sim.torso()
    return {
        "stamp_ns": sim.stamp_ns,
        "episode": sim.episode,
        "cause": sim.episode_cause,
        "start_ns": sim.episode_start_ns,
        "qpos": np.concatenate([[t.x, t.y, t.yaw], sim.joint_positions]),
        "qvel": np.concatenate([[t.vx, t.vy, t.yaw_rate], sim.joint_velocities]),
        "applied": sim.applied.copy(),
        "tree": sim.tree,
    }


def _run(sim: SwimmerSim, steps: int, rng, resets_at=(), rebuilds=None):
    """Drive the sim like a node: a command for every state, then advance. Returns the states and, per
    transition, ("step", efforts) or ("reset", options)."""
    rebuilds = rebuilds or {}
    states, events = [_snapshot(sim)], []
    for k in range(steps):
        if k in resets_at:
            sim.reset()
            events.append(("reset", None))
            states.append(_snapshot(sim))
        if k in rebuilds:
            sim.rebuild(rebuilds[k])
            events.append(("reset", {"num_joints": rebuilds[k]}))
            states.append(_snapshot(sim))
        a = rng.uniform(-1, 1, sim.num_joints)
        sim.command(a, now=k)
        if sim.advance(now=k):
            events.append(("reset", None))  # the command answered the episode's last state: never applied
        else:
            events.append(("step", a))
        states.append(_snapshot(sim))
    return states, events


def _replay(num_joints, seed, states, events, bodies=None):
    env = MorphSwimmerEnv(num_joints=num_joints, bodies=bodies)
    env.reset(seed=seed)
    _assert_state(env, states[0], np.zeros(env.num_joints))
    for (kind, arg), state in zip(events, states[1:], strict=True):
        if kind == "step":
            env.step(arg)
            applied = arg
        else:
            env.reset(options=arg)
            applied = np.zeros(env.num_joints)
        _assert_state(env, state, applied)


def _assert_state(env: MorphSwimmerEnv, state: dict, applied) -> None:
    assert env.tree == state["tree"]  # the same body: names, shape and order
    np.testing.assert_array_equal(env.data.qpos, state["qpos"])
    np.testing.assert_array_equal(env.data.qvel, state["qvel"])
    np.testing.assert_array_equal(applied, state["applied"])


@pytest.mark.parametrize("num_joints", [4, (2, 9)])
def test_episodes_replay_in_a_fresh_env(num_joints):
    sim = SwimmerSim(num_joints=num_joints, seed=11, effort_timeout=None, episode_steps=7)
    states, events = _run(sim, 90, np.random.default_rng(0), resets_at={30})
    _replay(num_joints, 11, states, events)

    lengths = [len(s["qpos"]) - 3 for s in states]
    lo, hi = (num_joints, num_joints) if isinstance(num_joints, int) else num_joints
    assert lo <= min(lengths) and max(lengths) <= hi
    if lo < hi:
        assert len(set(lengths)) >= 4  # redrawn: several lengths over the episodes
    # Every episode runs 7 steps except the one cut short by reset(); a new episode begins with 0 efforts.
    firsts = [i for i in range(1, len(states)) if states[i]["episode"] != states[i - 1]["episode"]]
    assert len(firsts) == sim.episode
    causes = [states[i]["cause"] for i in firsts]
    assert causes.count(EpisodeCause.RESET) == 1 and set(causes) == {EpisodeCause.STEPS, EpisodeCause.RESET}
    for i, j in zip([0, *firsts], firsts, strict=False):
        assert j - i == 8 or states[j]["cause"] is EpisodeCause.RESET  # 7 steps, then the next first state
    # The clock: one period per state, resets included; each episode starts at its first state's stamp.
    stamps = np.array([s["stamp_ns"] for s in states])
    np.testing.assert_array_equal(np.diff(stamps), PERIOD_NS)
    for i in firsts:
        assert states[i]["start_ns"] == states[i]["stamp_ns"]


@pytest.mark.parametrize("spec", ["y:2x2", "y:1-2x1-2,star:2-3x1,comb:3-4", "2-6,random:3-10"])
def test_bodies_drawn_per_episode_replay_in_a_fresh_env_of_the_spec(spec):
    sim = SwimmerSim(bodies=spec, seed=11, effort_timeout=None, episode_steps=5)
    states, events = _run(sim, 90, np.random.default_rng(0), resets_at={30})
    _replay(None, 11, states, events, bodies=spec)

    bodies = parse_bodies(spec)
    trees = [s["tree"] for s in states]
    assert sim.bodies == bodies and sim.joint_range == bodies.joint_range
    assert all(t.names == tuple(f"motor{k}_rot" for k in range(1, t.num_joints + 1)) for t in trees)
    assert all(len(s["qpos"]) - 3 == t.num_joints for s, t in zip(states, trees, strict=True))
    shapes = {t.parents.tobytes() for t in trees}
    if bodies.members() is not None and len(bodies.members()) == 1:
        assert shapes == {bodies.first().parents.tobytes()}
    else:
        assert len(shapes) >= 4 and not all(t.is_chain for t in trees)  # redrawn, trees among them
    # A body changes only where an episode begins.
    for before, after in zip(states, states[1:], strict=False):
        if after["episode"] == before["episode"]:
            assert after["tree"] is before["tree"]


def test_a_spec_of_chains_is_the_chain_range_bit_for_bit():
    by_range = SwimmerSim(num_joints=(2, 9), seed=4, effort_timeout=None, episode_steps=6)
    by_spec = SwimmerSim(bodies="2-9", seed=4, effort_timeout=None, episode_steps=6)
    a, _ = _run(by_range, 60, np.random.default_rng(2))
    b, _ = _run(by_spec, 60, np.random.default_rng(2))
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x["qpos"], y["qpos"])
        np.testing.assert_array_equal(x["qvel"], y["qvel"])


def test_a_spec_refuses_a_rebuild():
    sim = SwimmerSim(bodies="y:2x2", seed=0)
    with pytest.raises(ValueError, match="drawn from 'y:2x2'.*cannot be rebuilt"):
        sim.rebuild(4)
    assert sim.episode == 0 and sim.num_joints == 6


def test_a_different_seed_or_no_redraw_would_not_replay():
    """The replay check can fail: the same efforts in an env seeded differently give other states."""
    sim = SwimmerSim(num_joints=(2, 9), seed=11, effort_timeout=None, episode_steps=5)
    states, events = _run(sim, 20, np.random.default_rng(0))
    with pytest.raises(AssertionError):
        _replay((2, 9), 12, states, events)


def test_rebuild_in_a_range_lasts_one_episode_and_in_a_fixed_chain_for_good():
    rng = np.random.default_rng(1)
    ranged = SwimmerSim(num_joints=(2, 5), seed=3, effort_timeout=None, episode_steps=4)
    states, events = _run(ranged, 40, rng, rebuilds={6: 20})
    _replay((2, 5), 3, states, events)
    lengths = [len(s["qpos"]) - 3 for s in states]
    assert 20 in lengths and max(lengths[lengths.index(20) + 6 :]) <= 5  # back in the range after it

    fixed = SwimmerSim(num_joints=3, seed=3, effort_timeout=None, episode_steps=4)
    states, events = _run(fixed, 40, rng, rebuilds={6: 7})
    lengths = [len(s["qpos"]) - 3 for s in states]
    assert set(lengths[lengths.index(7) :]) == {7}
    assert fixed.joint_range == (7, 7)
    # The replay passes the new length on every later reset, as the sim does for a fixed chain.
    env = MorphSwimmerEnv(num_joints=3)
    env.reset(seed=3)
    n = 3
    for (kind, arg), state in zip(events, states[1:], strict=True):
        if kind == "step":
            env.step(arg)
        else:
            n = arg["num_joints"] if arg else n
            env.reset(options={"num_joints": n})
        np.testing.assert_array_equal(env.data.qpos, state["qpos"])


def test_episode_steps_zero_never_resets():
    sim = SwimmerSim(num_joints=3, seed=0, effort_timeout=None)
    assert not any(sim.advance(now=k) for k in range(200))
    assert sim.episode == 0 and sim.episode_step == 200 and sim.episode_cause is EpisodeCause.START


def test_changing_episode_steps_ends_a_long_episode_at_the_next_advance():
    sim = SwimmerSim(num_joints=3, seed=0, effort_timeout=None)
    for k in range(10):
        sim.advance(now=k)
    sim.episode_steps = 4
    assert sim.episode_over
    assert sim.advance(now=10) and sim.episode == 1 and sim.episode_cause is EpisodeCause.STEPS


@pytest.mark.parametrize("bad", [-1, 2.5, True, "3"])
def test_bad_episode_steps_are_refused(bad):
    with pytest.raises(ValueError, match="episode_steps"):
        SwimmerSim(num_joints=3, episode_steps=bad)


def test_reset_drops_the_held_efforts():
    sim = SwimmerSim(num_joints=3, seed=0, effort_timeout=None)
    sim.command([1.0, 1.0, 1.0], now=0)
    sim.reset()
    sim.step(now=0)
    assert sim.timed_out and sim.applied.tolist() == [0.0, 0.0, 0.0]


def test_diverged_physics_starts_a_new_episode_the_env_would_start():
    """64 joints driven bang-bang from rest diverge on the first step (MuJoCo's bad-acceleration
    warning): the env ends the episode (terminated), the sim begins the next one in its place."""
    sim = SwimmerSim(num_joints=64, seed=0, effort_timeout=None)
    env = MorphSwimmerEnv(num_joints=64)
    env.reset(seed=0)
    a = np.sign(np.random.default_rng(0).uniform(-1, 1, 64))
    sim.command(a, now=0)
    assert not sim.step(now=0)
    _, _, terminated, _, _ = env.step(a)
    assert terminated
    env.reset()
    assert sim.episode == 1 and sim.episode_cause is EpisodeCause.DIVERGED and sim.unstable_resets == 1
    assert sim.stamp_ns == PERIOD_NS == sim.episode_start_ns  # in place of the diverged state
    np.testing.assert_array_equal(sim.joint_positions, env.data.qpos[3:])
    np.testing.assert_array_equal(sim.torso().yaw, env.data.qpos[2])


def test_a_tree_rebuilt_in_a_fixed_sim_stays_through_resets_as_the_env_draws_it():
    tree = swimmer_tree(star_parents(3, 2))
    sim = SwimmerSim(4, seed=9, effort_timeout=None)
    sim.rebuild(tree)
    env = MorphSwimmerEnv(num_joints=4)
    env.reset(seed=9)
    env.reset(options={"tree": tree})
    for _ in range(3):
        assert sim.tree.parents.tolist() == tree.parents.tolist() and sim.joint_range == (6, 6)
        np.testing.assert_array_equal(sim.joint_positions, env.data.qpos[3:])
        sim.reset()
        env.reset(options={"tree": tree})
    sim.rebuild(5)  # back to a chain: its length from now on
    sim.reset()
    assert sim.tree.is_chain and sim.num_joints == 5
