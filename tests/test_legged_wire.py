"""Centipedes learned from their topics on real DDS: recorded into a bag by the bring-up (``scripts/record.sh``),
read by ``morph-bag info`` and trained on by ``morph-train --from-bags``; and trained live
(``scripts/live.sh``) with the trainer's weights. Small runs: what is checked is that every stage runs and
reads the legged body as one (12 global features, falls ending episodes), not how well it learns.

Runs inside a private network namespace (``scripts/test.sh``).
"""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest

from morph_core.algo.run_dir import RunDir
from trainer.bags.contents import bag_task, read_bags
from trainer.bags.io import BagReader

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

FROM_BAGS = ["--num-envs", "1", "--num-steps", "32", "--minibatch-size", "16", "--update-epochs", "1",
             "--checkpoint-interval", "32", "--tensorboard", "false", "--progress-bar", "false",
             "--compile", "false"]  # fmt: skip
LIVE = ["--num-envs", "1", "--num-steps", "64", "--minibatch-size", "32", "--update-epochs", "1",
        "--compile", "false", "--tensorboard", "false", "--progress-bar", "false", "--checkpoint-interval", "64",
        "--silence-timeout", "5"]  # fmt: skip


def _rows(run) -> list[dict]:
    with open(RunDir(run).progress) as f:
        return list(csv.DictReader(f))


@pytest.mark.timeout(600)
def test_a_centipede_is_recorded_read_and_trained_from_its_bag(tmp_path, namespace):
    bag = tmp_path / "bag"
    # Episodes long enough to outlast DDS matching the policy to the recorder (the lockstep sim steps on zero
    # effort until the policy node answers), as tests/test_record.py's.
    record = [sys.executable, "-m", "trainer.bags.record_bringup", "--out", str(bag), "--episodes", "2",
              "--steps-per-episode", "200", "--bodies", "centipede:2", "--namespace", namespace,
              "--timeout", "200"]  # fmt: skip
    done = subprocess.run(record, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "bodies centipede:2" in done.stdout

    reader = BagReader(bag, namespace=namespace)
    reader.read()
    assert not reader.stats.rejected and reader.stats.counts["policy_info"] > 0
    assert bag_task(bag, namespace) == "ant"
    data, _, _ = read_bags([bag], namespace)
    assert data.global_width == 12 and len(data) > 0 and set(data.num_joints.tolist()) == {8}
    assert (data.terminated | data.truncated).sum() >= 1

    info = subprocess.run([sys.executable, "-m", "trainer.bags.cli", "info", str(bag)], capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert info.returncode == 0, info.stdout + info.stderr
    assert "centipede" in info.stdout or "tree-" in info.stdout, info.stdout

    run = tmp_path / "run"
    train = [sys.executable, "-m", "trainer.cli.train", "--from-bags", str(bag), "--bodies", "centipede:2",
             "--out", str(run), "--iterations", "1", *FROM_BAGS]  # fmt: skip
    done = subprocess.run(train, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert len(_rows(run)) == 1
    # Without --bodies the run's policy would read a swimmer's 4 features: refused in one line, nothing run.
    refused = subprocess.run([*train[:5], "--out", str(tmp_path / "other"), "--iterations", "1", *FROM_BAGS],
                             capture_output=True, text=True, timeout=300)  # fmt: skip
    assert refused.returncode != 0 and "12 global features" in refused.stderr, refused.stderr
    assert "Traceback" not in refused.stderr


@pytest.mark.timeout(600)
def test_centipedes_train_live_with_the_trainers_weights(tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "trainer.live.bringup", "--pairs", "1", "--bodies", "centipede:2", "--out",
           str(out), "--max-updates", "1", "--episode-steps", "60", "--real-time-factor", "0",
           "--startup-timeout", "120", "--timeout", "300", "--", *LIVE]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=420)
    log = done.stdout + done.stderr
    assert done.returncode == 0 and "timed out" not in log, log[-3000:]
    rows = _rows(out)
    assert len(rows) == 1 and int(rows[0]["batch_size"]) >= 64, log[-3000:]
    assert "received" in log  # the policy node adopted the trainer's (12-wide) weights
