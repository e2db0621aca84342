"""Transitions from records: a real swimmer and a real policy in one process, recorded as the nodes publish.

The reference for every check is a replay: a fresh ``MorphSwimmerEnv`` with the
sim's seed, reset where the recording reset and stepped with the actions the
sim was stepped with. Perturbed recordings (a message dropped, changed,
duplicated, or added) must lose exactly the steps they spoil, each counted
under its reason, and give the rest unchanged.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from morph_core.env.bodies import star_parents, swimmer_tree, y_parents
from morph_core.env.reward import applied_action
from morph_core.env.sim import SwimmerSim
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.env.urdf import swimmer_urdf
from morph_core.msgs.joint_state import quaternion_from_yaw
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    PolicyInfoRecord,
)
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch, chain_batch
from morph_core.protocol.joint_map import JointMap
from morph_core.protocol.loopback import (
    GaussianController,
    LoopbackRecording,
    MeanController,
    SamplingController,
    body_sim,
)
from morph_core.protocol.transition_batch import (
    EXPORT_KEYS,
    MissingPolicyInfoError,
    TransitionBatch,
    TransitionBatchError,
)
from morph_core.protocol.transitions import (
    SkipCounts,
    TransitionAssembler,
    TransitionConfig,
    assemble,
)

SEED = 3
PERIOD_NS = 40_000_000
PER_JOINT = ("joint_pos", "joint_vel", "action", "next_joint_pos", "next_joint_vel")


@pytest.fixture(scope="module")
def policy():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    return GraphActorCritic().eval()


def record(controller, episodes=((3, 30), (5, 25), (5, 20)), seed=SEED, announce=True, same_stamp=False, late=None):
    """Episodes of (chain length, steps) in one lockstep loop; options as in ``LoopbackRecording``."""
    loop = LoopbackRecording(SwimmerSim(episodes[0][0], seed=seed, effort_timeout=None), controller)
    for i, (n, steps) in enumerate(episodes):
        if i:
            loop.new_episode(n, announce=announce, same_stamp=same_stamp)
        loop.run(steps, late=late)
    loop.finish()
    return loop


@pytest.fixture(scope="module")
def sampled(policy):
    return record(SamplingController(policy, seed=1))


def replay_by_order(loop):
    """(stamp, observation, action sampled, reward, next observation) per stepped state, from a fresh env
    with the sim's seed, reset where the recording reset."""
    env = MorphSwimmerEnv(num_joints=loop.truth[0].observation["joint_pos"].size)
    obs, _ = env.reset(seed=SEED)
    episode = 0
    for truth in loop.truth:
        if truth.episode != episode:
            episode = truth.episode
            obs, _ = env.reset(options={"num_joints": truth.observation["joint_pos"].size})
        if truth.action is None:
            continue
        # Stepped as the training loop steps it: with the sample clipped to the motors' range, the action
        # charged (env.reward); the transition keeps the sample itself for its log-prob.
        nxt, reward, _, _, _ = env.step(applied_action(truth.action))
        yield obs, truth.action, reward, nxt
        obs = nxt


def replay(loop):
    """stamp -> (observation, action stepped with, reward, next observation)."""
    stepped = [t.stamp_ns for t in loop.truth if t.action is not None]
    return dict(zip(stepped, replay_by_order(loop), strict=True))


def rows(batch: TransitionBatch) -> dict[int, dict]:
    """stamp -> one transition's arrays, unpadded."""
    a = batch.arrays()
    out = {}
    for i, stamp in enumerate(a["stamp_ns"]):
        n = a["num_joints"][i]
        out[int(stamp)] = {k: (v[i, :n] if k in PER_JOINT else v[i]) for k, v in a.items()}
    return out


