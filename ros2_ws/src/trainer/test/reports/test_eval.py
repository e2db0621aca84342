"""morph-eval: deterministic checkpoint evaluation into eval.csv, resumable, and the comparison plots."""

import csv
import dataclasses
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from morph_core.algo.evaluate import evaluate_episodes, evaluate_policy
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small
from morph_core.algo.train import TrainConfig, train
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import load_checkpoint
from morph_core.protocol.policy_updates import checkpoint_trust
from morph_core.protocol.trust import TrustedKeys, load_public_key
from trainer.cli.keys import main as keys_main
from trainer.reports.evaluation import EvalConfig, evaluate_run
from trainer.reports.ship import body_key, scored_bodies

SMALL = small(update_epochs=1, checkpoint_interval=128)


def test_evaluation_is_deterministic_and_covers_every_length():
    policy = GraphActorCritic()
    a = evaluate_policy(policy, [2, 5, 15], episodes=3, max_steps=50)
    b = evaluate_policy(policy, [2, 5, 15], episodes=3, max_steps=50, num_threads=2)
    assert sorted(a) == [2, 5, 15] and all(len(v) == 3 for v in a.values())
    for n in a:
        np.testing.assert_array_equal(a[n], b[n])  # threads change nothing
    assert len(set(a[5])) == 3  # episodes start from different reset seeds


@pytest.mark.slow
def test_eval_cli_writes_csv_skips_done_work_and_plots(tmp_path):
    runs = [train(TrainConfig(total_timesteps=256, clip_mode=m, seed=1, **SMALL), tmp_path / m)
            for m in ("compensated", "fixed")]  # fmt: skip
    cli = [sys.executable, "-m", "trainer.cli.eval", "--episodes", "2", "--joints", "2", "3"]
    subprocess.run([*cli, "--run", *map(str, runs), "--plots", str(tmp_path / "fig")], check=True)
    with RunDir(runs[0]).evaluation.open() as f:
        rows = list(csv.DictReader(f))
    assert {(r["global_step"], r["num_joints"]) for r in rows} == {(s, n) for s in ("128", "256") for n in ("2", "3")}
    assert len(rows) == 8
    assert all(int(r["steps"]) == 1000 and np.isfinite(float(r["distance"])) for r in rows)  # swimmers never end early
    mtime = RunDir(runs[0]).evaluation.stat().st_mtime_ns
    out = subprocess.run([*cli, "--run", str(runs[0])], check=True, capture_output=True, text=True)
    assert out.stdout == "" and RunDir(runs[0]).evaluation.stat().st_mtime_ns == mtime  # nothing redone
    for name in ("training_returns.png", "clip_fraction_per_dim.png", "eval_return_per_length.png"):
        assert (tmp_path / "fig" / name).read_bytes()[:4] == b"\x89PNG"
    table = (tmp_path / "fig" / "final_eval_table.md").read_text()
    assert "| 2 |" in table and "| 3 |" in table and "compensated (1 seeds)" in table
    assert "| 3 |" in (tmp_path / "fig" / "late_eval_table.md").read_text()
    summary = subprocess.run(
        [sys.executable, "-m", "trainer.reports.summary", "--run", *map(str, runs)],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    assert "| compensated | never | never |" in summary and "| fixed | never | never |" in summary
    assert "clip fraction per dimension, fixed (1 runs): " in summary and "nan" not in summary  # a dimension no
    # update sampled in so short a run is left out, not printed as nan

    # Checkpoints signed with morph-keys stay signed when shipped (their bytes are copied as they are).
    assert keys_main(["new", str(tmp_path / "key")]) == 0
    for checkpoint in sorted(p for run in runs for p in RunDir(run).checkpoints.glob("*.safetensors")):
        assert keys_main(["sign", str(checkpoint), "--key", str(tmp_path / "key")]) == 0
    # Ship the best evaluated checkpoint: it loads, and says where it came from and how it scored.
    dest = tmp_path / "models" / "swimmer_gnn.safetensors"
    subprocess.run(
        [sys.executable, "-m", "trainer.reports.ship", "--run", *map(str, runs), "--dest", str(dest)], check=True
    )
    trust = checkpoint_trust(load_checkpoint(dest), TrustedKeys([load_public_key(tmp_path / "key.pub")]))
    assert trust.order is not None and "(trusted)" in trust.description
    meta = json.loads(dest.with_suffix(".json").read_text())["metadata"]
    best = max(
        (np.mean([float(r["return"]) for r in rows_of(run) if r["global_step"] == step]), run.name, int(step))
        for run in runs
        for step in {r["global_step"] for r in rows_of(run)}
    )
    assert (meta["source_run"], meta["global_step"]) == best[1:]
    assert set(meta["eval_mean_return"]) == {"2", "3"}
    # the command reproduces the run: every option that differs from the defaults
    command = meta["training_command"]
    assert command.startswith(f"morph-train --clip-mode {best[1]} --seed 1 ")
    assert command.endswith(f"--out runs/{best[1]}")
    for flag in ("--num-envs 2", "--num-steps 64", "--total-timesteps 256", "--compile false"):
        assert flag in command
    GraphActorCritic.load(dest)

    # Shipping again: the policy at --dest is a candidate too, scored on its recorded evaluation.
    ship = [sys.executable, "-m", "trainer.reports.ship", "--run", *map(str, runs), "--dest", str(dest)]
    meta_path = dest.with_suffix(".json")
    shipped = json.loads(meta_path.read_text())

    def with_recorded(offset):  # the shipped policy's recorded returns, moved by ``offset``
        doc = json.loads(json.dumps(shipped))
        recorded = shipped["metadata"]["eval_mean_return"]
        doc["metadata"]["eval_mean_return"] = {n: r + offset for n, r in recorded.items()}
        meta_path.write_text(json.dumps(doc))

    with_recorded(+1.0)  # scores higher than every run's checkpoint: kept, nothing written
    before = dest.read_bytes(), meta_path.read_text()
    out = subprocess.run(ship, check=True, capture_output=True, text=True).stdout
    assert out.startswith(f"kept {dest}") and (dest.read_bytes(), meta_path.read_text()) == before
    subprocess.run([*ship, "--replace"], check=True, capture_output=True)  # unless told to replace it
    assert json.loads(meta_path.read_text()) == shipped
    with_recorded(-1.0)  # scores lower: the best run's checkpoint replaces it
    out = subprocess.run(ship, check=True, capture_output=True, text=True).stdout
    assert out.startswith("shipped") and json.loads(meta_path.read_text()) == shipped


def rows_of(run):
    with RunDir(run).evaluation.open() as f:
        return list(csv.DictReader(f))


def test_eval_cli_refuses_a_directory_that_is_not_a_run(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "trainer.cli.eval", "--run", str(tmp_path)], capture_output=True, text=True
    )
    assert out.returncode != 0 and "not a training run" in out.stderr


