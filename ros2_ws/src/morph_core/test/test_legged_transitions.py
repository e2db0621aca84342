"""Legged bodies from the topics: the 12 global features, Ant-v5's reward rebuilt and falls that end episodes.

A loopback recording of centipedes (``protocol.loopback``: what the sim and the policy node publish) is turned
into transitions with ``task="ant"`` and checked against what the env itself saw and paid.
"""

from __future__ import annotations

import numpy as np
import pytest

from morph_core.env.reward import ANT_HEALTHY_Z_RANGE
from morph_core.env.sim import SwimmerSim
from morph_core.msgs.episode_start import EpisodeCause, pack_episode_start, unpack_episode_start
from morph_core.msgs.records import EpisodeStartRecord, OdometryRecord
from morph_core.policy.config import PolicyConfig
from morph_core.policy.weights import untrained_weights
from morph_core.protocol.loopback import LoopbackRecording, SamplingController
from morph_core.protocol.transition_batch import TransitionBatch, TransitionBatchError
from morph_core.protocol.transitions import SkipCounts, TransitionAssembler, TransitionConfig, task_of

LEGGED = untrained_weights(PolicyConfig(global_features=12), seed=1)


def centipede_loop(contact_cost: bool = True, steps: int = 150) -> LoopbackRecording:
    """Three runs of ``steps`` of an untrained sampling policy on centipedes of 2..3 leg pairs (it falls often)."""
    sim = SwimmerSim(bodies="centipede:2-3", seed=5, effort_timeout=None)
    if not contact_cost:
        sim.robot._env._centipede.contact_cost_weight = 0.0  # the env's one term no topic carries, switched off
    loop = LoopbackRecording(sim, SamplingController(LEGGED, seed=7), describe=True)
    for i in range(3):
        if i:
            loop.new_episode()
        loop.run(steps)
    loop.finish()
    return loop


def rebuilt(loop: LoopbackRecording):
    asm = TransitionAssembler(TransitionConfig(task="ant"))
    transitions = asm.push_many(loop.records) + asm.flush()
    assert asm.skips == SkipCounts()
    return transitions


@pytest.fixture(scope="module")
def loop():
    return centipede_loop()


def test_the_observation_is_the_envs_twelve_global_features(loop):
    transitions = rebuilt(loop)
    env_globals = {s.stamp_ns: s.observation["global"] for s in loop.truth}
    assert len(transitions) > 400
    for t in transitions:
        assert t.global_feats.shape == t.next_global.shape == (12,)
        np.testing.assert_allclose(t.global_feats, env_globals[t.stamp_ns], rtol=0, atol=1e-12)


def test_falls_end_episodes_terminated_and_the_rest_truncated(loop):
    causes = [r.cause for r in loop.records if isinstance(r, EpisodeStartRecord)]
    falls = causes.count("fell")
    assert falls >= 3  # the untrained policy falls: the sim announced each fall as the next episode's cause
    transitions = rebuilt(loop)
    ends = [t for t in transitions if t.terminated or t.truncated]
    assert sum(t.terminated for t in transitions) == falls
    assert not any(t.terminated and t.truncated for t in transitions)
    assert len(ends) == len(causes)  # every episode ends once: at a fall, or cut off (new_episode, the end)
    for i, t in enumerate(transitions):
        if t.terminated:
            # the step into the fallen state (its root out of the healthy range: no healthy reward), the last of
            # its episode
            assert not ANT_HEALTHY_Z_RANGE[0] <= t.next_global[5] <= ANT_HEALTHY_Z_RANGE[1]
            assert i + 1 == len(transitions) or transitions[i + 1].episode != t.episode


