"""Learning from bags alone: record with the current policy, train from the bag, record again.

    python -m trainer.bags.rounds --rounds 20 --out runs/bag-rounds [--deadline-minutes 40] [-- TRAIN OPTIONS]
    python -m trainer.bags.rounds --out runs/bag-rounds --report-only

Each round
1. records ``--episodes-per-round`` episodes with the three ROS 2 nodes as
   separate processes (sim: lockstep, as fast as possible, ``episode_steps``
   per episode, chain length redrawn from min..max joints at each reset, or
   a body drawn from ``--bodies`` (``centipede:2-4``: episodes end at a fall),
   seeded per round; policy node: ``deterministic:=false`` with the latest
   checkpoint; ``morph-record``) into ``bags/round_NNN``;
2. trains on that bag alone, ``morph-train --from-bags`` (one pass over it:
   one update when the round's steps fit one batch, as a swimmer's do),
   resuming the run in ``train/`` across rounds
   (``--resume --new-data``) so the optimizer's state carries over; options
   after ``--`` go to morph-train (e.g. ``-- --compile false``);
3. appends a row to ``rounds.csv``: simulator steps so far (episodes x
   episode_steps) and steps recorded, the recorded complete episodes'
   return overall and per chain length, the reward per step over all
   recorded steps, the update's weight statistics, wall times.

Round 1 records with a fresh policy seeded as the simulator trainer seeds
its own (``--seed``), so the two start from the same weights. A run that
stops (a failed round, a kill, the deadline) keeps what it did; the same
command continues it. ``comparison.csv`` and ``comparison.png`` set each
round's return against the simulator trainer's training return at the same
number of env steps (``--compare-with``, progress.csv files of simulator
runs, interpolated at each round's simulator steps).

Needs DDS discovery: run it inside scripts/in_netns.sh (scripts/bag_rounds.sh does).
"""

from __future__ import annotations

import argparse
import csv
import glob
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from morph_core.algo.run_dir import RunDir
from morph_core.util.atomic import atomic_writer
from morph_core.util.config_cli import BoolAction, CommandLineParser
from morph_ros_util.processes import NodeProcess, has_endpoint, start_node, stop_all, use_fastdds_profile
from trainer.bags.record_bringup import fastdds_profile

DIMS = range(2, 11)
COLUMNS = [
    "round", "sim_steps", "env_steps", "steps", "episodes", "return_mean", *[f"return_d{d}" for d in DIMS],
    "reward_rate", "lost_steps", "is_weight_mean", "stale_frac", "approx_kl", "clip_frac",
    "record_s", "train_s", "round_s", "elapsed_s", "checkpoint",
]  # fmt: skip
"""rounds.csv: sim_steps = steps the sim ran (episodes x episode_steps, cumulative); env_steps = recorded
transitions trained on (cumulative); steps = this round's; episodes/return_* = the complete recorded
episodes; lost_steps = steps the sim ran that the bag lacks (recorder still discovering the nodes)"""


class RoundFailed(RuntimeError):
    """A round that could not be completed; the text says why."""


@dataclass(frozen=True)
class RoundsConfig:
    out: Path
    rounds: int
    episodes_per_round: int = 6
    episode_steps: int = 1000
    min_joints: int = 2
    max_joints: int = 10
    seed: int = 1
    storage: str = "mcap"
    record_timeout: float = 1800.0
    startup_timeout: float = 120.0
    deadline_minutes: float = 0.0
    namespace: str = ""
    """ROS namespace of the three nodes ('' = the root)"""
    train_args: tuple[str, ...] = ()
    bodies: str | None = None
    """a body spec (env.bodies: ``centipede:2-4``, ``y:2x2``, ...) the sim draws from at each reset, in place
    of chains of min..max joints"""

    @property
    def walkers(self) -> bool:
        """Bodies whose episodes end early at a fall (``env.bodies``' walkers): a round counts the steps its bag
        holds, not episodes x episode_steps."""
        # `env` (MuJoCo, the sim extra) only to read a --bodies spec
        from morph_core.env.bodies import parse_bodies

        return bool(self.bodies) and parse_bodies(self.bodies).has_walkers

    @property
    def train_dir(self) -> Path:
        return self.out / "train"

    def bag(self, r: int) -> Path:
        return self.out / "bags" / f"round_{r:03d}"

    def log(self, r: int, what: str) -> Path:
        return self.out / "logs" / f"round_{r:03d}.{what}.log"