def assert_matches_replay(batch, loop, joint_atol=0.0):
    reference = replay(loop)
    for stamp, row in rows(batch).items():
        obs, action, reward, nxt = reference[stamp]
        np.testing.assert_allclose(row["joint_pos"], obs["joint_pos"], rtol=0, atol=joint_atol)
        np.testing.assert_allclose(row["joint_vel"], obs["joint_vel"], rtol=0, atol=joint_atol)
        np.testing.assert_allclose(row["global"], obs["global"], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(row["action"], action)
        assert row["reward"] == pytest.approx(reward, abs=1e-9)
        np.testing.assert_allclose(row["next_joint_pos"], nxt["joint_pos"], rtol=0, atol=joint_atol)
        np.testing.assert_allclose(row["next_global"], nxt["global"], rtol=0, atol=1e-12)
    return reference


def without(records, predicate):
    return [r for r in records if not predicate(r)]


def state_stamps(loop):
    return [t.stamp_ns for t in loop.truth]


# -- the clean recording -----------------------------------------------------------------------


def test_lockstep_recording_gives_the_replayed_transitions(sampled, policy):
    result = assemble(sampled.records)
    batch = result.batch
    assert result.skips == SkipCounts()
    assert result.stats.boundaries_announced == 2 and result.stats.boundaries == 2
    # one run per episode, every stepped state a transition, the last of each truncated
    assert np.bincount(batch.episode).tolist() == [30, 25, 20]
    ends = np.flatnonzero(np.diff(batch.episode)).tolist() + [len(batch) - 1]
    assert np.flatnonzero(batch.truncated).tolist() == ends
    assert not batch.terminated.any()
    assert batch.num_joints.tolist() == [3] * 30 + [5] * 45
    assert batch.ppo_ready
    batch.require_policy_info()

    reference = assert_matches_replay(batch, sampled)
    assert set(reference) == set(batch.stamp_ns.tolist())
    assert (np.abs(batch.action) > 1).any(), "some sampled actions beyond the motors' range (charged unclipped)"
    # padding is zero, next observation is the next row inside a run
    assert not batch.joint_pos[:30, 3:].any() and not batch.action[:30, 3:].any()
    inside = ~batch.truncated
    np.testing.assert_array_equal(batch.next_joint_pos[inside], batch.joint_pos[1:][inside[:-1]])
    np.testing.assert_array_equal(batch.next_global[inside], batch.global_feats[1:][inside[:-1]])

    # log-probs: the ones published, and the policy's own on the replayed observations (float32)
    infos = {r.stamp_ns: r for r in sampled.records if isinstance(r, PolicyInfoRecord)}
    for i, stamp in enumerate(batch.stamp_ns.tolist()):
        assert batch.log_prob[i] == infos[stamp].log_prob
        n = batch.num_joints[i]
        obs = reference[stamp][0]
        lp = policy.log_prob(
            chain_batch(obs["joint_pos"], obs["joint_vel"], obs["global"]),
            torch.as_tensor(batch.action[i, :n], dtype=torch.float32)[None],
        )
        assert lp.item() == pytest.approx(batch.log_prob[i], abs=2e-4)


def test_streaming_gives_the_batch_result_with_bounded_delay(sampled):
    config = TransitionConfig(settle_states=2)
    asm = TransitionAssembler(config)
    released, latest_state = [], None
    for r in sampled.records:
        out = asm.push(r)
        if isinstance(r, JointStateRecord):
            latest_state = r.stamp_ns
        for t in out:
            # released at most settle + 2 periods after its state (judged once settle states follow s')
            assert latest_state - t.stamp_ns <= (config.settle_states + 2) * PERIOD_NS
        released += out
    before_flush = len(released)
    released += asm.flush()
    assert 0 < before_flush < len(released)
    streamed = TransitionBatch.from_transitions(released)
    batch = assemble(sampled.records).batch
    for k, v in batch.arrays().items():
        np.testing.assert_array_equal(streamed.arrays()[k], v, err_msg=k)


# -- episode boundaries ------------------------------------------------------------------------


def test_a_new_chain_is_a_boundary_without_announcement(policy):
    loop = record(SamplingController(policy, seed=2), episodes=((2, 12), (4, 10)), announce=False)
    result = assemble(loop.records)
    assert result.stats.boundaries_new_chain == 1 and result.stats.boundaries_announced == 0
    assert np.bincount(result.batch.episode).tolist() == [12, 10]
    assert_matches_replay(result.batch, loop)


@pytest.mark.parametrize("announce", [True, False])
def test_a_reset_that_keeps_the_stamp_starts_a_new_episode(policy, announce):
    """A sim that rebuilds without stepping its clock publishes the new first state with the last one's stamp;
    the odometry (and announcement) after the old state are the new state's."""
    loop = record(
        SamplingController(policy, seed=9), episodes=((3, 12), (5, 10), (5, 8)), announce=announce, same_stamp=True
    )
    stamps = [t.stamp_ns for t in loop.truth]
    assert len(stamps) - len(set(stamps)) == 2
    result = assemble(loop.records)
    assert result.skips == SkipCounts()
    assert np.bincount(result.batch.episode).tolist() == [12, 10, 8]
    stats = result.stats
    if announce:
        assert stats.boundaries_announced == 2 and stats.boundaries == 2
    else:  # 3 -> 5 joints is a new chain; 5 -> 5 only the repeated stamp tells
        assert stats.boundaries_new_chain == 1 and stats.boundaries_stamp_gap == 1
    # a replay keyed by stamp cannot tell the two states apart: compare episode by episode
    reference = list(replay_by_order(loop))
    assert len(reference) == len(result.batch)
    for i, (obs, action, reward, _) in enumerate(reference):
        np.testing.assert_array_equal(result.batch.joint_pos[i, : len(action)], obs["joint_pos"])
        np.testing.assert_allclose(result.batch.global_feats[i], obs["global"], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(result.batch.action[i, : len(action)], action)
        assert result.batch.reward[i] == pytest.approx(reward, abs=1e-9)


def test_announcement_arriving_after_its_state_still_splits(sampled):
    records = list(sampled.records)
    ann = [i for i, r in enumerate(records) if isinstance(r, EpisodeStartRecord)][1]
    moved = records.pop(ann)
    records.insert(ann + 8, moved)  # after its odometry, state, effort, policy_info and the next state
    result = assemble(records)
    assert result.stats.boundaries_announced == 2
    assert np.bincount(result.batch.episode).tolist() == [30, 25, 20]

    # The reset to the same chain length, announced after the settle window: the announcement is counted
    # as late. Stamps and names cannot tell the step across the reset from a real one; here it is refused
    # only because the rebuilt sim applied zero effort, not the answer to the last state.
    records = list(sampled.records)
    ann = [i for i, r in enumerate(records) if isinstance(r, EpisodeStartRecord)][2]
    records.insert(ann + 4 * 4, records.pop(ann))  # 4 states later
    result = assemble(records, TransitionConfig(settle_states=1))
    assert result.skips.late_message == 1
    assert result.stats.boundaries == 1  # the 3 -> 5 joints reset, announced in time
    assert result.skips.not_applied == 1 and result.skips.steps_skipped == 1
    assert np.bincount(result.batch.episode).tolist() == [30, 25, 20]


def test_a_lost_state_is_a_stamp_gap_and_the_rest_is_unchanged(sampled):
    lost = state_stamps(sampled)[10]
    records = without(sampled.records, lambda r: isinstance(r, JointStateRecord) and r.stamp_ns == lost)
    result = assemble(records)
    assert result.stats.boundaries_stamp_gap == 1 and result.stats.clock_restarts == 0
    # its odometry, effort and policy_info answer no recorded state
    assert (result.skips.orphan_odometry, result.skips.orphan_effort, result.skips.orphan_policy_info) == (1, 1, 1)
    assert result.skips.steps_skipped == 0
    # the steps into and out of the lost state are gone with it
    assert np.bincount(result.batch.episode).tolist() == [9, 19, 25, 20]
    assert_matches_replay(result.batch, sampled)  # the yaw unwrapping carries on across the gap


def test_a_restarted_clock_is_a_boundary(policy):
    first = record(SamplingController(policy, seed=4), episodes=((3, 40),))
    second = record(SamplingController(policy, seed=5), episodes=((3, 6),))
    shift = first.records[-1].log_ns
    records = first.records + [
        dataclasses.replace(r, log_ns=r.log_ns + shift)
        for r in second.records
        if not isinstance(r, EpisodeStartRecord)  # a sim that does not announce
    ]
    result = assemble(records)
    assert result.stats.boundaries_stamp_gap == 1 and result.stats.clock_restarts == 1
    assert np.bincount(result.batch.episode).tolist() == [40, 6]
    assert result.skips == SkipCounts()


def test_stamps_must_be_one_control_period_apart(sampled):
    result = assemble(sampled.records, TransitionConfig(control_period=0.05))
    assert len(result.batch) == 0
    assert result.stats.boundaries_stamp_gap == 75 and result.stats.boundaries_announced == 2


# -- skipped steps, by reason ------------------------------------------------------------------


def _stamp(loop, k):
    return state_stamps(loop)[k]


def _perturb_drop_odometry(loop):
    s = _stamp(loop, 10)
    return without(loop.records, lambda r: isinstance(r, OdometryRecord) and r.stamp_ns == s), {9, 10}


def _perturb_nan_velocity(loop):
    s = _stamp(loop, 10)

    def bad(r):
        if isinstance(r, JointStateRecord) and r.stamp_ns == s:
            v = r.velocity.copy()
            v[1] = math.nan
            return dataclasses.replace(r, velocity=v)
        return r

    return [bad(r) for r in loop.records], {9, 10}


def _perturb_not_applied(loop):
    s = _stamp(loop, 11)  # the state after step 10 says what was applied over it

    def bad(r):
        if isinstance(r, JointStateRecord) and r.stamp_ns == s:
            return dataclasses.replace(r, effort=r.effort + 0.01)
        return r

    return [bad(r) for r in loop.records], {10}


def _perturb_policy_info(field, value):
    def perturb(loop):
        s = _stamp(loop, 10)

        def bad(r):
            if isinstance(r, PolicyInfoRecord) and r.stamp_ns == s:
                return dataclasses.replace(r, **{field: value(r)})
            return r

        return [bad(r) for r in loop.records], {10}

    return perturb


def _perturb_orphan_effort(loop):
    i = next(i for i, r in enumerate(loop.records) if isinstance(r, EffortRecord)) + 5
    never = _stamp(loop, 10) + PERIOD_NS // 2
    e = EffortRecord(loop.records[i].log_ns, never, np.zeros(3))
    return loop.records[:i] + [e] + loop.records[i:], set()


def _perturb_orphan_policy_info(loop):
    i = next(i for i, r in enumerate(loop.records) if isinstance(r, PolicyInfoRecord) and r.stamp_ns == _stamp(loop, 5))
    info = dataclasses.replace(loop.records[i], stamp_ns=_stamp(loop, 5) + 7)
    return loop.records[: i + 1] + [info] + loop.records[i + 1 :], set()


def _perturb_no_answer(loop):
    s = _stamp(loop, 10)

    def answers(r):
        return (isinstance(r, EffortRecord) and r.answers_ns == s) or (
            isinstance(r, PolicyInfoRecord) and r.stamp_ns == s
        )

    return without(loop.records, answers), {10}


def _perturb_resent_state(loop):
    i = next(i for i, r in enumerate(loop.records) if isinstance(r, JointStateRecord) and r.stamp_ns == _stamp(loop, 7))
    return loop.records[: i + 3] + [loop.records[i - 1], loop.records[i]] + loop.records[i + 3 :], set()


def _perturb_conflicting_state(loop):
    """Another state with state 7's stamp and no odometry of its own: taken as a new start (the sim rebuilt
    without its clock moving on) whose observation cannot be told; the steps up to the first 7 stay."""
    i = next(i for i, r in enumerate(loop.records) if isinstance(r, JointStateRecord) and r.stamp_ns == _stamp(loop, 7))
    other = dataclasses.replace(loop.records[i], position=loop.records[i].position + 1e-3)
    return loop.records[: i + 3] + [other] + loop.records[i + 3 :], {7}


def _saturated_step(loop):
    """Index of a stepped state (not an episode's first or last) whose sampled action leaves [-1, 1]."""
    return next(
        k for k, t in enumerate(loop.truth[:29]) if k > 1 and t.action is not None and (np.abs(t.action) > 1).any()
    )


def _second_answer(loop, k, change):
    """The state k re-sent and answered again with another sample (as a lockstep re-send is), changed by
    ``change``; the first answer is the one the sim applied."""
    s = _stamp(loop, k)
    i = next(i for i, r in enumerate(loop.records) if isinstance(r, PolicyInfoRecord) and r.stamp_ns == s)
    info = loop.records[i]
    action = change(info.action)
    again = [
        next(r for r in loop.records if isinstance(r, JointStateRecord) and r.stamp_ns == s),
        EffortRecord(0, s, np.clip(action, -1.0, 1.0)),
        dataclasses.replace(info, action=action, log_prob_per_joint=info.log_prob_per_joint - 0.5),
    ]
    return loop.records[: i + 1] + again + loop.records[i + 1 :]


def _perturb_answered_twice(loop):
    return _second_answer(loop, 7, np.negative), set()


def _perturb_ambiguous(loop):
    k = _saturated_step(loop)

    def beyond(a):  # another sample that the motors' clip cannot tell from the first
        b = a.copy()
        out = np.abs(b) > 1
        b[out] *= 1.5
        return b

    return _second_answer(loop, k, beyond), {k}


def _perturb_malformed_state(loop):
    s = _stamp(loop, 10)

    def bad(r):
        if isinstance(r, JointStateRecord) and r.stamp_ns == s:
            return dataclasses.replace(r, position=r.position[:2])
        return r

    return [bad(r) for r in loop.records], {9, 10}


@pytest.mark.parametrize(
    ("perturb", "reason", "count"),
    [
        (_perturb_drop_odometry, "no_odometry", 2),
        (_perturb_nan_velocity, "non_finite", 2),
        (_perturb_not_applied, "not_applied", 1),
        (_perturb_policy_info("log_prob_per_joint", lambda r: r.log_prob_per_joint * math.inf), "non_finite", 1),
        (_perturb_policy_info("names", lambda r: ("a", "b", "c")), "names_mismatch", 1),
        (_perturb_policy_info("mean", lambda r: r.mean[:2]), "malformed", 1),
        (_perturb_orphan_effort, "orphan_effort", 1),
        (_perturb_orphan_policy_info, "orphan_policy_info", 1),
        (_perturb_no_answer, "no_answer", 1),
        (_perturb_resent_state, None, 0),
        (_perturb_conflicting_state, "duplicate_stamp", 1),
        (_perturb_answered_twice, None, 0),
        (_perturb_malformed_state, "malformed", 2),
        (_perturb_ambiguous, "ambiguous_answer", 1),
    ],
)
def test_each_spoiled_step_is_counted_and_the_rest_used(sampled, perturb, reason, count):
    clean = rows(assemble(sampled.records).batch)
    records, lost = perturb(sampled)
    result = assemble(records)
    counts = result.skips.as_dict()
    if reason is not None:
        assert counts.pop(reason) == count
    assert not any(counts.values()), counts
    lost_stamps = {_stamp(sampled, k) for k in lost}
    got = rows(result.batch)
    assert set(got) == set(clean) - lost_stamps
    for stamp, row in got.items():
        for k, v in row.items():
            if k not in ("episode", "truncated"):
                np.testing.assert_array_equal(v, clean[stamp][k], err_msg=k)
    # the run ends (truncated, bootstrapped on its next state) right before the lost steps
    if lost:
        assert got[_stamp(sampled, min(lost) - 1)]["truncated"]
    assert result.batch.num_episodes == 3 + (1 if lost else 0)


def test_a_late_answer_in_free_running_mode_is_not_the_action_applied(policy):
    late_steps = {4, 11}
    loop = record(SamplingController(policy, seed=6), episodes=((4, 20),), late=lambda i: i in late_steps)
    result = assemble(loop.records)
    assert result.skips.not_applied == len(late_steps) and result.skips.steps_skipped == len(late_steps)
    assert result.skips.late_message == 0  # within the settle window: used to judge, found not applied
    stepped = {t.stamp_ns for t in loop.truth if t.action is not None}
    assert set(result.batch.stamp_ns.tolist()) == stepped - {_stamp(loop, k) for k in late_steps}
    assert_matches_replay(result.batch, loop)


# -- without policy_info -----------------------------------------------------------------------


def test_a_deterministic_recording_gives_no_log_probs_and_ppo_refuses(policy):
    loop = record(MeanController(policy), episodes=((3, 15), (6, 12)))
    assert all(np.all(np.abs(t.action) < 1) for t in loop.truth if t.action is not None)  # effort == action
    result = assemble(loop.records)
    batch = result.batch
    assert len(batch) == 27 and result.skips.steps_skipped == 0
    assert not batch.has_policy_info.any() and np.isnan(batch.log_prob).all()
    assert result.stats.without_policy_info == 27 and not batch.ppo_ready
    with pytest.raises(MissingPolicyInfoError, match="27 of 27 steps have no policy_info"):
        batch.require_policy_info()
    assert_matches_replay(batch, loop)

    # untagged efforts (another controller) pair with the latest state before them: same transitions
    untagged = [dataclasses.replace(r, answers_ns=None) if isinstance(r, EffortRecord) else r for r in loop.records]
    again = assemble(untagged).batch
    for k, v in batch.arrays().items():
        np.testing.assert_array_equal(again.arrays()[k], v, err_msg=k)


def test_no_applied_effort_reported_trusts_the_answer_and_says_so():
    loop = record(GaussianController(log_std=-1.0, seed=7), episodes=((2, 10),))
    blank = [dataclasses.replace(r, effort=np.zeros(0)) if isinstance(r, JointStateRecord) else r for r in loop.records]
    result = assemble(blank)
    assert len(result.batch) == 10 and result.stats.applied_unverified == 10
    no_effort = [r for r in blank if not isinstance(r, EffortRecord)]
    result = assemble(no_effort)
    assert len(result.batch) == 0 and result.skips.no_applied_effort == 10


# -- the export layout -------------------------------------------------------------------------


def test_npz_round_trip_is_exact_and_has_the_layout(sampled, tmp_path):
    batch = assemble(sampled.records).batch
    path = tmp_path / "out" / "transitions.npz"
    batch.to_npz(path)
    assert [p.name for p in path.parent.iterdir()] == ["transitions.npz"]  # no temp file left
    with np.load(path) as data:
        assert tuple(data.files) == EXPORT_KEYS
        assert data["joint_pos"].shape == (75, 5) and data["global"].shape == (75, 4)
        assert data["episode"].dtype == np.int64 and data["truncated"].dtype == np.bool_
    back = TransitionBatch.from_npz(path)
    for k, v in batch.arrays().items():
        np.testing.assert_array_equal(back.arrays()[k], v, err_msg=k)

    empty = TransitionBatch.empty()
    empty.to_npz(tmp_path / "empty.npz")
    assert len(TransitionBatch.from_npz(tmp_path / "empty.npz")) == 0


def test_npz_that_is_not_a_batch_is_refused(sampled, tmp_path):
    arrays = assemble(sampled.records).batch.arrays()
    np.savez(tmp_path / "missing.npz", **{k: v for k, v in arrays.items() if k != "reward"})
    with pytest.raises(TransitionBatchError, match="missing keys \\['reward'\\]"):
        TransitionBatch.from_npz(tmp_path / "missing.npz")
    np.savez(tmp_path / "short.npz", **{**arrays, "reward": arrays["reward"][:-1]})
    with pytest.raises(TransitionBatchError, match="reward: expected float64 \\(75,\\)"):
        TransitionBatch.from_npz(tmp_path / "short.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(TransitionBatchError, match="not an .npz"):
        TransitionBatch.from_npz(tmp_path / "junk.npz")


def test_concatenate_pads_and_keeps_episodes_apart(sampled, policy):
    a = assemble(sampled.records).batch
    b = assemble(record(SamplingController(policy, seed=8), episodes=((7, 6),)).records).batch
    both = TransitionBatch.concatenate([a, b])
    assert len(both) == len(a) + len(b) and both.max_joints == 7
    assert both.num_episodes == a.num_episodes + b.num_episodes
    np.testing.assert_array_equal(both.joint_pos[: len(a), :5], a.joint_pos)
    assert not both.joint_pos[: len(a), 5:].any()
    np.testing.assert_array_equal(both.action[len(a) :], b.action)


def test_config_is_checked():
    with pytest.raises(ValueError, match="control_period"):
        TransitionConfig(control_period=-0.04)  # 0 is the task's
    with pytest.raises(ValueError, match="task must be one of swimmer, ant"):
        TransitionConfig(task="walker")
    with pytest.raises(ValueError, match=">= 0"):
        TransitionConfig(settle_states=-1)
    with pytest.raises(TypeError, match="not a record"):
        TransitionAssembler().push("joint_states")


# -- trees: the parents of each row ------------------------------------------------------------


def test_a_recording_is_chains_in_message_order(sampled):
    batch = assemble(sampled.records).batch
    assert batch.is_chains and batch.parents.dtype == np.int64
    assert batch.parents[0].tolist() == [-1, 0, 1, -1, -1] and batch.parents[-1].tolist() == [-1, 0, 1, 2, 3]


def test_npz_round_trip_keeps_the_trees(sampled, tmp_path, random_trees):
    trees = random_trees(assemble(sampled.records).batch)
    trees.to_npz(tmp_path / "trees.npz")
    with np.load(tmp_path / "trees.npz") as data:
        assert tuple(data.files) == EXPORT_KEYS and EXPORT_KEYS[-1] == "parents"
        assert data["parents"].dtype == np.int64 and data["parents"].shape == (75, 5)
    back = TransitionBatch.from_npz(tmp_path / "trees.npz")
    for k, v in trees.arrays().items():
        np.testing.assert_array_equal(back.arrays()[k], v, err_msg=k)
    assert not back.is_chains
    # Concatenating pads the parents with -1, not 0 (a 0 there would be a joint hanging off joint 0).
    wide = TransitionBatch.concatenate([back, random_trees(assemble(sampled.records).batch, seed=1)])
    assert wide.max_joints == 5 and (wide.parents[wide.num_joints == 3][:, 3:] == -1).all()


def test_an_npz_written_before_parents_reads_as_chains(sampled, tmp_path):
    batch = assemble(sampled.records).batch
    np.savez(tmp_path / "old.npz", **{k: v for k, v in batch.arrays().items() if k != "parents"})
    old = TransitionBatch.from_npz(tmp_path / "old.npz")
    assert old.is_chains
    for k, v in batch.arrays().items():
        np.testing.assert_array_equal(old.arrays()[k], v, err_msg=k)
    # and built in code without parents, as every caller did
    fields = {f.name: getattr(batch, f.name) for f in dataclasses.fields(TransitionBatch) if f.name != "parents"}
    np.testing.assert_array_equal(TransitionBatch(**fields).parents, batch.parents)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda p: p.astype(np.float64), r"parents: expected int64 \(75, 5\), got float64"),
        (lambda p: p.astype(np.int32), r"parents: expected int64 \(75, 5\), got int32"),
        (lambda p: p[:, :4], r"parents: expected int64 \(75, 5\), got int64 \(75, 4\)"),
        (lambda p: p[:-1], r"parents: expected int64 \(75, 5\), got int64 \(74, 5\)"),
        (lambda p: np.where(np.arange(5) == 2, 2, p), r"row 0, joint 2 has parent 2"),
        (lambda p: np.where((np.arange(75)[:, None] == 40) & (np.arange(5) == 1), -2, p), r"row 40, joint 1 .* -2"),
        (lambda p: np.where((np.arange(75)[:, None] == 7) & (np.arange(5) == 4), 0, p), r"row 7, joint 4 is padding"),
        (lambda p: np.where((np.arange(75)[:, None] == 50) & (np.arange(5) == 4), 0, p),
         r"row 50 continues episode 1 with another robot than row 49"),
    ],
)  # fmt: skip
def test_invalid_parents_are_refused_naming_the_file_and_row(sampled, tmp_path, damage, message):
    arrays = assemble(sampled.records).batch.arrays()
    path = tmp_path / "bad.npz"
    np.savez(path, **{**arrays, "parents": damage(arrays["parents"])})
    with pytest.raises(TransitionBatchError, match=f"^{path}: .*{message}"):
        TransitionBatch.from_npz(path)


