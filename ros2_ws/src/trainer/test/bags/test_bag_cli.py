"""``morph-bag`` on real bags: a swimmer and a real policy stepped in lockstep in this process, every
message serialized with the Jazzy type store and written by rosbags (MCAP and sqlite3), then read back
through trainer.bags.io. The export must equal the transitions of the records that were written."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from morph_core.algo.run_dir import RunDir
from morph_core.env.bodies import star_parents, swimmer_tree, y_parents
from morph_core.env.urdf import swimmer_urdf
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
)
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.config import PolicyConfig
from morph_core.protocol.joint_map import JointMap
from morph_core.protocol.loopback import MeanController, SamplingController, record_episodes
from morph_core.protocol.transition_batch import EXPORT_KEYS, TransitionBatch
from morph_core.protocol.transitions import SkipCounts, TransitionConfig, assemble
from trainer.bags.cli import main
from trainer.bags.contents import summarize_bag
from trainer.codec import header, record_message, stamp

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
NS = "/swimmer"
TOPICS = {
    "episode_start": "std_msgs/msg/Header",
    "joint_states": "sensor_msgs/msg/JointState",
    "odom": "nav_msgs/msg/Odometry",
    "effort_commands": "std_msgs/msg/Float64MultiArray",
    "policy_info": "trajectory_msgs/msg/JointTrajectory",
}


@pytest.fixture(scope="module")
def policy():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    return GraphActorCritic().eval()


# -- records as the nodes' messages --------------------------------------------------------------
def message(r):
    """(topic, message) a node publishes for a record; the announcement as another recorder's stamped Header."""
    if isinstance(r, EpisodeStartRecord):
        return "episode_start", header(r.stamp_ns, f"episode={r.episode} num_joints={r.num_joints}")
    return record_message(r)