# -- the nodes of one recording --------------------------------------------------------------------
class Bringup:
    """Sim, sampling policy and recorder as processes; output to one log file per round."""

    def __init__(self, log_path: Path, namespace: str = ""):
        # ROS loads once the driver has set the Fast DDS profile (main)
        import rclpy

        self._rclpy = rclpy
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self.log = open(log_path, "ab")  # noqa: SIM115 - closed in stop()
        self.procs: dict[str, NodeProcess] = {}
        self.namespace = "/" + namespace.strip("/") if namespace.strip("/") else ""
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node("bag_rounds", context=self.context)

    def start(self, name: str, module: str, params: dict) -> None:
        self.procs[name] = start_node(module, self.namespace, params, output=self.log, echo=True)

    def check_alive(self, but: str = "") -> None:
        for name, p in self.procs.items():
            if name != but and p.poll() is not None:
                raise RoundFailed(f"the {name} exited early (exit {p.returncode}); see {self.log.name}")

    def wait_for(self, what: str, condition, timeout: float) -> None:
        """Spin until ``condition(node)`` holds, every process alive."""
        executor = self._rclpy.executors.SingleThreadedExecutor(context=self.context)
        executor.add_node(self.node)
        deadline = time.monotonic() + timeout
        try:
            while not condition(self.node):
                self.check_alive()
                if time.monotonic() > deadline:
                    raise RoundFailed(f"timed out after {timeout} s waiting for {what} (DDS discovery failed?)")
                executor.spin_once(timeout_sec=0.05)
        finally:
            executor.remove_node(self.node)
            executor.shutdown()

    def stop(self) -> None:
        stop_all(self.procs.values())
        self.node.destroy_node()
        self.context.try_shutdown()
        self.log.close()


def record_round(cfg: RoundsConfig, r: int, checkpoint: Path) -> None:
    """Record round ``r``'s episodes with ``checkpoint`` into ``cfg.bag(r)`` (raises ``RoundFailed``)."""
    bag = cfg.bag(r)
    bag.parent.mkdir(parents=True, exist_ok=True)
    seed = cfg.seed * 1000 + r
    up = Bringup(cfg.log(r, "record"), cfg.namespace)
    ns = up.namespace
    try:
        # Recorder and policy first, the sim last: the lockstep loop starts at the sim's first state and
        # runs hundreds of steps a second, so whoever has not discovered the others by then misses steps.
        up.start("recorder", "trainer.bags.record",
                 {"output": str(bag), "storage": cfg.storage, "max_episodes": cfg.episodes_per_round})  # fmt: skip
        up.start("policy node", "morph_policy_node.policy_node",
                 {"checkpoint": str(checkpoint), "deterministic": "false", "seed": seed})  # fmt: skip
        # The recorder listens to the announcements before the sim starts: it stops at episode
        # max_episodes + 1, and must hear that announcement before the episode's data.
        wanted = [(f"{ns}/{topic}", node, kind) for topic, node, kind in (
            ("episode_start", "morph_record", "sub"),
            ("joint_states", "morph_record", "sub"), ("effort_commands", "morph_record", "sub"),
            ("policy_info", "morph_record", "sub"), ("joint_states", "morph_policy", "sub"),
            ("effort_commands", "morph_policy", "pub"), ("policy_info", "morph_policy", "pub"),
        )]  # fmt: skip
        up.wait_for("the recorder and the policy node", lambda n: all(has_endpoint(n, *w) for w in wanted),
                    cfg.startup_timeout)  # fmt: skip
        bodies = (
            {"topology": cfg.bodies}
            if cfg.bodies
            else {"num_joints": cfg.min_joints, "min_joints": cfg.min_joints, "max_joints": cfg.max_joints}
        )
        up.start("sim", "swimmer_sim_node.sim_node", {
            **bodies, "episode_steps": cfg.episode_steps, "lockstep": "true", "real_time_factor": 0.0,
            "effort_timeout": 2.0, "seed": seed,
        })  # fmt: skip
        recorder = up.procs["recorder"]
        deadline = time.monotonic() + cfg.record_timeout
        while recorder.poll() is None:
            up.check_alive(but="recorder")
            if time.monotonic() > deadline:
                raise RoundFailed(f"recording did not finish within {cfg.record_timeout} s; see {up.log.name}")
            time.sleep(0.2)
        if recorder.returncode != 0:
            raise RoundFailed(f"the recorder failed (exit {recorder.returncode}); see {up.log.name}")
    finally:
        up.stop()
    if not (bag / "metadata.yaml").exists():
        raise RoundFailed(f"{bag}: the recorder left no metadata.yaml; see {cfg.log(r, 'record')}")