def test_fuzzed_parents_give_the_documented_error_or_exactly_the_file(sampled, tmp_path, random_trees):
    """Random damage to the parents of a real export: either a valid file read exactly as written, or a
    TransitionBatchError naming the file; never another exception, never parents other than the file's."""
    rng = np.random.default_rng(0)
    exported = tmp_path / "export.npz"
    random_trees(assemble(sampled.records).batch).to_npz(exported)
    with np.load(exported) as data:
        arrays = {k: data[k] for k in data.files}
    dtypes = [np.int64, np.int32, np.uint8, np.float64, np.float32, np.bool_, np.int16, np.complex64]
    outcomes = {"read": 0, "refused": 0}
    for i in range(300):
        p = arrays["parents"].copy()
        kind = rng.integers(6)
        if kind == 0:  # a few entries anywhere, to anything
            for _ in range(rng.integers(1, 4)):
                p[rng.integers(p.shape[0]), rng.integers(p.shape[1])] = rng.integers(-4, 7)
        elif kind == 1:  # extreme values
            p[rng.integers(p.shape[0]), rng.integers(p.shape[1])] = rng.choice([np.iinfo(np.int64).min, 2**62, -1])
        elif kind == 2:
            p = p.astype(dtypes[rng.integers(len(dtypes))])
        elif kind == 3:  # cut or grown
            p = p[: rng.integers(0, 76), : rng.integers(0, 6)] if rng.random() < 0.5 else np.pad(p, ((0, 1), (0, 1)))
        elif kind == 4:  # another dimensionality
            p = [p.reshape(-1), p[None], np.int64(3), np.zeros((75, 5, 1), np.int64)][rng.integers(4)]
        else:  # one row's tree swapped for a random tree of its joints (valid unless mid-episode)
            r = rng.integers(p.shape[0])
            n = int(arrays["num_joints"][r])
            p[r, :n] = [rng.integers(-1, j) if j else -1 for j in range(n)]
        path = tmp_path / f"fuzz{i}.npz"
        np.savez(path, **{**arrays, "parents": p})
        try:
            back = TransitionBatch.from_npz(path)
        except TransitionBatchError as err:
            assert str(err).startswith(f"{path}: ") and "parents" in str(err), err
            outcomes["refused"] += 1
        else:
            assert back.parents.dtype == np.int64
            np.testing.assert_array_equal(back.parents, p)
            outcomes["read"] += 1
    assert outcomes["read"] > 10 and outcomes["refused"] > 100, outcomes