def write_bag(path, records, storage="mcap", with_clock=True):
    """A bag as rosbag2 would record the nodes (plus /clock, which the reader skips)."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    topics = dict(TOPICS)
    if any(isinstance(r, DescriptionRecord) for r in records):
        topics["robot_description"] = "std_msgs/msg/String"
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {name: w.add_connection(f"{NS}/{name}", ty, typestore=TS) for name, ty in topics.items()}
        clock = w.add_connection("/clock", "rosgraph_msgs/msg/Clock", typestore=TS)
        for r in records:
            name, msg = message(r)
            if with_clock and name == "joint_states":
                tick = T["rosgraph_msgs/msg/Clock"](clock=stamp(r.stamp_ns))
                w.write(clock, r.log_ns - 1, TS.serialize_cdr(tick, "rosgraph_msgs/msg/Clock"))
            w.write(conns[name], r.log_ns, TS.serialize_cdr(msg, msg.__msgtype__))
    return path


@pytest.fixture(scope="module")
def sampled_records(policy):
    return record_episodes(SamplingController(policy, seed=1), ((3, 20), (6, 15)))


# -- export --------------------------------------------------------------------------------------
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_export_equals_the_transitions_of_the_recorded_messages(tmp_path, sampled_records, storage, capsys):
    bag = write_bag(tmp_path / "run", sampled_records, storage)
    out = tmp_path / "transitions.npz"
    assert main(["export", str(bag), "--out", str(out), "--require-policy-info"]) == 0
    text = capsys.readouterr().out
    assert "wrote 35 steps (2 episodes, chains of 3..6 joints, 35 with policy_info)" in text

    expected = assemble(sampled_records).batch
    with np.load(out) as data:
        assert tuple(data.files) == EXPORT_KEYS
    got = TransitionBatch.from_npz(out)
    for k, v in expected.arrays().items():
        np.testing.assert_array_equal(got.arrays()[k], v, err_msg=k)
    assert np.bincount(got.episode).tolist() == [20, 15] and got.ppo_ready


def test_several_bags_export_as_separate_streams(tmp_path, sampled_records, policy):
    other = record_episodes(SamplingController(policy, seed=2), ((4, 12),), seed=5)
    a = write_bag(tmp_path / "a", sampled_records)
    b = write_bag(tmp_path / "b", other, "sqlite3")
    out = tmp_path / "both.npz"
    assert main(["export", str(a), str(b), "--out", str(out)]) == 0
    got = TransitionBatch.from_npz(out)
    expected = TransitionBatch.concatenate([assemble(sampled_records).batch, assemble(other).batch])
    for k, v in expected.arrays().items():
        np.testing.assert_array_equal(got.arrays()[k], v, err_msg=k)
    assert got.num_episodes == 3


def test_a_bag_exports_chains_of_message_order_unless_a_robot_is_given(tmp_path, sampled_records):
    bag = write_bag(tmp_path / "run", sampled_records)
    out = tmp_path / "t.npz"
    assert main(["export", str(bag), "--out", str(out)]) == 0
    got = TransitionBatch.from_npz(out)
    assert got.is_chains and got.parents[-1].tolist() == [-1, 0, 1, 2, 3, 4]
    # A robot known otherwise than from the bag (a URDF): its tree, here a star under joint 0, for the states whose
    # joints it has; the 3-joint states lack three of its six joints.
    star = JointMap.from_urdf(swimmer_urdf([-1, 0, 0, 0, 0, 0]))
    summary = summarize_bag(bag, TransitionConfig(), joint_map=star)
    trees = summary.batch
    assert summary.skips.missing_joint == 20 and trees.num_joints.tolist() == [6] * 15
    assert (trees.parents == [-1, 0, 0, 0, 0, 0]).all()
    for k, v in got.arrays().items():
        if k not in ("parents", "episode"):
            np.testing.assert_array_equal(trees.arrays()[k], v[20:], err_msg=k)


def test_without_policy_info_export_says_so_and_can_refuse(tmp_path, policy, capsys):
    records = record_episodes(MeanController(policy), ((3, 10),))
    bag = write_bag(tmp_path / "deterministic", records)
    out = tmp_path / "t.npz"
    assert main(["export", str(bag), "--out", str(out), "--require-policy-info"]) == 1
    assert "10 of 10 steps have no policy_info" in capsys.readouterr().err
    assert not out.exists()
    assert main(["export", str(bag), "--out", str(out)]) == 0
    assert "usable for PPO: 0 (10 without policy_info" in capsys.readouterr().out
    got = TransitionBatch.from_npz(out)
    assert len(got) == 10 and not got.has_policy_info.any() and np.isnan(got.log_prob).all()


# -- info ----------------------------------------------------------------------------------------
def test_info_counts_topics_episodes_chains_and_skips(tmp_path, sampled_records, capsys):
    # spoil two things: an odometry dropped (two steps lost) and an effort for a stamp that never was
    states = [r.stamp_ns for r in sampled_records if isinstance(r, JointStateRecord)]
    records = [r for r in sampled_records if not (isinstance(r, OdometryRecord) and r.stamp_ns == states[5])]
    stray = EffortRecord(records[40].log_ns, states[7] + 1, np.zeros(3))
    records = records[:40] + [stray] + records[40:]
    records = [dataclasses.replace(r, log_ns=i * 1000 + 1000) for i, r in enumerate(records)]
    bag = write_bag(tmp_path / "spoiled", records)

    assert main(["info", str(bag), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    info = doc["bags"][0]
    assert info == doc["total"]
    topics = {t["topic"]: t["messages"] for t in info["topics"]}
    count = {kind: sum(isinstance(r, kind) for r in records) for kind in (JointStateRecord, OdometryRecord)}
    assert topics[f"{NS}/joint_states"] == count[JointStateRecord] == topics["/clock"] == 37
    assert topics[f"{NS}/odom"] == count[OdometryRecord] == 36
    assert topics[f"{NS}/effort_commands"] == 38 and topics[f"{NS}/policy_info"] == 37
    assert topics[f"{NS}/episode_start"] == 2
    assert info["episodes"] == 3 and info["boundaries"] == {"announced": 1, "new_chain": 0, "stamp_gap": 0}
    assert info["steps"] == info["steps_usable_for_ppo"] == 33
    assert info["steps_per_chain"] == {"3": 18, "6": 15}
    assert info["skipped_steps"]["no_odometry"] == 2 and sum(info["skipped_steps"].values()) == 2
    assert info["unused_messages"]["orphan_effort"] == 1 and sum(info["unused_messages"].values()) == 1

    assert info["robot_description"] == {"messages": 0, "bodies": []}
    assert info["steps_per_body"] == {"chain-3": 18, "chain-6": 15}

    assert main(["info", str(bag)]) == 0
    text = capsys.readouterr().out
    assert "skipped steps: no_odometry 2" in text and "unused messages: orphan_effort 1" in text
    assert "steps: 33 (3 joints: 18, 6 joints: 15)" in text and "usable for PPO: 33" in text
    assert "no robot_description: joints taken as chains in message order" in text
    assert "bodies: chain-3 18, chain-6 15" in text


def test_info_names_the_described_robots_and_export_reads_their_trees(tmp_path, policy, sampled_records, capsys):
    """Branched swimmers, joints listed in another order at every state, efforts naming theirs."""
    trees = (swimmer_tree(star_parents(2, 2)), swimmer_tree(y_parents(1, 2)))
    records = record_episodes(SamplingController(policy, seed=3), ((trees[0], 12), (trees[1], 10)), describe=True,
                              shuffle_seed=2, name_efforts=True)  # fmt: skip
    bag = write_bag(tmp_path / "trees", records)
    assert main(["info", str(bag), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)["total"]
    assert info["robot_description"] == {"messages": 2, "bodies": ["star-2x2", "y-1x2"]}
    assert info["steps_per_body"] == {"star-2x2": 12, "y-1x2": 10} and info["steps"] == 22
    assert not any(info["skipped_steps"].values()) and not any(info["unused_messages"].values())
    assert main(["info", str(bag)]) == 0
    text = capsys.readouterr().out
    assert "robot_description: 2 (star-2x2, y-1x2)" in text and "bodies: star-2x2 12, y-1x2 10" in text
    assert "no robot_description" not in text

    chains = write_bag(tmp_path / "chains", sampled_records)
    out = tmp_path / "both.npz"
    assert main(["export", str(bag), str(chains), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "no robot_description" in text and "robot_description: 2 (star-2x2, y-1x2)" in text
    assert "wrote 57 steps (4 episodes, 3..6 joints: star-2x2 12, y-1x2 10, chain-3 20, chain-6 15 steps" in text
    got = TransitionBatch.from_npz(out)
    expected = TransitionBatch.concatenate([assemble(records).batch, assemble(sampled_records).batch])
    for k, v in expected.arrays().items():
        np.testing.assert_array_equal(got.arrays()[k], v, err_msg=k)
    assert got.parents[0, :4].tolist() == trees[0].parents.tolist() and not got.is_chains


def test_options_reach_the_assembly(tmp_path, sampled_records, capsys):
    bag = write_bag(tmp_path / "run", sampled_records)
    # a control period the stamps do not have: every pair is a gap, no steps
    assert main(["info", str(bag), "--json", "--control-period", "0.05"]) == 0
    info = json.loads(capsys.readouterr().out)["total"]
    assert info["steps"] == 0 and info["boundaries"]["stamp_gap"] == 37 - 1 - 1  # 37 states, 1 announced
    assert main(["export", str(bag), "--out", str(tmp_path / "x.npz"), "--control-period", "0.05"]) == 1
    assert "no usable steps" in capsys.readouterr().err
    assert main(["info", str(bag), "--settle-states", "-1"]) == 1
    assert ">= 0" in capsys.readouterr().err


def test_bad_bags_give_clear_errors(tmp_path, capsys):
    assert main(["info", str(tmp_path / "nothing")]) == 1
    assert "no such file or directory" in capsys.readouterr().err
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "x.txt").write_text("hello")
    assert main(["info", str(tmp_path / "junk")]) == 1
    assert "not a rosbag2 bag" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["export", str(tmp_path / "junk")])  # --out missing: argparse usage error


@pytest.mark.slow
def test_runs_as_a_module(tmp_path, sampled_records):
    bag = write_bag(tmp_path / "run", sampled_records)
    done = subprocess.run(
        [sys.executable, "-m", "trainer.bags.cli", "info", str(bag)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert f"{NS}/joint_states" in done.stdout and "usable for PPO: 35" in done.stdout


def test_states_recorded_before_the_bags_first_description_are_read_on_it(tmp_path, policy, capsys):
    """A recorder whose description reader matched after its state reader: the latched URDF comes a few states
    late. Those states were published while it was the robot's, and are read on it (not as chains)."""
    tree = swimmer_tree(y_parents(1, 2))
    records = record_episodes(SamplingController(policy, seed=4), ((tree, 25),), describe=True, shuffle_seed=5,
                              name_efforts=True)  # fmt: skip
    states = [i for i, r in enumerate(records) if isinstance(r, JointStateRecord)]
    (first,) = [i for i, r in enumerate(records) if isinstance(r, DescriptionRecord)]
    late = records[:first] + records[first + 1 : states[6]] + [records[first]] + records[states[6] :]
    late = [dataclasses.replace(r, log_ns=1000 * (i + 1)) for i, r in enumerate(late)]
    on_time = summarize_bag(write_bag(tmp_path / "on_time", records), TransitionConfig()).batch
    summary = summarize_bag(write_bag(tmp_path / "late", late), TransitionConfig())
    assert summary.skips == SkipCounts() and summary.stats.boundaries == 0 and len(summary.batch) == 25
    for k, v in on_time.arrays().items():
        np.testing.assert_array_equal(summary.batch.arrays()[k], v, err_msg=k)
    # Read as the stream alone says (no bag to look ahead in): the first states are chains in their message order,
    # each in an order of its own, so hardly a step among them.
    alone = assemble(late).batch
    assert len(alone) < 25 and (alone.parents[-1, :5] == tree.parents).all()