@pytest.mark.slow
def test_two_processes_evaluate_every_checkpoint_as_one_process_does(tmp_path):
    run = train(TrainConfig(total_timesteps=512, seed=2, **SMALL), tmp_path / "run")
    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    cfg = EvalConfig(lengths=[2, 4, 7], episodes=2)
    one = evaluate_run(run, cfg, log=lambda _: None)
    two = evaluate_run(copy, dataclasses.replace(cfg, processes=2), log=lambda _: None)
    assert len(one) == 4 * 3 * 2  # 4 checkpoints, 3 lengths, 2 episodes
    assert one == two
    assert RunDir(run).evaluation.read_text() == RunDir(copy).evaluation.read_text()


def test_a_length_given_twice_is_evaluated_and_written_once(tmp_path):
    run = train(TrainConfig(total_timesteps=256, seed=2, **SMALL), tmp_path / "run")
    rows = evaluate_run(run, EvalConfig(lengths=[3, 2, 3], episodes=2), log=lambda _: None)
    keys = [(r["global_step"], r["num_joints"], r["episode"]) for r in rows]
    assert len(keys) == len(set(keys)) == 2 * 2 * 2  # 2 checkpoints, lengths 3 and 2, 2 episodes
    returns = evaluate_policy(GraphActorCritic(), [3, 2, 3], episodes=2, max_steps=5)
    assert list(returns) == [3, 2] and all(len(v) == 2 for v in returns.values())


class _BangBang(NumpyPolicy):
    """The policy's own mean action, but +-1 on every joint of a 64-joint chain: driven so from rest, 64
    joints can diverge at their first step (MuJoCo's bad-acceleration warning; one of three episodes here)."""

    def mean_actions(self, joint_pos, joint_vel, global_feats, num_joints, parents=None):
        mean = super().mean_actions(joint_pos, joint_vel, global_feats, num_joints, parents)
        return np.where((num_joints == 64)[:, None], bang(mean.shape[1]), mean).astype(np.float32)


def bang(width: int) -> np.ndarray:
    return np.where(np.arange(width) % 2 == 0, 1.0, -1.0)