# -- what a round's bag holds ----------------------------------------------------------------------
@dataclass(frozen=True)
class RoundData:
    steps: int
    digest: str
    episodes: int
    """complete episodes (episode_steps transitions, or ended by a fall)"""
    returns: dict[int, list[float]]
    """returns of the complete episodes by chain length"""
    reward_rate: float
    announced: int
    """episodes the sim announced in the bag"""


def read_round(bag: Path, episode_steps: int, namespace: str | None = None) -> RoundData:
    # the bag reader and the data's digest (torch) only when a round's bag is read
    from ruamel.yaml import YAML

    from morph_core.algo.train_from_data import EpisodeReturns, data_digest
    from trainer.bags.contents import read_bags

    data, _, _ = read_bags([bag], namespace)
    if not len(data):
        raise RoundFailed(f"{bag}: no usable steps (morph-bag info {bag} says why)")
    ep = EpisodeReturns.of(data)
    last = np.cumsum(ep.lengths) - 1  # each episode's last row: episodes are contiguous runs, in order
    complete = (ep.lengths == episode_steps) | data.terminated[last]
    returns: dict[int, list[float]] = {}
    for n, ret in zip(ep.num_joints[complete], ep.returns[complete], strict=True):
        returns.setdefault(int(n), []).append(float(ret))
    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]}
    announced = sum(n for name, n in counts.items() if name.endswith("/episode_start"))
    return RoundData(
        steps=len(data),
        digest=data_digest(data),
        episodes=int(complete.sum()),
        returns=returns,
        reward_rate=float(data.reward.mean()),
        announced=announced,
    )


# -- training --------------------------------------------------------------------------------------
def initial_policy(cfg: RoundsConfig) -> Path:
    """Round 1's policy: fresh, seeded as the simulator trainer seeds it (``algo.train``), reading the bodies'
    global features."""
    # the rounds' driver loads torch only for round 1's policy; training runs in morph-train's process
    import torch

    from morph_core.algo.train import TrainConfig
    from morph_core.env.bodies import fit_global_features, parse_bodies
    from morph_core.policy.actor_critic import GraphActorCritic

    path = cfg.out / "init" / "policy.safetensors"
    if not path.exists():
        policy = TrainConfig().policy
        if cfg.bodies:
            policy = fit_global_features(policy, parse_bodies(cfg.bodies))
        torch.set_num_threads(1)
        torch.manual_seed(cfg.seed)
        GraphActorCritic(policy).save(path, metadata={"seed": cfg.seed})
    return path


def train_round(cfg: RoundsConfig, r: int, data: RoundData, init: Path) -> None:
    """One round's ``morph-train --from-bags``: a new run, its resume, or the next round of the run."""
    # torch only when a round reads its run's state
    from morph_core.algo.train_from_data import run_state

    state = run_state(cfg.train_dir)
    if state is None:
        started = RunDir(cfg.train_dir).config.exists()
        if r != 1 and not started:
            raise RoundFailed(f"round {r}: {cfg.train_dir} holds no trained state from the rounds before")
        mode = ["--resume"] if started else ["--init", str(init)]
    elif state["digest"] == data.digest:
        if state["done"] >= state["iterations"]:
            return  # trained already (the round was cut after training)
        mode = ["--resume"]
    else:
        mode = ["--resume", "--new-data"]
    cmd = [sys.executable, "-m", "trainer.cli.train", "--from-bags", str(cfg.bag(r)), "--out", str(cfg.train_dir)]
    # One pass over the round's bag (morph-train's default): one update when its steps fit a batch, as a swimmer's
    # six 1,000-step episodes do; a centipede's 30 short episodes may fill two (one would leave half unused).
    cmd += [*mode, "--seed", str(cfg.seed), "--checkpoint-interval", "1"]
    cmd += ["--progress-bar", "false", *cfg.train_args]
    log = cfg.log(r, "train")
    with log.open("ab") as f:
        f.write(f"$ {' '.join(cmd)}\n".encode())
        f.flush()
        done = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        tail = log.read_text(errors="replace").strip().splitlines()[-1:]
        raise RoundFailed(f"round {r}: morph-train failed (exit {done.returncode}): {' '.join(tail)}; see {log}")


