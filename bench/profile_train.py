"""Where a steady training iteration's time goes, per process: py-spy over the real training loop.

    python bench/profile_train.py [--bodies 2-10] [--processes 2] [--iterations 4] [--root CHECKOUT ...]

Starts ``morph-train`` at the paper configuration (6 swimmers x 1,024 steps, minibatch 256, 10 epochs, the
update compiled) on ``--bodies``, waits until its first iteration (the compile warm-up) has logged, then
samples every process of the run with py-spy (``--subprocesses --idle``: wall-clock samples, waiting
included) until the run ends. Each sample goes to the first category that its stack matches from the leaf
up (``CATEGORIES``); a sample inside a MuJoCo call counts as physics by the source line it stands on. The
table gives each category's share of a process's samples and its seconds per iteration (the share times
the steady iterations' mean wall time from ``progress.csv``).

``--root`` profiles the code of other checkouts of this repository (their packages on PYTHONPATH), in
turns with each other (A, B, A, B with ``--rounds 2``), so that a before/after pair sees the same load.
Needs py-spy (``pip install py-spy`` into the venv: a profiler, not a dependency of the project).
"""

from __future__ import annotations

import argparse
import csv
import linecache
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

from morph_core.algo.run_dir import RunDir

PACKAGES = ("morph_core", "trainer", "morph_policy_node", "swimmer_sim_node", "morph_ros_util")
BATCH = 6 * 1024

PHYSICS_CALLS = ("mj_step", "mj_rnePostConstraint", "_batch.step", "batch.step(", "mujoco.rollout")
"""a sample whose deepest project frame stands on a line calling one of these is in MuJoCo's physics"""

EXCHANGE_CALLS = (".release()",)
"""a sample on a line posting a semaphore is in the exchange: under load the post hands the core to the
process it wakes"""

# (category, regex on a frame "function (path:line)"), tried on each frame from the leaf up; the first hit wins.
CATEGORIES: list[tuple[str, str]] = [
    (
        "idle waiting",
        r"^(take_spinning|poll_spinning|Connection\.(recv|poll|_recv|_poll)|wait|select|"
        r"Helpers\._receive|_Helper\.serve \(.*|SemLock\.acquire) ",
    ),
    ("env resets", r"^(\w+\.)?(reset|_reset_body|_build|restore_body) \(morph_core/env/"),
    (
        "observation building",
        r"^(\w+\.)?(write_observation|write_graph_observation|write_global_features|"
        r"_observation|observations|_write|_write_body|pad_observations|_write_rows) "
        r"\(morph_core/(env|policy/chains)",
    ),
    ("policy inference", r"\(morph_core/policy/numpy_actor\.py|^NumpyPolicy"),
    ("action application", r"^(applied_action|.*_applied) \(morph_core/env/reward"),
    (
        "env step: reward, checks",
        r"^(\w+\.)?(advance|swimmer_reward|control_cost|_reward|_healthy|_contact\w*) "
        r"\(morph_core/env/",
    ),
    ("vec env bookkeeping", r"\(morph_core/env/vec_env\.py"),
    ("rollout writes, noise", r"^collect \(morph_core/algo/rollout\.py|^RolloutWorker\.collect"),
    ("GAE", r"^compute_gae "),
    ("compiled step", r"^part_gradient |\(morph_core/algo/compiled\.py"),
    ("optimizer step", r"^Learner\.step "),
    (
        "gradient exchange",
        r"^(Helpers\.(gather|stepped|publish_parameters|epoch|begin)|_GradientPeer\._write|"
        r"_Helper\.take_parameters) ",
    ),
    (
        "batching",
        r"^(Rollout\.batch|RolloutBatch\.minibatch|part_inputs|update_terms|"
        r"normalized_minibatch_advantages|_GradientPeer\.(begin|epoch)|epoch_steps|"
        r"Helpers\.publish_advantages) ",
    ),
    ("statistics", r"^(update_stats|explained_variance|update\b)"),
    ("logging, checkpoint", r"^(Run\.|Fit\.step|Rollouts\.row|fit\b|merge_env_states|.*get_state)"),
]
_COMPILED = [(name, re.compile(pattern)) for name, pattern in CATEGORIES]
_NOT_THE_LOOP = ("Thread._bootstrap ", "Thread.run ")
_PROCESS = re.compile(r'^process (\d+):"([^"]*)";?')
_FRAME = re.compile(r"^(?P<func>.*) \((?P<file>[^()]*):(?P<line>\d+)\)$")


def _source_line(module_file: str, line: int, roots: list[Path]) -> str:
    for root in roots:
        path = root / module_file
        if path.is_file():
            return linecache.getline(str(path), line)
    return ""


def classify(frames: list[str], roots: list[Path]) -> str:
    """The category of one sample's stack (root first)."""
    for frame in reversed(frames):
        m = _FRAME.match(frame)
        if m and m["file"].startswith("morph_core/"):  # the deepest project frame: on a physics call?
            text = _source_line(m["file"], int(m["line"]), roots)
            if any(call in text for call in PHYSICS_CALLS):
                return "physics"
            if any(call in text for call in EXCHANGE_CALLS):
                return "gradient exchange"
            break
    for frame in reversed(frames):
        for name, pattern in _COMPILED:
            if pattern.search(frame):
                return name
    return "other"