def test_a_swimmer_whose_physics_diverges_ends_its_episode_while_the_others_go_on():
    policy = GraphActorCritic()
    mixed = evaluate_policy(_BangBang(policy), [64, 3], episodes=3, max_steps=30)  # 64 first: the 3s shift rows
    ended = []
    for k in range(3):  # each 64-joint episode, stepped alone as the env steps it
        env = MorphSwimmerEnv(num_joints=64)
        env.reset(seed=10_000 + k)
        total, steps, terminated = 0.0, 0, False
        while not terminated and steps < 30:
            _, reward, terminated, _, _ = env.step(bang(64))
            total, steps = total + reward, steps + 1
        assert mixed[64][k] == total
        ended.append(steps)
    assert ended == [30, 30, 1]  # the third diverged at its first step (seed 10_002) and ended there
    # the others' rows stay theirs once one swimmer has ended: the returns they get without it (to the
    # last bits of float32 matrix products, which a batch of other rows can round differently)
    np.testing.assert_allclose(mixed[3], evaluate_policy(policy, [3], episodes=3, max_steps=30)[3], rtol=1e-6)


def test_episode_lengths_and_distances_are_those_of_the_env_stepped_alone():
    # How long each episode lasted and how far its root travelled, beside its return: the diverged episode
    # stopped where it ended, the others ran to max_steps.
    policy = _BangBang(GraphActorCritic())
    results = evaluate_episodes(policy, [64, 3], episodes=3, max_steps=30)
    for k in range(3):
        env = MorphSwimmerEnv(num_joints=64)
        env.reset(seed=10_000 + k)
        x0, steps, terminated = env.data.qpos[0], 0, False
        while not terminated and steps < 30:
            _, _, terminated, _, info = env.step(bang(64))
            steps += 1
        assert results[64].steps[k] == steps
        assert results[64].distance[k] == info["x_position"] - x0
    assert list(results[64].steps) == [30, 30, 1] and list(results[3].steps) == [30, 30, 30]
    assert np.all(results[3].distance != 0)  # the 3-joint swimmers moved
    np.testing.assert_array_equal(results[3].returns, evaluate_policy(policy, [64, 3], episodes=3, max_steps=30)[3])


def test_evaluation_runs_the_policy_the_torch_network_computes():
    # The NumPy forward pass the evaluation uses, against the torch policy's own mean action, step by step.
    import torch

    from morph_core.env.swimmer_env import MorphSwimmerEnv
    from morph_core.policy.chains import ChainBatch

    torch.manual_seed(0)
    policy = GraphActorCritic()
    returns = evaluate_policy(policy, [3], episodes=1, max_steps=40)[3]
    env = MorphSwimmerEnv(num_joints=3)
    obs, _ = env.reset(seed=10_000)
    total = 0.0
    with torch.no_grad():
        for _ in range(40):
            mean = policy(ChainBatch.from_observations([obs]))[0].numpy()[0, :3]
            obs, r, _, _, _ = env.step(np.clip(mean, -1.0, 1.0))
            total += r
    assert returns[0] == pytest.approx(total, rel=1e-4, abs=1e-5)


@pytest.mark.slow
def test_from_step_adds_lengths_to_the_late_checkpoints_only(tmp_path):
    # Zero-shot on longer chains late in training: the same checkpoints the stride picks, from a step on.
    run = train(TrainConfig(total_timesteps=640, seed=3, **SMALL), tmp_path / "run")  # checkpoints 128..640
    evaluate_run(run, EvalConfig(lengths=[2], episodes=1, stride=2), log=lambda _: None)  # 128, 384, 640
    rows = evaluate_run(run, EvalConfig(lengths=[4], episodes=1, stride=2, from_step=300), log=lambda _: None)
    steps = {n: sorted({int(r["global_step"]) for r in rows if int(r["num_joints"]) == n}) for n in (2, 4)}
    assert steps == {2: [128, 384, 640], 4: [384, 640]}
    # Past the last checkpoint: the last one is still evaluated.
    rows = evaluate_run(run, EvalConfig(lengths=[5], episodes=1, from_step=10_000), log=lambda _: None)
    assert sorted({int(r["global_step"]) for r in rows if int(r["num_joints"]) == 5}) == [640]


def test_evaluation_runs_a_tree_as_the_policy_computes_it_on_that_tree():
    # A tree's returns are those of the NumPy policy stepped on that tree's own env, with its parents.
    from morph_core.env.bodies import parse_bodies

    torch_policy = GraphActorCritic()
    actor = NumpyPolicy(torch_policy)
    star = parse_bodies("star:3x1").members()[0]
    returns = evaluate_policy(actor, [star, 3], episodes=2, max_steps=40)
    for k in range(2):
        env = MorphSwimmerEnv(num_joints=3)
        obs, _ = env.reset(seed=10_000 + k, options={"tree": star})
        np.testing.assert_array_equal(obs["parents"], [-1, -1, -1])
        total = 0.0
        for _ in range(40):
            mean = actor.mean(obs["joint_pos"], obs["joint_vel"], obs["global"], parents=obs["parents"])
            obs, r, _, _, _ = env.step(np.clip(mean, -1.0, 1.0))
            total += r
        assert returns[star][k] == pytest.approx(total, rel=1e-4, abs=1e-5)
    # the same joint count as a chain is another body, with other returns
    assert not np.allclose(returns[star], returns[3])


