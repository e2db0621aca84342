"""A lockstep recording over DDS, exported from its bag, equals a replay of its actions in a fresh env.

The whole chain of issue 10 on real processes: swimmer_sim_node (lockstep, episodes) and a sampling
morph_policy_node talk over Fast DDS, morph-record writes the bag, bag_io reads it back and
protocol.transitions rebuilds the steps. A fresh MorphSwimmerEnv reset as the sim resets (seed, then
no seed) and stepped with the recorded actions must give the same observations and rewards, and the
checkpoint's own density the same log-probs.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from morph_core.env.reward import applied_action
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.msgs.records import EpisodeStartRecord
from morph_core.policy.actor_critic import GraphActorCritic, gaussian_log_prob
from morph_core.policy.chains import ChainBatch
from morph_core.protocol.transitions import assemble
from trainer.bags.io import BagReader

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STEPS = 60
JOINTS = 3
SEED = 4


@pytest.mark.timeout(240)
def test_exported_bag_equals_a_replay_in_the_env(untrained_checkpoint, tmp_path, namespace):
    bag = tmp_path / "bag"
    cmd = [sys.executable, "-m", "trainer.bags.record_bringup", "--out", str(bag), "--episodes", "2"]
    cmd += ["--steps-per-episode", str(STEPS), "--joints", str(JOINTS), "--seed", str(SEED)]
    cmd += ["--namespace", namespace, "--checkpoint", str(untrained_checkpoint), "--timeout", "150"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=220)
    assert done.returncode == 0, done.stdout + done.stderr

    records = BagReader(bag, namespace=namespace, required=("joint_states", "odom", "policy_info")).read()
    starts = {r.episode: r.stamp_ns for r in records if isinstance(r, EpisodeStartRecord)}
    assert set(starts) == {0, 1}, starts
    data = assemble(records).batch
    # Episode 1 was recorded whole (the recorder was up long before); its first state opens it.
    ep1 = np.flatnonzero(data.stamp_ns >= starts[1])
    assert ep1.size >= STEPS - 1 and data.stamp_ns[ep1[0]] == starts[1]
    assert (np.diff(data.stamp_ns[ep1]) == 40_000_000).all()  # one control period apart, nothing skipped

    env = MorphSwimmerEnv(num_joints=JOINTS)
    env.reset(seed=SEED)  # episode 0, as the sim's seeded reset
    obs, _ = env.reset()  # episode 1: the next draw of the same generator
    policy = GraphActorCritic.load(untrained_checkpoint)
    for i in ep1:
        np.testing.assert_array_equal(data.joint_pos[i, :JOINTS], obs["joint_pos"])
        np.testing.assert_array_equal(data.joint_vel[i, :JOINTS], obs["joint_vel"])
        np.testing.assert_allclose(data.global_feats[i], obs["global"], rtol=0, atol=1e-12)
        action = data.action[i, :JOINTS]
        with torch.no_grad():
            batch = ChainBatch.from_padded(
                obs["joint_pos"][None], obs["joint_vel"][None], obs["global"][None], [JOINTS]
            )
            mean = policy(batch)[0]
            expected = gaussian_log_prob(
                torch.as_tensor(action[None], dtype=torch.float32), mean, policy.log_std, batch.mask
            )
        assert data.log_prob[i] == pytest.approx(float(expected), abs=1e-4)  # float32 network vs float64 record
        # Stepped as training steps it: the sample clipped to the motors' range is what is charged.
        obs, reward, terminated, _, _ = env.step(applied_action(action))
        assert not terminated
        assert data.reward[i] == pytest.approx(reward, abs=1e-9)