def parse(raw: Path, roots: list[Path], others: Counter | None = None) -> dict[str, Counter]:
    """Samples per category per process (process 0, then helpers in pid order) from py-spy's raw output."""
    per_pid: dict[int, Counter] = defaultdict(Counter)
    cmdlines: dict[int, str] = {}
    for line in raw.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if not count.isdigit():  # a command line with a newline in it
            continue
        pid = None
        while m := _PROCESS.match(stack):  # the process frames come first (a command line may hold a ";")
            pid, cmdlines[int(m[1])], stack = int(m[1]), m[2], stack[m.end() :]
        frames = stack.split(";")
        if pid is None or not stack or any(f.startswith(_NOT_THE_LOOP) or "resource_tracker" in f for f in frames):
            continue  # the loop's thread alone: a tqdm monitor, a resource sharer or tracker would count as idle
        category = classify(frames, roots)
        per_pid[pid][category] += int(count)
        if category == "other" and others is not None:
            others[";".join(frames[-3:])] += int(count)
    out = {}
    helpers = 0
    for pid in sorted(per_pid):
        cmd = cmdlines[pid]
        if "resource_tracker" in cmd:
            continue
        if "multiprocessing-fork" in cmd:
            helpers += 1
            out[f"helper {helpers}"] = per_pid[pid]
        else:
            out["process 0"] = per_pid[pid]
    return out


def profile(
    root: Path, bodies: str, processes: int, iterations: int, rate: int, py_spy: str, keep: Path | None = None
) -> dict:
    """Run and sample one training at ``root``'s code; the shares per process and the steady iteration time."""
    paths = [str(root / "ros2_ws" / "src" / p) for p in PACKAGES]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
    with tempfile.TemporaryDirectory() as d:
        run_dir, raw = Path(d) / "run", Path(d) / "raw.txt"
        cmd = [sys.executable, "-m", "trainer.cli.train", "--out", str(run_dir), "--bodies", bodies,
               "--processes", str(processes), "--total-timesteps", str((1 + iterations) * BATCH),
               "--tensorboard", "false", "--progress-bar", "false"]  # fmt: skip
        train = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        progress = RunDir(run_dir).progress
        while train.poll() is None and _rows(progress) < 1:  # the warm-up iteration (compiling) first
            time.sleep(0.2)
        if train.poll() is not None:
            raise SystemExit(f"training failed: {train.stderr.read()}")
        spy = subprocess.Popen([py_spy, "record", "--pid", str(train.pid), "--subprocesses", "--idle",
                                "--format", "raw", "--rate", str(rate), "--nonblocking", "-o", str(raw)],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)  # fmt: skip
        train.wait()
        try:
            spy.wait(timeout=30)
        except subprocess.TimeoutExpired:
            spy.send_signal(signal.SIGINT)
            spy.wait()
        if train.returncode != 0:
            raise SystemExit(f"training failed: {train.stderr.read()}")
        with progress.open() as f:
            rows = list(csv.DictReader(f))[1:]
        wall = [float(r["wall_time"]) for r in rows]
        iteration_s = (wall[-1] - wall[0]) / (len(wall) - 1)
        roots, others = [Path(p) for p in paths], Counter()
        if keep is not None:
            shutil.copy(raw, keep)
        return {"shares": parse(raw, roots, others), "others": others, "iteration_s": iteration_s,
                "rollout_s": sum(float(r["rollout_s"]) for r in rows) / len(rows),
                "update_s": sum(float(r["update_s"]) for r in rows) / len(rows)}  # fmt: skip


def _rows(progress: Path) -> int:
    try:
        return max(0, len(progress.read_text().splitlines()) - 1)
    except FileNotFoundError:
        return 0


def report(label: str, result: dict) -> None:
    it = result["iteration_s"]
    print(f"\n{label}: steady iteration {it:.3f} s by wall clock (rollout {result['rollout_s']:.3f} s, "
          f"update {result['update_s']:.3f} s, means of the timed iterations)")  # fmt: skip
    procs = list(result["shares"])
    names = [n for n, _ in CATEGORIES] + ["physics", "other"]
    totals = {p: sum(result["shares"][p].values()) for p in procs}
    print("| category | " + " | ".join(f"{p} share | {p} s/iter" for p in procs) + " |")
    print("|---|" + "---:|---:|" * len(procs))
    order = sorted(set(names), key=lambda n: -sum(result["shares"][p][n] / max(totals[p], 1) for p in procs))
    for name in order:
        if not any(result["shares"][p][name] for p in procs):
            continue
        cells = []
        for p in procs:
            share = result["shares"][p][name] / max(totals[p], 1)
            cells.append(f"{share:.1%} | {share * it:.3f}")
        print(f"| {name} | " + " | ".join(cells) + " |")
    print("samples: " + ", ".join(f"{p} {totals[p]}" for p in procs))
    for stack, count in result["others"].most_common(3):
        print(f"  other: {count} samples in {stack}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bodies", default="2-10", help="the bodies to train on (env.bodies spec)")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--iterations", type=int, default=4, help="steady iterations sampled after the warm-up")
    parser.add_argument("--rate", type=int, default=50, help="py-spy samples per second")
    parser.add_argument("--root", type=Path, nargs="+", default=[Path(__file__).resolve().parents[1]],
                        help="checkouts whose code to profile, in turns (default: this one)")  # fmt: skip
    parser.add_argument("--rounds", type=int, default=1, help="runs of each checkout, in turns")
    parser.add_argument("--keep", type=Path, default=None, metavar="DIR", help="keep py-spy's raw samples here")
    args = parser.parse_args()
    py_spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(py_spy).exists():
        parser.error("py-spy not found: pip install py-spy into this venv")
    for r in range(args.rounds):
        for root in args.root:
            keep = None
            if args.keep is not None:
                args.keep.mkdir(parents=True, exist_ok=True)
                keep = args.keep / f"{root.name}-{args.bodies.replace(':', '_')}-p{args.processes}-r{r + 1}.txt"
            result = profile(root.resolve(), args.bodies, args.processes, args.iterations, args.rate, py_spy, keep)
            report(f"{root} round {r + 1}, bodies {args.bodies}, {args.processes} process(es)", result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