# -- the robot's tree, from its robot_description ------------------------------------------------------
STAR3 = [-1, 0, 0]
TREE5 = [-1, 0, 1, 0, -1]  # pre-order: a joint's subtree right after it


def description(body, log_ns=0, prefix=""):
    """The sim's robot_description of a body (a chain length, a parent array or a tree)."""
    return DescriptionRecord(log_ns, swimmer_urdf(body, prefix))


def first_state_index(records, num_joints=None):
    return next(
        i
        for i, r in enumerate(records)
        if isinstance(r, JointStateRecord) and (num_joints is None or len(r.names) == num_joints)
    )


def test_each_state_is_read_on_the_tree_of_the_latest_description(sampled):
    """Descriptions of trees whose joints are the chain's, in the chain's order: the same steps, another graph."""
    records = list(sampled.records)
    announced = [i for i, r in enumerate(records) if isinstance(r, EpisodeStartRecord)][1]  # the 5-joint episode
    records.insert(announced, description(TREE5, records[announced].log_ns))
    records.insert(0, description(STAR3))
    asm = TransitionAssembler()
    transitions = asm.push_many(records) + asm.flush()
    assert asm.skips == SkipCounts() and asm.stats.descriptions == 2
    assert not asm.joint_map.is_fallback and asm.joint_map.robot.tree.parents.tolist() == TREE5
    batch = TransitionBatch.from_transitions(transitions)
    chains = assemble(sampled.records).batch
    for k, v in chains.arrays().items():  # the same steps, only the graph differs
        if k != "parents":
            np.testing.assert_array_equal(batch.arrays()[k], v, err_msg=k)
    assert batch.parents[0].tolist() == [-1, 0, 0, -1, -1] and batch.parents[-1].tolist() == TREE5
    assert all(t.parents.tolist() == {3: STAR3, 5: TREE5}[len(t.joint_pos)] for t in transitions)
    # Known otherwise (a URDF file beside a bag recorded without the topic): the same from the first state on.
    given = TransitionAssembler(joint_map=JointMap.from_urdf(swimmer_urdf(STAR3)))
    star = given.push_many(sampled.records[: first_state_index(sampled.records, 5)]) + given.flush()
    assert len(star) == 30 and all(t.parents.tolist() == STAR3 for t in star)


