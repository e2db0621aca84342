"""Recording branched swimmers over real DDS, and learning from the bag: the sim node with ``topology`` and
``shuffle_joints``, a sampling policy node and ``morph-record``, three processes; the bag read back onto the trees
its ``robot_description`` gives equals a replay in ``MorphSwimmerEnv(bodies=...)``, and trains.

Needs the sim node's ``topology`` and ``shuffle_joints`` (issue 38's sim work). Runs inside a private network
namespace (``scripts/test.sh``).
"""

from __future__ import annotations

import csv
import time

import numpy as np
import pytest
import torch

from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import options_of, small
from morph_core.env.reward import applied_action
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.msgs.records import DescriptionRecord, EpisodeStartRecord, JointStateRecord
from morph_core.policy.actor_critic import GraphActorCritic, gaussian_log_prob
from morph_core.policy.chains import ChainBatch
from morph_core.protocol.transitions import TransitionConfig
from trainer.bags.contents import summarize_bag
from trainer.bags.io import BagReader
from trainer.cli.train import main as train_main

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
SPEC = "star:2x2,y:1x2"
LABELS = {"star-2x2", "y-1x2"}
SEED = 5
STEPS = 40
SMALL = options_of(small(num_envs=1, num_steps=32, minibatch_size=16, update_epochs=1, checkpoint_interval=32))


@pytest.mark.timeout(300)
def test_a_bag_of_branched_shuffled_swimmers_replays_on_its_trees_and_trains(
    probe, launch, untrained_checkpoint, tmp_path, namespace, capsys
):
    bag = tmp_path / "bag"
    recorder = launch("morph-record", output=str(bag), max_episodes=3)  # episodes 0, 1 and 2, then it stops

    def recorder_reads(topic: str) -> bool:
        return any(i.node_name == "morph_record" for i in probe.node.get_subscriptions_info_by_topic(topic))

    topics = [f"{namespace}/{t}" for t in ("episode_start", "robot_description", "joint_states", "policy_info")]
    probe.spin_until(lambda: all(map(recorder_reads, topics)), STARTUP, "the recorder subscribed")
    launch("swimmer_sim_node", topology=SPEC, shuffle_joints=True, seed=SEED, episode_steps=STEPS, lockstep=True,
           real_time_factor=0.0, effort_timeout=2.0)  # fmt: skip
    launch("morph_policy_node", checkpoint=str(untrained_checkpoint), deterministic=False)
    deadline = time.monotonic() + 200
    while recorder.alive():
        assert time.monotonic() < deadline, recorder.log()
        probe.spin_for(0.2)
    assert recorder.stop() == 0, recorder.log()

    records = BagReader(bag, namespace=namespace).read()
    states = [r for r in records if isinstance(r, JointStateRecord)]
    assert sum(list(r.names) != sorted(r.names) for r in states) > len(states) // 2  # listed in orders of their own
    first = next(i for i, r in enumerate(records) if isinstance(r, DescriptionRecord))
    starts = {r.episode: r.stamp_ns for r in records if isinstance(r, EpisodeStartRecord)}
    assert len(starts) == 3, starts

    summary = summarize_bag(bag, TransitionConfig(), namespace)
    assert summary.described and set(summary.described) <= LABELS
    assert set(summary.steps_per_body) <= LABELS
    # The recorder's readers match the sim's writers one by one: the latched URDF may reach it after a few states,
    # which are read on it (bag_io.first_description); only if the body changed meanwhile do they not fit it.
    misfits = summary.skips.unknown_joint + summary.skips.missing_joint
    assert misfits <= sum(isinstance(r, JointStateRecord) for r in records[:first])
    assert summary.skips.names_mismatch == summary.skips.not_applied == summary.skips.bad_description == 0
    data = summary.batch
    assert not data.is_chains

    # The episodes recorded whole equal a replay of their actions in a fresh env of the same bodies, reset as the
    # sim resets (seeded, then from the same generator), in the tree's order whatever order the states had.
    env = MorphSwimmerEnv(bodies=SPEC)
    env.reset(seed=SEED)
    policy = GraphActorCritic.load(untrained_checkpoint)
    replayed = 0
    for k in range(1, max(starts) + 1):
        obs, _ = env.reset()
        if k not in starts or k - 1 not in starts:  # not recorded, or maybe not from its first state
            continue
        end = starts.get(k + 1)
        rows = np.flatnonzero((data.stamp_ns >= starts[k]) & (True if end is None else data.stamp_ns < end))
        assert len(rows) >= STEPS - 1 and data.stamp_ns[rows[0]] == starts[k], k
        replayed += 1
        n = env.num_joints
        for i in rows:
            np.testing.assert_array_equal(data.parents[i, :n], env.tree.parents)
            np.testing.assert_array_equal(data.joint_pos[i, :n], obs["joint_pos"])
            np.testing.assert_array_equal(data.joint_vel[i, :n], obs["joint_vel"])
            np.testing.assert_allclose(data.global_feats[i], obs["global"], rtol=0, atol=1e-12)
            action = data.action[i, :n]
            if data.has_policy_info[i]:  # the policy's density on this tree, for the action in the tree's order
                with torch.no_grad():
                    pos, vel, glob = obs["joint_pos"][None], obs["joint_vel"][None], obs["global"][None]
                    batch = ChainBatch.from_padded(pos, vel, glob, [n], parents=env.tree.parents[None])
                    mean = policy(batch)[0]
                    expected = gaussian_log_prob(
                        torch.as_tensor(action[None], dtype=torch.float32), mean, policy.log_std, batch.mask
                    )
                assert data.log_prob[i] == pytest.approx(float(expected), abs=1e-4)
            obs, reward, _, _, _ = env.step(applied_action(action))
            assert data.reward[i] == pytest.approx(reward, abs=1e-9)
    assert replayed == 2

    run = tmp_path / "run"
    assert train_main(["--from-bags", str(bag), "--namespace", namespace, "--out", str(run), "--iterations", "1",
                       *SMALL]) == 0  # fmt: skip
    assert "joints: " in capsys.readouterr().out  # the bodies named, not "chains of"
    with RunDir(run).progress.open() as f:
        (row,) = list(csv.DictReader(f))
    assert np.isfinite(float(row["return_trees"])) and np.isfinite(float(row["approx_kl"]))
