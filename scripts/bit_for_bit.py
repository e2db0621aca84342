"""Short runs of the three trainers whose ``progress.csv`` must not change under a refactor, and their comparison.

    python scripts/bit_for_bit.py make ROOT OUT      # the runs, with the packages of the checkout ROOT
    python scripts/bit_for_bit.py compare OUT_A OUT_B

``make`` runs, each in a subprocess whose PYTHONPATH is ROOT's packages (so a checkout of an older commit
can make the reference): the simulator trainer (compensated, seed 1, 18,432 steps) with one process, with
two, and on bodies with trees; the same one-process run stopped at 12,288 steps and resumed to 18,432 (with
``--resume-with ROOT2``, the resume runs ROOT2's code on ROOT's state: an old run continued by new code);
``morph-train --from-bags`` on a recorded bag (made once beside OUT); and the live in-process trainer.
``compare`` says, per run, whether every column but the timings is equal.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
from pathlib import Path

PACKAGES = ("morph_core", "trainer", "morph_policy_node", "swimmer_sim_node", "morph_ros_util")
TIMING = {"wall_time", "sps"}
"""wall-clock columns; any column ending in ``_s`` is a timing too"""
QUIET = ["--tensorboard", "false", "--progress-bar", "false"]
SIM = ["--clip-mode", "compensated", "--seed", "1", *QUIET]
BAG_OPTIONS = ["--num-envs", "1", "--num-steps", "64", "--minibatch-size", "16", "--update-epochs", "2",
               "--checkpoint-interval", "64", "--iterations", "6", "--seed", "3", *QUIET]  # fmt: skip
LIVE = ["--seed", "1", "--total-timesteps", "1600", "--num-envs", "1", "--num-steps", "256", "--minibatch-size", "64",
        "--update-epochs", "2", "--min-joints", "2", "--max-joints", "4", "--episode-steps", "100", "--lag", "1",
        "--tensorboard", "false"]  # fmt: skip

MAKE_BAG = """
import sys, torch
from rosbags.typesys import Stores, get_typestore
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.protocol.loopback import SamplingController, record_episodes
from trainer.bags.messages import record_message
from trainer.bags.writer import BagTopic, BagWriter, WriterOptions
ts = get_typestore(Stores.ROS2_JAZZY)
types = {"episode_start": "std_msgs/msg/Int64MultiArray", "joint_states": "sensor_msgs/msg/JointState",
         "odom": "nav_msgs/msg/Odometry", "effort_commands": "std_msgs/msg/Float64MultiArray",
         "policy_info": "trajectory_msgs/msg/JointTrajectory"}
torch.set_num_threads(1)
torch.manual_seed(11)
records = record_episodes(SamplingController(GraphActorCritic(), seed=1), ((3, 120), (6, 100), (9, 80), (4, 90)))
with BagWriter(sys.argv[1], WriterOptions(storage="mcap")) as w:
    ids = {name: w.add_topic(BagTopic(f"/swimmer/{name}", ty)) for name, ty in types.items()}
    for r in records:
        name, msg = record_message(r)
        w.write(ids[name], r.log_ns, ts.serialize_cdr(msg, msg.__msgtype__))
"""


def _env(root: Path) -> dict:
    paths = [str(root / "ros2_ws" / "src" / p) for p in PACKAGES]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


def _run(root: Path, args: list[str]) -> None:
    print("+", " ".join(args), flush=True)
    subprocess.run([sys.executable, *args], env=_env(root), check=True, stdout=subprocess.DEVNULL)


def make(root: Path, out: Path, resume_with: Path) -> None:
    out.mkdir(parents=True, exist_ok=False)
    train = ["-m", "trainer.cli.train"]
    _run(root, [*train, "--out", str(out / "sim-p1"), *SIM, "--total-timesteps", "18432"])
    _run(root, [*train, "--out", str(out / "sim-p2"), *SIM, "--total-timesteps", "18432", "--processes", "2"])
    _run(root, [*train, "--out", str(out / "sim-trees"), *SIM, "--total-timesteps", "18432", "--bodies", "2-4,y:2x2"])
    _run(root, [*train, "--out", str(out / "sim-resumed"), *SIM, "--total-timesteps", "12288"])
    _run(resume_with, [*train, "--out", str(out / "sim-resumed"), "--resume", "--total-timesteps", "18432"])
    bag = out.parent / "bag"
    if not bag.exists():
        _run(root, ["-c", MAKE_BAG, str(bag)])
    _run(root, [*train, "--from-bags", str(bag), "--out", str(out / "bags"), *BAG_OPTIONS])
    _run(root, ["-m", "trainer.live.in_process", "--out", str(out / "live"), *LIVE])


def _rows(path: Path) -> tuple[list[str], list[dict]]:
    with path.open() as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def compare(a: Path, b: Path) -> bool:
    same = True
    for run in sorted(p.name for p in a.iterdir() if (p / "progress.csv").exists()):
        cols_a, rows_a = _rows(a / run / "progress.csv")
        cols_b, rows_b = _rows(b / run / "progress.csv")
        compared = [c for c in cols_a if c not in TIMING and not c.endswith("_s")]
        diffs = [] if cols_a == cols_b and len(rows_a) == len(rows_b) else ["columns or row count differ"]
        for i, (ra, rb) in enumerate(zip(rows_a, rows_b, strict=False)):
            diffs += [f"row {i} {c}: {ra[c]} != {rb.get(c)}" for c in compared if ra[c] != rb.get(c)]
        print(f"{run}: {len(rows_a)} rows x {len(compared)} columns compared: "
              f"{'identical' if not diffs else 'DIFFERENT: ' + '; '.join(diffs[:5])}")  # fmt: skip
        same &= not diffs
    return same


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make")
    m.add_argument("root", type=Path)
    m.add_argument("out", type=Path)
    m.add_argument("--resume-with", type=Path, default=None, help="the checkout whose code resumes (default ROOT)")
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    args = parser.parse_args()
    if args.command == "make":
        make(args.root.resolve(), args.out.resolve(), (args.resume_with or args.root).resolve())
        return 0
    return 0 if compare(args.a, args.b) else 1


if __name__ == "__main__":
    sys.exit(main())