def test_a_bag_of_a_body_in_3d_is_read_as_a_legged_bodys(tmp_path, sampled_records, capsys):
    """A body whose odometry leaves the plane is a legged one (``bag_task``): its steps are Ant-v5's, with 12
    global features (``trainer/test/bags/test_legged_bags.py`` trains on a centipede's)."""
    tilt = (0.05, -0.02, 0.3, float(np.sqrt(1 - 0.05**2 - 0.02**2 - 0.3**2)))
    records = [dataclasses.replace(r, orientation_xyzw=tilt) if isinstance(r, OdometryRecord) else r
               for r in sampled_records]  # fmt: skip
    bag = write_bag(tmp_path / "legs", records)
    # (a swimmer tilted: its states 0.04 s apart, a centipede's would be 0.05)
    assert main(["export", str(bag), "--out", str(tmp_path / "t.npz"), "--control-period", "0.04"]) == 0
    assert "task: ant" in capsys.readouterr().out
    assert TransitionBatch.from_npz(tmp_path / "t.npz").global_width == 12


def test_info_names_a_body_by_what_it_is():
    """The ant is no swimmer of the star-4x2 shape; a centipede is named by its size (the sim's robot names)."""
    import mujoco

    from morph_core.env.centipede_model import ant_mjcf, centipede_mjcf
    from morph_core.env.urdf import robot_urdf
    from morph_core.policy.tree import read_urdf
    from trainer.bags.contents import described_body

    def named(urdf: str) -> str:
        return described_body(urdf, read_urdf(urdf).tree)

    ant = robot_urdf(mujoco.MjModel.from_xml_string(ant_mjcf()))
    assert named(ant) == "robot 'ant' (star-4x2 tree)"
    assert named(robot_urdf(mujoco.MjModel.from_xml_string(centipede_mjcf(5)))) == "centipede-5"
    assert named(swimmer_urdf(swimmer_tree(star_parents(4, 2)))) == "star-4x2"
    assert named(swimmer_urdf(swimmer_tree(y_parents(1, 2)))) == "y-1x2"