def test_a_description_that_changes_the_tree_splits_the_episode(policy):
    loop = record(SamplingController(policy, seed=2), episodes=((4, 30),))
    states = [i for i, r in enumerate(loop.records) if isinstance(r, JointStateRecord)]
    # The robot's description changes as the 16th state arrives; its joints keep their names.
    records = [description(4)] + loop.records[: states[15]] + [description([-1, 0, 0, 2])] + loop.records[states[15] :]
    result = assemble_with(records)
    assert np.bincount(result.batch.episode).tolist() == [14, 15]
    assert result.stats.boundaries_new_chain == 1 and result.skips == SkipCounts()
    assert (result.batch.parents[:14] == [-1, 0, 1, 2]).all() and (result.batch.parents[14:] == [-1, 0, 0, 2]).all()
    assert result.batch.truncated[[13, 28]].all()

    # The same description again (a latched publisher re-sending it), or one of the chain the states formed
    # without a description (a recorder that started after the sim: the latched URDF comes after the first
    # states): the tree does not change, nor does the episode.
    for late in ([description(4)] * 2, [description(4)]):
        records = loop.records[: states[15]] + late + loop.records[states[15] :]
        result = assemble_with(records)
        assert np.bincount(result.batch.episode).tolist() == [30] and result.stats.descriptions == len(late)
        for k, v in assemble(loop.records).batch.arrays().items():
            np.testing.assert_array_equal(result.batch.arrays()[k], v, err_msg=k)