@pytest.mark.slow
def test_eval_cli_evaluates_named_trees_beside_chains_and_reads_files_written_before_trees(tmp_path, capsys):
    run = train(TrainConfig(total_timesteps=256, seed=1, **SMALL), tmp_path / "run")
    cfg = EvalConfig(lengths=[2], bodies="star:2x1,y:1x1", episodes=1)
    rows = evaluate_run(run, cfg, log=lambda _: None)
    assert {(r["global_step"], r["body"], r["num_joints"]) for r in rows} == {
        (s, b, n) for s in (128, 256) for b, n in (("chain-2", 2), ("star-2x1", 2), ("y-1x1", 3))
    }
    # An eval.csv of before trees (no body column) reads as chains: nothing is evaluated again.
    with RunDir(run).evaluation.open() as f:
        old = [r for r in csv.DictReader(f) if r["body"].startswith("chain-")]
    with RunDir(run).evaluation.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["global_step", "num_joints", "episode", "return"])
        w.writeheader()
        w.writerows({k: r[k] for k in w.fieldnames} for r in old)
    rows = evaluate_run(run, EvalConfig(lengths=[2], episodes=1), log=lambda _: None)
    assert sorted((int(r["global_step"]), r["body"]) for r in rows) == [(128, "chain-2"), (256, "chain-2")]
    evaluate_run(run, EvalConfig(lengths=[3], episodes=1), log=lambda _: None)  # rewrites it with today's columns
    with RunDir(run).evaluation.open() as f:
        got = {(r["body"], r["steps"] == "", r["distance"] == "") for r in csv.DictReader(f)}
    assert got == {("chain-2", True, True), ("chain-3", False, False)}  # the old rows kept, their new fields empty
    with pytest.raises(ValueError, match="random family"):
        evaluate_run(run, EvalConfig(lengths=[], bodies="random:3-5"), log=lambda _: None)
    # One policy file (a shipped model): a table of the same returns, nothing written.
    from trainer.cli.eval import main

    ckpt = RunDir(run).checkpoints / "policy_00000256.safetensors"
    assert main(["--checkpoint", str(ckpt), "--joints", "--bodies", "y:1x1", "--episodes", "1"]) == 0
    table, said = capsys.readouterr()
    want = next(float(r["return"]) for r in evaluate_run(run, cfg, log=lambda _: None)
                if r["body"] == "y-1x1" and int(r["global_step"]) == 256)  # fmt: skip
    assert f"| y-1x1 | 3 | {want:.1f} ± 0.0 |" in table and "chain-" not in table
    assert said == f"morph-eval: {ckpt}: 1 deterministic episodes (the policy's mean action) on each of 1 bodies\n"
    # A file that is no policy: one line, before any episode; options of --run: refused.
    assert main(["--checkpoint", str(RunDir(run).config), "--episodes", "1"]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("morph-eval: error: ") and len(err.splitlines()) == 1
    with pytest.raises(SystemExit):
        main(["--checkpoint", str(ckpt), "--plots", str(run / "figures")])
    assert "are for --run: --checkpoint evaluates one file and writes nothing" in capsys.readouterr().err
    assert not (run / "figures").exists()


def test_a_tree_run_is_shipped_by_its_chains_and_trees_a_chain_run_by_its_chains_alone():
    table = {"2": 10.0, "3": 20.0, "12": -50.0, "y-1x2": 4.0, "star-3x2": 6.0}
    chains = {"min_joints": 2, "max_joints": 3, "bodies": ""}
    trees = {"min_joints": 2, "max_joints": 3, "bodies": "2-3,random:3-10"}
    assert scored_bodies(chains, table) == ["2", "3"]
    assert scored_bodies({**chains, "bodies": "2-3"}, table) == ["2", "3"]
    assert scored_bodies(trees, table) == ["2", "3", "y-1x2", "star-3x2"]
    # A centipede run by the sizes it trained on; the zero-shot sizes are reported, not scored.
    legged = {"centipede-2": 900.0, "centipede-4": 950.0, "centipede-5": 1500.0, "centipede-10": 300.0}
    assert scored_bodies({**chains, "bodies": "centipede:2-4"}, legged) == ["centipede-2", "centipede-4"]
    assert scored_bodies({**chains, "bodies": "2-3,centipede:2"}, {**table, **legged}) == ["2", "3", "centipede-2"]
    assert [body_key(label) for label in ("chain-2", "chain-40", "y-1x2", "tree-0a1b2c3d")] == [
        "2", "40", "y-1x2", "tree-0a1b2c3d"
    ]  # fmt: skip