def latest_checkpoint(cfg: RoundsConfig) -> Path:
    # torch only when a round reads its run's state
    from morph_core.algo.train_from_data import run_state

    state = run_state(cfg.train_dir)
    return RunDir(cfg.train_dir).checkpoint(state["global_step"])


def last_update(cfg: RoundsConfig) -> dict:
    with RunDir(cfg.train_dir).progress.open() as f:
        rows = list(csv.DictReader(f))
    return rows[-1]


# -- the rounds ------------------------------------------------------------------------------------
def read_rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with path.open() as f:
        return list(csv.DictReader(f))


def write_rows(path: Path, rows: list[dict], columns: list[str]) -> None:
    with atomic_writer(path) as f:
        w = csv.DictWriter(f, fieldnames=columns)
        w.writeheader()
        w.writerows(rows)


def run_rounds(cfg: RoundsConfig) -> int:
    cfg.out.mkdir(parents=True, exist_ok=True)
    rows_path = cfg.out / "rounds.csv"
    rows = read_rows(rows_path)
    init = initial_policy(cfg)
    started = time.monotonic()
    elapsed0 = float(rows[-1]["elapsed_s"]) if rows else 0.0
    last_round_s = float(rows[-1]["round_s"]) if rows else 0.0
    for r in range(len(rows) + 1, cfg.rounds + 1):
        spent = (time.monotonic() - started) / 60
        if cfg.deadline_minutes and spent + last_round_s / 60 > cfg.deadline_minutes:
            print(f"bag_rounds: stopping before round {r}: it would end past the {cfg.deadline_minutes} min deadline")
            break
        t0 = time.monotonic()
        checkpoint = init if r == 1 else latest_checkpoint(cfg)
        bag = cfg.bag(r)
        if bag.exists() and not (bag / "metadata.yaml").exists():
            aside = bag.with_name(f"{bag.name}.incomplete-{int(time.time())}")
            bag.rename(aside)  # a recording that was cut: kept aside, recorded again
            print(f"bag_rounds: round {r}: the earlier recording was incomplete, moved to {aside}")
        if not bag.exists():
            print(f"bag_rounds: round {r}: recording {cfg.episodes_per_round} episodes with {checkpoint}", flush=True)
            record_round(cfg, r, checkpoint)
        record_s = time.monotonic() - t0
        data = read_round(bag, cfg.episode_steps, cfg.namespace or None)
        t1 = time.monotonic()
        train_round(cfg, r, data, init)
        train_s = time.monotonic() - t1
        upd = last_update(cfg)
        # A walker's episodes end at falls: how many steps its sim ran is not told by the announcements.
        ran = data.steps if cfg.walkers else data.announced * cfg.episode_steps
        sim_steps = (int(rows[-1]["sim_steps"]) if rows else 0) + ran
        env_steps = (int(rows[-1]["env_steps"]) if rows else 0) + data.steps
        flat = [x for v in data.returns.values() for x in v]
        round_s = time.monotonic() - t0
        row = {
            "round": r,
            "sim_steps": sim_steps,
            "env_steps": env_steps,
            "steps": data.steps,
            "episodes": data.episodes,
            "return_mean": float(np.mean(flat)) if flat else math.nan,
            **{f"return_d{d}": float(np.mean(data.returns[d])) if d in data.returns else "" for d in DIMS},
            "reward_rate": data.reward_rate,
            "lost_steps": ran - data.steps,
            "is_weight_mean": upd["is_weight_mean"],
            "stale_frac": upd["stale_frac"],
            "approx_kl": upd["approx_kl"],
            "clip_frac": upd["clip_frac"],
            "record_s": round(record_s, 1),
            "train_s": round(train_s, 1),
            "round_s": round(round_s, 1),
            "elapsed_s": round(elapsed0 + time.monotonic() - started, 1),
            "checkpoint": os.path.relpath(checkpoint, cfg.out),
        }
        rows.append(row)
        write_rows(rows_path, rows, COLUMNS)
        last_round_s = round_s
        print(
            f"bag_rounds: round {r}: {data.steps} steps ({sim_steps} sim steps so far), {data.episodes} complete "
            f"episodes, return {row['return_mean']:.1f}, reward/step {data.reward_rate:.4f}; "
            f"{record_s:.0f} s recording, {train_s:.0f} s training",
            flush=True,
        )
    return 0


