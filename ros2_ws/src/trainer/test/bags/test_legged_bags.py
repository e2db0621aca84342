"""Legged bodies through bags: the 3-D odometry written and read back, old planar bags read as before, a
centipede's bag turned into Ant-v5's transitions (``morph-bag``, ``morph-train --from-bags``), and the 3-D
odometry fuzzed on the bag path."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from morph_core.algo.run_dir import RunDir
from morph_core.env.sim import SwimmerSim
from morph_core.msgs.records import EpisodeStartRecord, OdometryRecord
from morph_core.policy.config import PolicyConfig
from morph_core.policy.weights import untrained_weights
from morph_core.protocol.loopback import GaussianController, LoopbackRecording, SamplingController, record_episodes
from morph_core.protocol.transitions import SkipCounts, TransitionAssembler, TransitionConfig
from trainer.bags.contents import bag_config, bag_task, read_bags
from trainer.bags.io import read_bag
from trainer.bags.writer import BagTopic, BagWriter, WriterOptions
from trainer.codec import TOPIC_TYPES, odometry_record, record_message

TS = get_typestore(Stores.ROS2_JAZZY)
NS = "/robot"


def write_bag(path, records):
    with BagWriter(path, WriterOptions()) as w:
        ids = {name: w.add_topic(BagTopic(f"{NS}/{name}", ty)) for name, ty in TOPIC_TYPES.items()}
        for r in records:
            name, msg = record_message(r)
            w.write(ids[name], r.log_ns, TS.serialize_cdr(msg, msg.__msgtype__))
    return path


def centipede_records(steps: int = 120) -> list:
    sim = SwimmerSim(bodies="centipede:2-3", seed=5, effort_timeout=None)
    legged = untrained_weights(PolicyConfig(global_features=12), seed=1)
    loop = LoopbackRecording(sim, SamplingController(legged, seed=7), describe=True)
    for i in range(2):
        if i:
            loop.new_episode()
        loop.run(steps)
    loop.finish()
    return loop.records


@pytest.fixture(scope="module")
def centipede_bag(tmp_path_factory):
    records = centipede_records()
    return write_bag(tmp_path_factory.mktemp("legged") / "bag", records), records


def test_the_3d_odometry_and_the_fall_cause_read_back_as_written(centipede_bag):
    path, records = centipede_bag
    back, stats = read_bag(path)
    assert not stats.rejected and len(back) == len(records)
    odometry = [(a, b) for a, b in zip(back, records, strict=True) if isinstance(b, OdometryRecord)]
    assert odometry and not any(b.planar for _, b in odometry)
    for a, b in odometry:
        assert a == b  # every field: z, the body-frame linear z, the angular x and y
    causes = [r.cause for r in back if isinstance(r, EpisodeStartRecord)]
    assert "fell" in causes and causes == ["start", *causes[1:]]
    assert [c for c in causes if c == "fell"] == [r.cause for r in records if isinstance(r, EpisodeStartRecord)
                                                   and r.cause == "fell"]  # fmt: skip


def test_an_old_planar_bag_reads_as_before(tmp_path):
    # A bag of a swimmer as the nodes recorded it before the record held 3-D fields (they were zero on the wire
    # then as now): its odometry reads with the zero defaults, its transitions are the swimmer's.
    records = record_episodes(GaussianController(seed=2), [(3, 30)])
    path = write_bag(tmp_path / "old", records)
    back, _ = read_bag(path)
    old = [r for r in back if isinstance(r, OdometryRecord)]
    assert old and all(r.planar and r.z == 0.0 and r.body_linear_z == 0.0 and r.angular_xy == (0.0, 0.0) for r in old)
    assert old == [r for r in records if isinstance(r, OdometryRecord)]
    assert bag_task(path) == "swimmer" and bag_config(path, TransitionConfig()).task == "swimmer"
    data, _, skips = read_bags([path])
    assert data.global_width == 4 and len(data) == 30 and skips == SkipCounts() and not data.terminated.any()


def test_a_centipedes_bag_gives_ant_transitions(centipede_bag):
    path, records = centipede_bag
    assert bag_task(path) == "ant"
    assert bag_config(path, TransitionConfig(settle_states=3)) == TransitionConfig(task="ant", settle_states=3)
    data, _, skips = read_bags([path])
    assert skips == SkipCounts() and data.global_width == 12
    falls = sum(isinstance(r, EpisodeStartRecord) and r.cause == "fell" for r in records)
    assert falls >= 1 and data.terminated.sum() == falls
    asm = TransitionAssembler(TransitionConfig(task="ant"))
    direct = asm.push_many(records) + asm.flush()
    np.testing.assert_array_equal(data.reward, [t.reward for t in direct])  # the bag holds what was recorded


@pytest.mark.slow
def test_morph_bag_info_and_export_of_a_centipedes_bag(centipede_bag, tmp_path):
    path, _ = centipede_bag
    out = subprocess.run([sys.executable, "-m", "trainer.bags.cli", "export", str(path), "--out",
                          str(tmp_path / "t.npz")], capture_output=True, text=True)  # fmt: skip
    assert out.returncode == 0, out.stderr
    from morph_core.protocol.transition_batch import TransitionBatch

    assert TransitionBatch.from_npz(tmp_path / "t.npz").global_width == 12
    assert "task: ant" in out.stdout
    info = subprocess.run([sys.executable, "-m", "trainer.bags.cli", "info", "--json", str(path)],
                          capture_output=True, text=True)  # fmt: skip
    total = json.loads(info.stdout)["total"]
    assert total["task"] == "ant" and total["steps_terminated"] >= 1


# -- fuzz: the 3-D odometry on the bag path ------------------------------------------------------------
def _fuzzed(rng, stamp_ns: int) -> OdometryRecord:
    """An odometry for ``stamp_ns`` whose fields (the 3-D ones too) are drawn from values a broken source might
    send."""
    special = [math.nan, math.inf, -math.inf, 1e308, -1e308, 0.0, 1e-320, 0.5]

    def value():
        return float(rng.choice(special)) if rng.random() < 0.3 else float(rng.normal(0, 3))

    quat = tuple(value() for _ in range(4)) if rng.random() < 0.5 else (0.0, 0.0, 0.0, 1.0)
    return OdometryRecord(0, stamp_ns, value(), value(), quat, (value(), value()), value(), value(), value(),
                          (value(), value()))  # fmt: skip


def _through_cdr(record: OdometryRecord) -> OdometryRecord:
    _, msg = record_message(record)
    return odometry_record(TS.deserialize_cdr(TS.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__), record.log_ns)


def _rss_kb() -> int:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))


@pytest.mark.slow
def test_fuzzed_3d_odometry_is_refused_by_reason_with_flat_memory():
    # 12,000 odometry messages (CDR, as a bag stores them, half of them fuzzed) among a centipede's real
    # states, answers and announcements: none crashes, a bad one costs its steps under a reason, the good ones
    # still make transitions, and memory stays flat (the second half adds nothing).
    rng = np.random.default_rng(0)
    good = centipede_records(steps=40)
    asm = TransitionAssembler(TransitionConfig(task="ant"))
    sent = made = 0

    def burst(n: int) -> None:
        nonlocal sent, made
        while sent < n:
            for r in good:
                if isinstance(r, OdometryRecord):
                    r = _through_cdr(_fuzzed(rng, r.stamp_ns) if rng.random() < 0.5 else r)
                    sent += 1
                made += len(asm.push(r))
            made += len(asm.flush())

    burst(6000)
    before = _rss_kb()
    burst(12_000)
    after = _rss_kb()
    assert sent >= 12_000
    skips = asm.skips
    assert skips.non_finite > 0 and skips.malformed > 0 and made > 0, skips
    assert after - before < 20_000, f"RSS grew by {after - before} kB"


@pytest.mark.parametrize("given", [(), ("--learning-rate", "0.001")])
def test_walkers_learn_at_the_same_settings_from_bags_live_and_the_simulator(centipede_bag, tmp_path, given):
    # The centipede results' PPO settings (LEGGED_DEFAULTS) where no option sets them, in every source: a bag
    # run and a live run of centipedes start as a simulator run does (before, they took the swimmer's 0.01 and
    # the live trainer's 0.003, at which a 12-feature policy's updates run away).
    from morph_core.algo.ppo_config import LEGGED_DEFAULTS
    from trainer.cli.train import build_parser, main
    from trainer.train_options import live_config

    path, _ = centipede_bag
    bags = tmp_path / "bags"
    assert main(["--from-bags", str(path), "--out", str(bags), "--bodies", "centipede:2-3", "--iterations", "1",
                 "--compile", "false", "--progress-bar", "false", "--tensorboard", "false", *given]) == 0  # fmt: skip
    parser = build_parser()
    args = parser.parse_args(["--live", "--namespaces", "/a", "--out", str(tmp_path / "live"), "--bodies",
                              "centipede:2-4", *given])  # fmt: skip
    live, _, _ = live_config(args, parser)
    from_bags = json.loads(RunDir(bags).config.read_text())
    want = {**LEGGED_DEFAULTS, **({"learning_rate": 0.001} if given else {})}
    for key, value in want.items():
        assert from_bags[key] == getattr(live, key) == value, key
