"""``morph-train --from-bags`` on real bags: a swimmer and a sampling policy stepped in lockstep in this
process (protocol.loopback), every message serialized with the Jazzy type store and written by
trainer.bags.writer (MCAP and sqlite3), read back through trainer.bags.io. PPO from the bag, resume after a
SIGKILL equal to an uninterrupted run, the refusal of bags without policy_info, every bad input."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
from rosbags.typesys import Stores, get_typestore

from morph_core.algo.checkpoint import load_training_state
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import options_of, small
from morph_core.algo.train_from_data import run_state
from morph_core.env.bodies import star_parents, swimmer_tree, y_parents
from morph_core.msgs.records import (
    PolicyInfoRecord,
)
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.protocol.loopback import MeanController, SamplingController, record_episodes
from morph_core.protocol.transitions import SkipCounts
from trainer.bags.contents import read_bags
from trainer.bags.writer import BagTopic, BagWriter, WriterOptions
from trainer.cli.train import main
from trainer.codec import record_message

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
NS = "/swimmer"
TYPES = {
    "episode_start": "std_msgs/msg/Int64MultiArray",
    "joint_states": "sensor_msgs/msg/JointState",
    "odom": "nav_msgs/msg/Odometry",
    "effort_commands": "std_msgs/msg/Float64MultiArray",
    "policy_info": "trajectory_msgs/msg/JointTrajectory",
}
SMALL = options_of(small(num_envs=1, num_steps=32, minibatch_size=16, checkpoint_interval=32))
CLI = [sys.executable, "-m", "trainer.cli.train"]


# -- a lockstep recording as the nodes' messages, in a bag ----------------------------------------
def write_bag(path, records, storage="mcap", types=None, chunk_size=256 * 1024):
    """A bag as morph-record writes it; ``types`` overrides a topic's type (a message of that type is made by
    ``message`` unless the override is for a topic left out: type None drops the topic)."""
    types = {**TYPES, **(types or {})}
    with BagWriter(path, WriterOptions(storage=storage, chunk_size=chunk_size)) as w:
        ids = {name: w.add_topic(BagTopic(f"{NS}/{name}", ty)) for name, ty in types.items() if ty is not None}
        for r in records:
            name, msg = record_message(r)
            if name in ids:
                w.write(ids[name], r.log_ns, TS.serialize_cdr(msg, msg.__msgtype__))
    return path


# -- fixtures and helpers ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def init(tmp_path_factory):
    """The recording policy as a checkpoint."""
    torch.set_num_threads(1)
    torch.manual_seed(11)
    path = tmp_path_factory.mktemp("init") / "policy.safetensors"
    GraphActorCritic().save(path)
    return path


@pytest.fixture(scope="module")
def sampled(init):
    """Records of three episodes of 3, 6 and 9 joints sampled by the init policy (150 steps)."""
    return record_episodes(SamplingController(GraphActorCritic.load(init), seed=1), ((3, 60), (6, 50), (9, 40)))


def _rows(run):
    with RunDir(run).progress.open() as f:
        return list(csv.DictReader(f))


def _weights(run):
    tensors, meta = load_training_state(RunDir(run).state)
    return tensors, meta["counters"]


def _error(capsys) -> str:
    err = capsys.readouterr().err
    lines = [x for x in err.splitlines() if x.startswith("morph-train: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# -- PPO from a bag ------------------------------------------------------------------------------
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_ppo_from_a_bag_changes_the_policy_and_logs_per_dimension(tmp_path, init, sampled, storage, capsys):
    bag = write_bag(tmp_path / "bag", sampled, storage)
    run = tmp_path / "run"
    assert main(["--from-bags", str(bag), "--out", str(run), "--init", str(init), "--iterations", "2", *SMALL]) == 0
    out = capsys.readouterr().out
    assert "150 steps (3 episodes, chains of 3..9 joints) from 1 bag(s); 2 update(s) of up to 32 samples" in out
    before = GraphActorCritic.load(init).state_dict()
    tensors, counters = _weights(run)
    assert counters["iteration"] == 2 and counters["global_step"] == 60  # 150 steps in 5 parts of 30
    changed = [k for k in before if not torch.equal(before[k], tensors[f"policy.{k}"])]
    assert changed, "the policy did not change"
    rows = _rows(run)
    assert len(rows) == 2
    for r in rows:
        for k in ("policy_loss", "value_loss", "approx_kl", "clip_frac", "entropy", "is_weight_mean"):
            assert np.isfinite(float(r[k])), k
        assert float(r["approx_kl"]) >= 0.0
    logged = {d for r in rows for d in range(2, 11) if r[f"clip_frac_d{d}"] != ""}
    assert len(logged) >= 2 and logged <= {3, 6, 9}
    for r in rows:
        for d in logged & {d for d in range(2, 11) if r[f"clip_frac_d{d}"] != ""}:
            assert 0.0 <= float(r[f"clip_frac_d{d}"]) <= 1.0
    assert all(rows[0][f"return_d{d}"] != "" for d in (3, 6, 9)) and rows[0]["episodes"] == "3"
    # Recorded by the init policy: the first update is on-policy, the second sees an older policy's data.
    assert float(rows[0]["stale_frac"]) == 0.0 and float(rows[0]["is_weight_mean"]) == pytest.approx(1.0, abs=1e-5)
    assert float(rows[1]["stale_frac"]) == 1.0 and float(rows[1]["is_weight_mean"]) < 1.0
    ckpts = sorted(p.name for p in RunDir(run).checkpoints.glob("*.safetensors"))
    assert ckpts == ["policy_00000060.safetensors"]  # 30 did not reach the interval of 32 samples; 60 did
    assert GraphActorCritic.load(RunDir(run).checkpoints / ckpts[-1]) is not None  # loads as the policy node would


@pytest.mark.slow
def test_killed_run_resumes_exactly_and_refuses_other_bags(tmp_path, init, sampled, capsys):
    bag = write_bag(tmp_path / "bag", sampled)
    other = write_bag(tmp_path / "other", sampled[: len(sampled) // 2], "sqlite3")
    args = ["--from-bags", str(bag), "--init", str(init), "--iterations", "200", "--seed", "5", *SMALL]
    ref = tmp_path / "ref"
    subprocess.run([*CLI, *args, "--out", str(ref)], check=True, capture_output=True, timeout=600)
    run = tmp_path / "killed"
    proc = subprocess.Popen([*CLI, *args, "--out", str(run)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    # Kill it mid-run, once it has checkpointed a few times: polling files the child writes.
    while time.monotonic() < deadline and proc.poll() is None:
        if RunDir(run).state.exists() and RunDir(run).progress.exists() and len(_rows(run)) >= 5:
            break
        time.sleep(0.005)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    killed_at = run_state(run)["done"]
    assert killed_at < 200, "the run finished before it could be killed; make it longer"

    # Other bags, as a resume or as new data while updates are left: refused, nothing changed.
    assert main(["--from-bags", str(other), "--out", str(run), "--resume", *SMALL]) == 1
    assert "trains on other data" in _error(capsys)
    assert main(["--from-bags", str(other), "--out", str(run), "--resume", "--new-data", *SMALL]) == 1
    assert "updates left on its data" in _error(capsys)
    assert main(["--from-bags", str(bag), "--out", str(run), "--resume", "--init", str(init), *SMALL]) == 1
    assert "--init starts a new run" in _error(capsys)
    assert main(["--from-bags", str(bag), "--out", str(run), *SMALL]) == 1
    assert "already holds a run" in _error(capsys)
    assert run_state(run)["done"] == killed_at

    subprocess.run([*CLI, "--from-bags", str(bag), "--out", str(run), "--resume"], check=True, timeout=600)
    (w_ref, c_ref), (w_run, c_run) = _weights(ref), _weights(run)
    assert c_ref == c_run and c_ref["iteration"] == 200
    assert w_ref.keys() == w_run.keys()
    for k in w_ref:
        assert torch.equal(w_ref[k], w_run[k]), k  # weights, Adam moments, generator, pass order
    assert [r["global_step"] for r in _rows(run)] == [r["global_step"] for r in _rows(ref)]
    assert [r["policy_loss"] for r in _rows(run)] == [r["policy_loss"] for r in _rows(ref)]


def test_a_finished_run_resumed_says_so_and_options_given_are_written_back(tmp_path, init, sampled, capsys):
    bag = write_bag(tmp_path / "bag", sampled)
    run = tmp_path / "run"
    config = lambda: json.loads(RunDir(run).config.read_text())  # noqa: E731
    assert main(["--from-bags", str(bag), "--out", str(run), "--init", str(init), "--iterations", "2", *SMALL]) == 0
    capsys.readouterr()
    assert main(["--from-bags", str(bag), "--out", str(run), "--resume"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        f"morph-train: {run} already finished at update 2 (2 updates on these bags): nothing to do; raise "
        "--iterations to go on, or train on new bags with --resume --new-data"
    ]
    assert run_state(run)["done"] == 2
    assert main(["--from-bags", str(bag), "--out", str(run), "--resume", "--iterations", "3",
                 "--minibatch-size", "8"]) == 0  # fmt: skip
    assert "morph-train: resumed with minibatch_size 16 -> 8" in capsys.readouterr().out
    assert config()["minibatch_size"] == 8 and run_state(run)["done"] == 3
    # The optimizer's state comes back with the learning rate and epsilon given (issue 39: they were refused).
    assert main(["--from-bags", str(bag), "--out", str(run), "--resume", "--iterations", "4",
                 "--learning-rate", "0.003", "--adam-eps", "1e-6"]) == 0  # fmt: skip
    assert "morph-train: resumed with learning_rate 0.01 -> 0.003, adam_eps 1e-05 -> 1e-06" in capsys.readouterr().out
    assert config()["learning_rate"] == 0.003 and run_state(run)["done"] == 4
    assert [float(r["learning_rate"]) for r in _rows(run)] == [0.01, 0.01, 0.01, 0.003]
    groups = load_training_state(RunDir(run).state)[1]["param_groups"]
    assert [(g["lr"], g["eps"]) for g in groups] == [(0.003, 1e-6)]


def test_updates_far_above_the_kl_target_are_warned_about_and_the_run_summed_up(tmp_path, init, sampled, capsys):
    bag = write_bag(tmp_path / "bag", sampled)
    run = tmp_path / "run"
    # The warning's limit is 10 x --kl-target (a target the compensated rule does not use: the updates are
    # the same as at the default): these updates' KL is above 1e-7, far below the default's 0.1.
    args = ["--from-bags", str(bag), "--out", str(run), "--init", str(init), "--iterations", "2", "--kl-target", "1e-8"]
    assert main([*args, *SMALL]) == 0
    out, err = capsys.readouterr()
    rows = _rows(run)
    warnings = [line for line in err.splitlines() if line.startswith("morph-train: warning: update")]
    assert warnings == [
        f"morph-train: warning: update {r['iteration']} (step {r['global_step']}): approximate KL "
        f"{float(r['approx_kl']):.3g} > 1e-07 (10x kl_target): the policy moved far from the one that acted; a "
        "lower --learning-rate keeps it closer (a trained policy given with --init: e.g. --learning-rate 0.001)"
        for r in rows
    ]
    top = max(float(r["approx_kl"]) for r in rows)
    assert out.splitlines()[-2:] == [
        f"morph-train: done: step 60 (update 2); return of the recorded episodes {float(rows[-1]['return_mean']):.1f}"
        f"; last update's approximate KL {float(rows[-1]['approx_kl']):.3g}; 2 of 2 updates above KL 1e-07 (max "
        f"{top:.3g})",
        f"morph-train: files in {run}: config.json, progress.csv, checkpoints/ (1, the last "
        "policy_00000060.safetensors), state.safetensors (for --resume)",
    ]
    assert main(["--from-bags", str(bag), "--out", str(tmp_path / "quiet"), "--init", str(init), "--iterations", "2",
                 "--kl-target", "1", *SMALL]) == 0  # fmt: skip
    assert "warning" not in capsys.readouterr().err and max(float(r["approx_kl"]) for r in rows) < 10


# -- bad input -----------------------------------------------------------------------------------
def test_a_bag_without_policy_info_is_refused_naming_what_is_missing(tmp_path, init, capsys):
    records = record_episodes(MeanController(GraphActorCritic.load(init)), ((3, 20),))
    bag = write_bag(tmp_path / "deterministic", records, types={"policy_info": None})
    run = tmp_path / "run"
    assert main(["--from-bags", str(bag), "--out", str(run), *SMALL]) == 1
    line = _error(capsys)
    assert "20 of 20 steps have no policy_info" in line and "morph_policy_node deterministic:=false" in line
    assert not RunDir(run).state.exists() and not RunDir(run).progress.exists()


def test_bad_bags_give_one_line_errors_naming_the_file(tmp_path, sampled, capsys):
    def fails(path, *extra) -> str:
        assert main(["--from-bags", str(path), "--out", str(tmp_path / "run"), *extra, *SMALL]) == 1
        return _error(capsys)

    assert "no such file or directory" in fails(tmp_path / "nothing") and str(tmp_path / "nothing") in fails(
        tmp_path / "nothing"
    )
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("hello")
    assert "not a rosbag2 bag" in fails(tmp_path / "junk")
    (tmp_path / "fake.mcap").write_bytes(b"not an mcap file at all")
    assert f"{tmp_path / 'fake.mcap'}: not an MCAP file" in fails(tmp_path / "fake.mcap")
    no_odom = write_bag(tmp_path / "no_odom", sampled, types={"odom": None})
    line = fails(no_odom)
    assert str(no_odom) in line and "required topic /swimmer/odom is not in the bag" in line
    wrong = write_bag(tmp_path / "wrong", [r for r in sampled if not isinstance(r, PolicyInfoRecord)],
                      types={"policy_info": "std_msgs/msg/String"})  # fmt: skip
    line = fails(wrong)
    assert "wrong_0.mcap" in line and "/swimmer/policy_info has type std_msgs/msg/String" in line
    assert "not a policy checkpoint" in fails(write_bag(tmp_path / "ok", sampled), "--init", str(tmp_path / "x.bin"))
    assert not (tmp_path / "run").exists()  # nothing was created for any of them


def test_a_truncated_bag_trains_on_its_valid_prefix_with_a_warning(tmp_path, sampled, capsys):
    whole = write_bag(tmp_path / "whole", sampled, chunk_size=4096)
    cut = tmp_path / "cut"
    cut.mkdir()
    data = (whole / "whole_0.mcap").read_bytes()
    (cut / "cut_0.mcap").write_bytes(data[: len(data) // 2])  # a recorder killed mid-write: no metadata.yaml
    run = tmp_path / "run"
    assert main(["--from-bags", str(cut), "--out", str(run), "--iterations", "1", *SMALL]) == 0
    captured = capsys.readouterr()
    assert "morph-train: warning:" in captured.err and "cut_0.mcap: incomplete MCAP file" in captured.err
    steps = int(captured.out.split("morph-train: ")[1].split(" steps")[0])
    assert 0 < steps < 150
    assert run_state(run)["steps"] == steps


def test_options_of_bag_training_need_from_bags(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "x"), "--iterations", "2"])
    assert "--iterations: only with --from-bags" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--from-bags", "b", "--out", str(tmp_path / "x"), "--new-data"])
    assert "--new-data continues a run: pass --resume too" in capsys.readouterr().err
    assert main(["--from-bags", "b", "--out", str(tmp_path / "x"), "--resume"]) == 1
    assert "no run to resume" in _error(capsys)


def test_a_few_lost_policy_infos_are_warned_about_and_left_out_of_the_updates(tmp_path, sampled, capsys):
    infos = [i for i, r in enumerate(sampled) if isinstance(r, PolicyInfoRecord)]
    dropped = {infos[10], infos[70], infos[71]}  # the efforts of those steps are there: the steps stay
    bag = write_bag(tmp_path / "bag", [r for i, r in enumerate(sampled) if i not in dropped])
    run = tmp_path / "run"
    one_batch = options_of(small(num_envs=1, num_steps=256, minibatch_size=16, checkpoint_interval=32))  # one update
    assert main(["--from-bags", str(bag), "--out", str(run), *one_batch]) == 0
    captured = capsys.readouterr()
    assert "morph-train: warning: 3 of 150 steps have no policy_info" in captured.err
    (row,) = _rows(run)
    assert (row["data_steps"], row["usable_steps"], row["batch_size"]) == ("150", "147", "147")


# -- branched swimmers ----------------------------------------------------------------------------------
TREES = (swimmer_tree(star_parents(2, 2)), swimmer_tree(y_parents(1, 2)), swimmer_tree([-1, 0, 1, 0, -1]))


def test_ppo_from_a_bag_of_branched_swimmers_reads_each_step_on_its_tree(tmp_path, init, capsys):
    """Joints listed in another order at every state, efforts naming theirs, the robot_description before each
    body: the bag trains on the described trees and its log shows them."""
    records = record_episodes(
        SamplingController(GraphActorCritic.load(init), seed=5),
        tuple(zip(TREES, (40, 30, 30), strict=True)),
        describe=True,
        shuffle_seed=3,
        name_efforts=True,
    )
    bag = write_bag(tmp_path / "bag", records, types={"robot_description": "std_msgs/msg/String"})
    data, warnings, skips = read_bags([bag])
    assert not warnings and skips == SkipCounts() and len(data) == 100
    for episode, tree in enumerate(TREES):  # every step on its body's tree, its joints in the tree's order
        rows = data.parents[data.episode == episode, : tree.num_joints]
        assert (rows == tree.parents).all()
    run = tmp_path / "run"
    assert main(["--from-bags", str(bag), "--out", str(run), "--init", str(init), "--iterations", "2", *SMALL]) == 0
    out = capsys.readouterr().out
    assert "100 steps (3 episodes, 4..5 joints: star-2x2 40, y-1x2 30, tree-" in out and " 30 steps) from 1 bag" in out
    before = GraphActorCritic.load(init).state_dict()
    tensors, counters = _weights(run)
    assert counters["iteration"] == 2
    assert [k for k in before if not torch.equal(before[k], tensors[f"policy.{k}"])], "the policy did not change"
    rows = _rows(run)
    assert len(rows) == 2 and all(np.isfinite(float(r["approx_kl"])) for r in rows)
    assert rows[0]["return_chains"] == "" and np.isfinite(float(rows[0]["return_trees"]))
    assert float(rows[0]["return_trees"]) == pytest.approx(float(rows[0]["return_mean"]))
    # On-policy first update: the policy's log-prob of each step on its tree is the one recorded.
    assert float(rows[0]["stale_frac"]) == 0.0 and float(rows[0]["is_weight_mean"]) == pytest.approx(1.0, abs=1e-5)