def test_info_says_why_a_bag_gave_no_step_when_none_was_skipped(tmp_path, sampled_records, capsys):
    """'steps: 0' and 'skipped steps: none' said nothing: the line names why there was no step to skip."""
    firsts, seen = [], set()
    for r in sampled_records:  # each episode's first state alone: no next state, so no step and nothing skipped
        if isinstance(r, JointStateRecord):
            if len(r.names) in seen:
                continue
            seen.add(len(r.names))
        firsts.append(r)
    bag = write_bag(tmp_path / "firsts", firsts)
    assert main(["info", str(bag)]) == 0
    text = capsys.readouterr().out
    line = next(x for x in text.splitlines() if "skipped steps:" in x)
    assert "steps: 0" in text and "none followed by a next state of its episode" in line, text
    from trainer.cli.train import main as train_main

    assert train_main(["--from-bags", str(bag), "--out", str(tmp_path / "run"), "--compile", "false"]) == 1
    err = capsys.readouterr().err  # morph-train --from-bags said "(skipped: none)" and no more
    assert "(skipped: none; " in err and "none followed by a next state" in err and len(err.splitlines()) == 1
    only_odometry = write_bag(tmp_path / "odom", [r for r in sampled_records if isinstance(r, OdometryRecord)])
    assert main(["info", str(only_odometry)]) == 0
    assert "no joint_states of the robot's topics were read" in capsys.readouterr().out


def test_training_a_policy_that_reads_joint_descriptions_from_the_topics_is_refused_in_one_line(
    tmp_path, sampled_records, capsys
):
    """The transitions rebuilt from bags or a live stream do not carry joint descriptions: morph-train says so at
    once, for a fresh policy of joint_features 11 and for an --init checkpoint that reads them."""
    from trainer.cli.train import main as train_main
    from trainer.train_options import check_live

    bag = write_bag(tmp_path / "bag", sampled_records)
    init = tmp_path / "described.safetensors"
    GraphActorCritic(PolicyConfig(global_features=12, joint_features=11)).save(init)
    for extra in (["--policy-joint-features", "11"], ["--init", str(init)]):
        assert train_main(["--from-bags", str(bag), "--out", str(tmp_path / "run"), "--compile", "false", *extra]) == 1
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and "reads joint descriptions (joint_features 11)" in err, err
        assert not RunDir(tmp_path / "run").state.exists()
        with pytest.raises(SystemExit):
            check_live(["--live", "--namespaces", "a", "--out", str(tmp_path / "live"), *extra])
        assert "training from the topics (--from-bags, --live) does not carry them yet" in capsys.readouterr().err