def test_a_new_description_restarts_the_yaw_unwrapping_as_the_policy_node_does(policy):
    """The policy node takes a new description for a new robot (its graph) and restarts its unwrapping at the first
    state it reads on it, even when the tree is the one the states already formed: so does the assembler."""
    loop = record(SamplingController(policy, seed=2), episodes=((4, 30),))
    index = {stamp: i for i, stamp in enumerate(state_stamps(loop))}

    def turned(r):  # the swimmer turning steadily: past +pi at state 15, where the description comes
        if isinstance(r, OdometryRecord):
            return dataclasses.replace(
                r, orientation_xyzw=quaternion_from_yaw(math.pi + 0.02 + 0.05 * (index[r.stamp_ns] - 15))
            )
        return r

    records = [turned(r) for r in loop.records]
    states = [i for i, r in enumerate(records) if isinstance(r, JointStateRecord)]
    plain = assemble(records).batch
    late = assemble_with(records[: states[15]] + [description(4)] + records[states[15] :]).batch
    assert np.bincount(late.episode).tolist() == [30]  # the same tree: no boundary
    np.testing.assert_array_equal(late.global_feats[:15], plain.global_feats[:15])
    np.testing.assert_allclose(late.global_feats[15:, 0], plain.global_feats[15:, 0] - 2 * math.pi, atol=1e-12)
    np.testing.assert_allclose(late.global_feats[15:, 1:], plain.global_feats[15:, 1:], rtol=0, atol=1e-12)
    assert late.next_global[14, 0] == pytest.approx(plain.next_global[14, 0] - 2 * math.pi)