# -- against the simulator trainer -----------------------------------------------------------------
def simulator_returns(paths: list[Path], steps: np.ndarray) -> np.ndarray:
    """[runs, len(steps)] training return (return_mean) of each simulator run, interpolated at ``steps``
    (NaN beyond a run's last row)."""
    out = np.full((len(paths), len(steps)), np.nan)
    for i, path in enumerate(paths):
        rows = [r for r in read_rows(path) if r["return_mean"] != ""]
        g = np.array([float(r["global_step"]) for r in rows])
        ret = np.array([float(r["return_mean"]) for r in rows])
        inside = steps <= g[-1]
        out[i, inside] = np.interp(steps[inside], g, ret)
    return out


def compare(out: Path, pattern: str) -> list[dict]:
    """``comparison.csv`` (and ``comparison.png``): each round's return beside the simulator runs' at the same
    env steps (mean, min and max over the runs matching ``pattern``/progress.csv)."""
    rows = read_rows(out / "rounds.csv")
    paths = sorted(RunDir(p).progress for p in glob.glob(pattern))
    paths = [p for p in paths if p.exists()]
    if not rows:
        return []
    steps = np.array([float(r["sim_steps"]) for r in rows])
    sim = simulator_returns(paths, steps) if paths else np.full((0, len(steps)), np.nan)
    table = []
    for i, r in enumerate(rows):
        col = sim[:, i][np.isfinite(sim[:, i])]
        table.append({
            "round": r["round"], "sim_steps": r["sim_steps"], "env_steps": r["env_steps"],
            "bag_return": r["return_mean"], "bag_episodes": r["episodes"],
            "bag_reward_rate_x1000": 1000 * float(r["reward_rate"]),
            "simulator_return_mean": float(col.mean()) if len(col) else "",
            "simulator_return_min": float(col.min()) if len(col) else "",
            "simulator_return_max": float(col.max()) if len(col) else "",
            "simulator_runs": len(col),
        })  # fmt: skip
    write_rows(out / "comparison.csv", table, list(table[0]))
    _plot(out / "comparison.png", table, len(paths), pattern)
    return table


def _plot(path: Path, table: list[dict], runs: int, pattern: str) -> None:
    # Matplotlib only for the figure
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after the backend is chosen

    def col(key):
        return np.array([float(t[key]) if t[key] != "" else np.nan for t in table])

    x = col("sim_steps")
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    if runs:
        ax.fill_between(x, col("simulator_return_min"), col("simulator_return_max"), alpha=0.2, color="C0")
        ax.plot(x, col("simulator_return_mean"), color="C0", label=f"simulator trainer ({runs} runs: mean, range)")
    ax.plot(x, col("bag_return"), "o-", color="C1", label="from bags alone: complete recorded episodes")
    ax.plot(x, col("bag_reward_rate_x1000"), "s--", color="C2", ms=3,
            label="from bags alone: 1000 x reward per recorded step")  # fmt: skip
    ax.set_xlabel("env steps (steps the sim ran)")
    ax.set_ylabel("training return (1000-step episodes)")
    ax.set_title("Learning from recorded bags vs the simulator trainer")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def format_table(table: list[dict]) -> str:
    def f(v):
        return f"{float(v):.1f}" if v != "" and not math.isnan(float(v)) else "-"

    lines = ["| round | env steps | from bags: return of complete episodes (n) | from bags: 1000 x reward/step "
             "| simulator trainer at those steps: mean (min..max) |", "|---:|---:|---:|---:|---:|"]  # fmt: skip
    for t in table:
        lines.append(
            f"| {t['round']} | {int(float(t['sim_steps'])):,} | {f(t['bag_return'])} ({t['bag_episodes']}) | "
            f"{f(t['bag_reward_rate_x1000'])} | "
            f"{f(t['simulator_return_mean'])} ({f(t['simulator_return_min'])}..{f(t['simulator_return_max'])}) |"
        )
    return "\n".join(lines)