@pytest.mark.slow
def test_the_reward_is_ant_v5s_from_the_topics_and_the_env_agrees_without_contact_cost():
    # Without its contact cost the env pays what the topics rebuild: forward velocity (the odometry's x, where
    # the env reads the root's xpos, which MuJoCo leaves one physics step behind: per step they differ, over an
    # episode the sums telescope to their ends), healthy reward and control cost.
    loop = centipede_loop(contact_cost=False)
    paid = {s.stamp_ns: s.reward for s in loop.truth if s.reward is not None}
    runs: dict[int, list[tuple[float, float]]] = {}
    for t in rebuilt(loop):
        runs.setdefault(t.episode, []).append((t.reward, paid[t.stamp_ns]))
        assert abs(t.reward - paid[t.stamp_ns]) < 0.1  # the forward term's step lag
    for steps in runs.values():
        ours, env = (np.sum(x) for x in zip(*steps, strict=True))
        assert abs(ours - env) < 0.02 + 1e-3 * abs(env)
    # With it (Ant-v5's default), the env pays less: the contact cost is on no topic.
    with_contact = centipede_loop()
    paid = {s.stamp_ns: s.reward for s in with_contact.truth if s.reward is not None}
    total_ours = sum(t.reward for t in rebuilt(with_contact))
    total_env = sum(paid[t.stamp_ns] for t in rebuilt(with_contact))
    assert total_ours > total_env


def test_the_task_sets_width_period_and_is_checked():
    assert TransitionConfig().period == 0.04 and TransitionConfig(task="ant").period == 0.05
    assert TransitionConfig(task="ant", control_period=0.02).period == 0.02
    assert TransitionConfig(task="ant").global_features == 12 and TransitionConfig().global_features == 4
    assert task_of(12) == "ant" and task_of(4) == "swimmer"
    with pytest.raises(ValueError, match="no task has 7"):
        task_of(7)
    with pytest.raises(ValueError, match="task must be one of"):
        TransitionConfig(task="")


def test_the_fell_cause_goes_over_the_wire():
    label, data = pack_episode_start(3, 50_000_000, 8, EpisodeCause.FELL)
    assert unpack_episode_start(0, label, data).cause == "fell"


def test_an_odometry_out_of_the_plane_is_not_planar():
    flat = OdometryRecord(0, 0, 1.0, 2.0, (0.0, 0.0, 0.6, 0.8), (0.1, 0.2), 0.3)
    assert flat.planar and flat.position == (1.0, 2.0, 0.0) and flat.body_angular == (0.0, 0.0, 0.3)
    tilted = OdometryRecord(0, 0, 1.0, 2.0, (0.6, 0.0, 0.0, 0.8), (0.1, 0.2), 0.3, 0.5, 0.4, (0.1, 0.2))
    assert not tilted.planar and tilted.body_linear == (0.1, 0.2, 0.4)


# -- the batch: any global width ------------------------------------------------------------------
def test_a_batch_and_its_npz_carry_twelve_global_features(loop, tmp_path):
    batch = TransitionBatch.from_transitions(rebuilt(loop))
    assert batch.global_width == 12 and batch.terminated.sum() >= 3
    batch.to_npz(tmp_path / "legged.npz")
    back = TransitionBatch.from_npz(tmp_path / "legged.npz")
    assert back.global_width == 12
    for key, array in batch.arrays().items():
        np.testing.assert_array_equal(back.arrays()[key], array)
    swimmer = TransitionBatch.empty()
    assert swimmer.global_width == 4
    with pytest.raises(TransitionBatchError, match="4 and 12 global features"):
        TransitionBatch.concatenate([batch, _swimmer_batch()])
    bad = dict(batch.arrays(), next_global=batch.next_global[:, :4])
    with pytest.raises(TransitionBatchError, match="next_global"):
        TransitionBatch.from_arrays(bad)


def _swimmer_batch() -> TransitionBatch:
    from morph_core.protocol.loopback import GaussianController, record_episodes

    records = record_episodes(GaussianController(seed=1), [(3, 10)], describe=True)
    asm = TransitionAssembler()
    return TransitionBatch.from_transitions(asm.push_many(records) + asm.flush())


def test_an_old_npz_reads_four_wide(tmp_path):
    # A file of before the width was free (and before parents): a swimmer's 4 globals, written as np.savez did.
    old = _swimmer_batch().arrays()
    del old["parents"]
    np.savez(tmp_path / "old.npz", **old)
    back = TransitionBatch.from_npz(tmp_path / "old.npz")
    assert back.global_width == 4 and back.is_chains
    np.testing.assert_array_equal(back.global_feats, old["global"])