def assemble_with(records, joint_map=None):
    asm = TransitionAssembler(joint_map=joint_map)
    transitions = asm.push_many(records) + asm.flush()

    class Result:
        batch = TransitionBatch.from_transitions(transitions)
        stats, skips = asm.stats, asm.skips

    return Result


@pytest.mark.parametrize(
    "text",
    [
        "not a URDF",
        "<robot name='r'><link name='a'/></robot>",  # no actuated joint
        swimmer_urdf(3).replace('type="revolute"', 'type="prismatic"', 1),
        swimmer_urdf(3).replace('name="motor2_rot"', 'name="motor1_rot"'),
        b"\xff\xfe<robot/>",
    ],
)
def test_a_description_that_is_no_robot_is_counted_and_the_last_good_one_kept(policy, text):
    loop = record(SamplingController(policy, seed=2), episodes=((3, 5),))
    chains = assemble(loop.records).batch
    for before in ([], [description(STAR3)]):
        result = assemble_with(before + [DescriptionRecord(0, text)] + loop.records)
        assert result.skips.bad_description == 1 and result.skips.steps_skipped == 0
        assert result.stats.descriptions == len(before)
        assert len(result.batch) == 5 and (result.batch.parents == (STAR3 if before else [-1, 0, 1])).all()
        np.testing.assert_array_equal(result.batch.action, chains.action)


@pytest.mark.parametrize(
    ("body", "prefix", "reason"),
    [
        (3, "other_", "unknown_joint"),  # the description names other joints
        (STAR3 + [0], "", "missing_joint"),  # the states lack one of its joints
    ],
)
def test_a_state_that_does_not_fit_the_description_is_skipped_by_reason(policy, body, prefix, reason):
    loop = record(SamplingController(policy, seed=2), episodes=((3, 5),))
    result = assemble_with([description(body, prefix=prefix)] + loop.records)
    assert len(result.batch) == 0 and result.stats.states == 6
    assert result.skips.as_dict()[reason] == 5 and result.skips.steps_skipped == 5


TREES = (swimmer_tree(star_parents(2, 2)), swimmer_tree(y_parents(1, 2)), swimmer_tree(TREE5))


def record_trees(controller, bodies=((TREES[0], 20), (TREES[1], 15), (TREES[2], 12)), **options):
    loop = LoopbackRecording(body_sim(bodies[0][0], SEED), controller, **options)
    for i, (body, steps) in enumerate(bodies):
        if i:
            loop.new_episode(body)
        loop.run(steps)
    loop.finish()
    return loop, [body for body, _ in bodies]


def replay_trees(loop, bodies):
    """stamp -> (observation, action stepped with, reward, next observation), from a fresh env with the sim's
    seed, rebuilt as the recording rebuilt it."""
    env = MorphSwimmerEnv(num_joints=bodies[0].num_joints)
    env.reset(seed=SEED)
    obs, _ = env.reset(options={"tree": bodies[0]})
    episode, out = 0, {}
    for truth in loop.truth:
        if truth.episode != episode:
            episode = truth.episode
            obs, _ = env.reset(options={"tree": bodies[episode]})
        if truth.action is None:
            continue
        nxt, reward, _, _, _ = env.step(applied_action(truth.action))
        out[truth.stamp_ns] = (obs, truth.action, reward, nxt)
        obs = nxt
    return out