# -- command line ----------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    train_args = []
    if "--" in argv:
        i = argv.index("--")
        argv, train_args = argv[:i], argv[i + 1 :]
    ap = CommandLineParser(prog=os.environ.get("MORPH_PROG", "python -m trainer.bags.rounds"), description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--out", type=Path, required=True, help="experiment directory (continued if it exists)")
    ap.add_argument("--rounds", type=int, default=0, help="rounds to have done in all")
    ap.add_argument("--episodes-per-round", type=int, default=RoundsConfig.episodes_per_round)
    ap.add_argument("--episode-steps", type=int, default=RoundsConfig.episode_steps,
                    help="control steps per episode (Swimmer-v5's time limit: 1000)")  # fmt: skip
    ap.add_argument("--bodies", default=None,
                    help="a body spec (env.bodies: centipede:2-4, y:2x2, ...) instead of chains of min..max joints; "
                         "walkers take the centipede results' PPO settings, as morph-train does")  # fmt: skip
    ap.add_argument("--min-joints", type=int, default=RoundsConfig.min_joints)
    ap.add_argument("--max-joints", type=int, default=RoundsConfig.max_joints)
    ap.add_argument("--seed", type=int, default=RoundsConfig.seed,
                    help="seed of the first policy and morph-train; round r samples with seed*1000+r")  # fmt: skip
    ap.add_argument("--storage", choices=("mcap", "sqlite3"), default=RoundsConfig.storage)
    ap.add_argument("--namespace", default="", help="ROS namespace of the nodes (default: the root)")
    ap.add_argument("--record-timeout", type=float, default=RoundsConfig.record_timeout, help="wall s per recording")
    ap.add_argument("--deadline-minutes", type=float, default=0.0,
                    help="start no round that would end after this many minutes from now (0: none)")  # fmt: skip
    ap.add_argument("--compare-with", default="docs/results_data/compensated-s*",
                    help="simulator run directories (a glob) to compare with")  # fmt: skip
    ap.add_argument(
        "--report-only", action=BoolAction, default=False, help="only write the comparison of the rounds done"
    )
    args = ap.parse_args(argv)
    if not args.report_only:
        if args.rounds < 1 or args.episodes_per_round < 1 or args.episode_steps < 1:
            ap.error("--rounds, --episodes-per-round and --episode-steps must be >= 1")
        if not 1 <= args.min_joints <= args.max_joints <= 64:
            ap.error("need 1 <= --min-joints <= --max-joints <= 64")
        if args.bodies is not None:
            # `env` (MuJoCo, the sim extra) only to read a --bodies spec
            from morph_core.env.bodies import parse_bodies

            try:
                parse_bodies(args.bodies)
            except ValueError as err:
                ap.error(f"--bodies: {err}")
        bodies = (
            ("--bodies", args.bodies)
            if args.bodies
            else ("--min-joints", str(args.min_joints), "--max-joints", str(args.max_joints))
        )
        cfg = RoundsConfig(
            out=args.out, rounds=args.rounds, episodes_per_round=args.episodes_per_round,
            episode_steps=args.episode_steps, min_joints=args.min_joints, max_joints=args.max_joints,
            seed=args.seed, storage=args.storage, record_timeout=args.record_timeout,
            deadline_minutes=args.deadline_minutes, namespace=args.namespace, train_args=(*train_args, *bodies),
            bodies=args.bodies,
        )  # fmt: skip
        if cfg.out.exists() and (cfg.out / "rounds.csv").exists():
            print(f"bag_rounds: continuing {cfg.out} ({len(read_rows(cfg.out / 'rounds.csv'))} rounds done)")
        use_fastdds_profile(fastdds_profile())
        try:
            run_rounds(cfg)
        except RoundFailed as err:
            done = len(read_rows(cfg.out / "rounds.csv"))
            print(f"bag_rounds: error: {err}", file=sys.stderr)
            print(f"bag_rounds: stopped; {done} rounds are in {cfg.out / 'rounds.csv'}; the same command continues",
                  file=sys.stderr)  # fmt: skip
            _report(args.out, args.compare_with)
            return 1
    _report(args.out, args.compare_with)
    return 0


def _report(out: Path, pattern: str) -> None:
    table = compare(out, pattern)
    if table:
        print(format_table(table))
        print(f"bag_rounds: wrote {out / 'comparison.csv'} and {out / 'comparison.png'}")


if __name__ == "__main__":
    sys.exit(main())
