"""Short runs of the three trainers whose ``progress.csv`` must not change under a refactor, and their comparison.

    python scripts/bit_for_bit.py make ROOT OUT      # the runs, with the packages of the checkout ROOT
    python scripts/bit_for_bit.py compare OUT_A OUT_B

``make`` runs, each in a subprocess whose PYTHONPATH is ROOT's packages (so a checkout of an older commit
can make the reference): the simulator trainer (compensated, seed 1, 18,432 steps) with one process, with
two, and on bodies with trees; the same one-process run stopped at 12,288 steps and resumed to 18,432 (with
``--resume-with ROOT2``, the resume runs ROOT2's code on ROOT's state: an old run continued by new code);
``morph-train --from-bags`` on a recorded bag (made once beside OUT); and the live in-process trainer.
``compare`` says, per run, whether every column but the timings is equal.

Bit for bit is a same-machine guarantee: NumPy's BLAS and torch pick their kernels by processor and thread
count, so floats round differently on another CPU and a training trajectory drifts from the first update on.
``make`` writes ``machine.json`` (the CPU, its kernels' capability, the library versions) beside the runs, and
``compare`` refuses two outputs made on different machines in one line instead of reporting a difference that
says nothing about the code: make both sides here, one after the other.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

from morph_core.algo.run_dir import RunDir

PACKAGES = ("morph_core", "trainer", "morph_policy_node", "swimmer_sim_node", "morph_ros_util")
TIMING = {"wall_time", "sps"}
"""wall-clock columns; any column ending in ``_s`` is a timing too"""
QUIET = ["--tensorboard", "false", "--progress-bar", "false"]
SIM = ["--rule", "compensated", "--seed", "1", *QUIET]
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
from trainer.codec import record_message
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


MACHINE = "machine.json"

FINGERPRINT = """
import json, os, platform, mujoco, numpy, torch
cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "")
flags = next((line.split(":", 1)[1].split() for line in open("/proc/cpuinfo") if line.startswith("flags")), [])
simd = sorted(f for f in flags if f.startswith(("avx", "sse", "fma")))
print(json.dumps({"machine": platform.machine(), "cpu": cpu, "simd": simd, "cores": os.cpu_count(),
                  "torch": torch.__version__, "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
                  "numpy": numpy.__version__, "mujoco": mujoco.__version__,
                  "env": {k: os.environ[k] for k in ("OPENBLAS_CORETYPE", "ATEN_CPU_CAPABILITY") if k in os.environ}}))
"""
"""what decides how floats round here (read in ROOT's environment, as the runs are)"""


def _machine(root: Path) -> dict:
    done = subprocess.run([sys.executable, "-c", FINGERPRINT], env=_env(root), check=True, capture_output=True)
    return json.loads(done.stdout)


def make(root: Path, out: Path, resume_with: Path) -> None:
    out.mkdir(parents=True, exist_ok=False)
    (out / MACHINE).write_text(json.dumps(_machine(root), indent=1) + "\n")
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


def other_machine(a: Path, b: Path) -> str | None:
    """Why outputs ``a`` and ``b`` cannot be compared bit for bit (made on different machines), or None."""
    ma, mb = ((p / MACHINE).read_text() if (p / MACHINE).exists() else None for p in (a, b))
    if ma is None and mb is None:
        return None  # both made before machine.json existed: on the same machine, as they always were
    if ma is None or mb is None:
        return f"only one of {a} and {b} says which machine made it ({MACHINE})"
    ja, jb = json.loads(ma), json.loads(mb)
    differ = [k for k in sorted(set(ja) | set(jb)) if ja.get(k) != jb.get(k)]
    return f"made on different machines ({', '.join(differ)} differ)" if differ else None


def compare(a: Path, b: Path) -> bool:
    same = True
    for run in sorted(p.name for p in a.iterdir() if RunDir(p).progress.exists()):
        if not RunDir(b / run).progress.exists():  # e.g. B's make still running, or stopped by an error
            print(f"{run}: MISSING in {b}")
            same = False
            continue
        cols_a, rows_a = _rows(RunDir(a / run).progress)
        cols_b, rows_b = _rows(RunDir(b / run).progress)
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
    why = other_machine(args.a, args.b)
    if why:
        print(f"bit_for_bit: cannot compare: {why}; bit for bit holds on one machine: make both here", file=sys.stderr)
        return 2
    return 0 if compare(args.a, args.b) else 1


if __name__ == "__main__":
    sys.exit(main())