@pytest.mark.parametrize("name_efforts", [True, False])
def test_shuffled_states_of_trees_give_the_replayed_transitions_in_the_trees_order(policy, name_efforts):
    loop, bodies = record_trees(
        SamplingController(policy, seed=3), describe=True, shuffle_seed=4, name_efforts=name_efforts
    )
    states = [r for r in loop.records if isinstance(r, JointStateRecord)]
    efforts = [r for r in loop.records if isinstance(r, EffortRecord)]
    assert sum(r.names != tuple(sorted(r.names)) for r in states) > 40  # listed in an order of their own
    assert all((e.names is not None) == name_efforts for e in efforts)
    asm = TransitionAssembler()
    transitions = asm.push_many(loop.records) + asm.flush()
    assert asm.skips == SkipCounts() and asm.stats.descriptions == 3
    assert asm.stats.boundaries_announced == 2 and asm.stats.boundaries == 2
    batch = TransitionBatch.from_transitions(transitions)
    assert np.bincount(batch.episode).tolist() == [20, 15, 12]
    for t in transitions:  # one run per episode, each of its own body
        assert t.names == bodies[t.episode].names and t.parents.tolist() == bodies[t.episode].parents.tolist()
    reference = replay_trees(loop, bodies)
    assert set(reference) == set(batch.stamp_ns.tolist())
    for stamp, row in rows(batch).items():
        obs, action, reward, nxt = reference[stamp]
        np.testing.assert_array_equal(row["joint_pos"], obs["joint_pos"])
        np.testing.assert_array_equal(row["joint_vel"], obs["joint_vel"])
        np.testing.assert_allclose(row["global"], obs["global"], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(row["action"], action)
        np.testing.assert_array_equal(row["parents"][: row["num_joints"]], obs["parents"])
        assert row["reward"] == pytest.approx(reward, abs=1e-9)
        np.testing.assert_array_equal(row["next_joint_pos"], nxt["joint_pos"])
    # The behaviour log-prob is the policy's on the tree, for the action in the tree's order.
    for i in range(0, len(batch), 5):
        n = batch.num_joints[i]
        rows_i = slice(i, i + 1)
        pos, vel, glob = batch.joint_pos[rows_i, :n], batch.joint_vel[rows_i, :n], batch.global_feats[rows_i]
        tree_batch = ChainBatch.from_padded(pos, vel, glob, [n], parents=batch.parents[rows_i, :n])
        lp = policy.log_prob(tree_batch, torch.as_tensor(batch.action[rows_i, :n], dtype=torch.float32))
        assert lp.item() == pytest.approx(batch.log_prob[i], abs=2e-4)


def test_the_deterministic_policy_answer_of_shuffled_states_is_read_by_name(policy):
    """No policy_info: the action is the effort command, unnamed ones in the order of the state they answer."""
    loop, bodies = record_trees(MeanController(policy), describe=True, shuffle_seed=5)
    result = assemble_with(loop.records)
    assert result.skips == SkipCounts() and result.stats.without_policy_info == len(result.batch) == 47
    reference = replay_trees(loop, bodies)
    for stamp, row in rows(result.batch).items():
        np.testing.assert_array_equal(row["action"], np.clip(reference[stamp][1], -1.0, 1.0))


def with_a_fixed_joint(records):
    """The records as from a robot whose description has one more joint, fixed, which every state carries
    (as joint_state_broadcaster publishes every joint it has)."""
    fixed = (
        '<link name="camera"/><joint name="camera_mount" type="fixed">'
        '<parent link="torso"/><child link="camera"/></joint>'
    )
    out = []
    for r in records:
        if isinstance(r, DescriptionRecord):
            r = dataclasses.replace(r, text=r.text.replace("</robot>", fixed + "</robot>"))
        elif isinstance(r, JointStateRecord):
            k = 1 + r.stamp_ns // PERIOD_NS % len(r.names)  # somewhere among the others
            names = r.names[:k] + ("camera_mount",) + r.names[k:]
            pos, vel, eff = (np.insert(x, k, 0.0) for x in (r.position, r.velocity, r.effort))
            r = dataclasses.replace(r, names=names, position=pos, velocity=vel, effort=eff)
        out.append(r)
    return out


def test_joints_the_robot_does_not_actuate_are_left_alone(policy):
    loop, _ = record_trees(SamplingController(policy, seed=3), describe=True, shuffle_seed=6, name_efforts=True)
    clean = assemble(loop.records).batch
    result = assemble_with(with_a_fixed_joint(loop.records))
    assert result.skips == SkipCounts()
    for k, v in clean.arrays().items():
        np.testing.assert_array_equal(result.batch.arrays()[k], v, err_msg=k)
    # Unnamed efforts, one per joint of the state: the fixed joint's entry is left out too.
    loop, _ = record_trees(MeanController(policy), describe=True, shuffle_seed=6)
    states = {r.stamp_ns: r for r in with_a_fixed_joint(loop.records) if isinstance(r, JointStateRecord)}

    def widen(r):
        if isinstance(r, EffortRecord):
            state = states[r.answers_ns]
            at = {name: r.effort[i] for i, name in enumerate(n for n in state.names if n != "camera_mount")}
            return dataclasses.replace(r, effort=np.array([at.get(name, 0.0) for name in state.names]))
        return r

    result = assemble_with([widen(r) for r in with_a_fixed_joint(loop.records)])
    assert result.skips == SkipCounts() and len(result.batch) == 47


def test_answers_naming_other_joints_are_names_mismatches(policy):
    loop, _ = record_trees(SamplingController(policy, seed=3), describe=True, shuffle_seed=7, name_efforts=True)
    stamp = [r.stamp_ns for r in loop.records if isinstance(r, JointStateRecord)][5]

    def rename(r):
        if (
            isinstance(r, (EffortRecord, PolicyInfoRecord))
            and getattr(r, "answers_ns", getattr(r, "stamp_ns", None)) == stamp
        ):
            return dataclasses.replace(r, names=("motor1_rot",) * len(r.names))
        return r

    result = assemble_with([rename(r) for r in loop.records])
    assert result.skips.names_mismatch == 1 and result.skips.steps_skipped == 1

    # An effort command naming the tree's joints in another order than the state's: laid out by its names.
    def reverse(r):
        if isinstance(r, EffortRecord):
            return dataclasses.replace(r, names=r.names[::-1], effort=r.effort[::-1])
        return r

    clean = assemble(loop.records).batch
    result = assemble_with([reverse(r) for r in loop.records if not isinstance(r, PolicyInfoRecord)])
    assert result.skips == SkipCounts() and len(result.batch) == len(clean)
    np.testing.assert_array_equal(result.batch.action, np.clip(clean.action, -1.0, 1.0))


def test_answers_computed_on_another_tree_are_not_taken_for_the_state_as_read_here(policy):
    """Without the descriptions the trees' states read as chains in message order, which is not what the policy
    answered on: its efforts say so (their tree dimension), and no step is made of them."""
    loop, _ = record_trees(SamplingController(policy, seed=3), describe=True, name_efforts=True)
    described = assemble(loop.records)
    assert described.skips.wrong_tree == 0 and len(described.batch) == 20 + 15 + 12
    blind = assemble([r for r in loop.records if not isinstance(r, DescriptionRecord)])
    assert len(blind.batch) == 0
    assert blind.skips.wrong_tree == described.stats.states - 3  # every state but each episode's last
    assert blind.skips.steps_skipped == blind.skips.wrong_tree  # a skipped step, as morph-bag info lists them
