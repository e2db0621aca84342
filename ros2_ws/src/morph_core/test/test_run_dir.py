"""``algo.run_dir.RunDir``, the one owner of a run directory's file names: what a run writes is what it names,
the names are those of the runs already on disk (old runs keep loading), and no other module spells them."""

import ast
from pathlib import Path

from morph_core.algo.checkpoint import previous_state_path
from morph_core.algo.run_dir import RunDir, checkpoint_step
from morph_core.algo.train import TrainConfig, train

ROOT = Path(__file__).resolve().parents[4]

# The layout runs on disk have (docs/results_data, users' runs): a change here is a change of format.
ON_DISK = {"config": "config.json", "init": "init.json", "progress": "progress.csv", "tensorboard": "tb",
           "checkpoints": "checkpoints", "state": "state.safetensors", "previous_state": "state.prev.safetensors",
           "evaluation": "eval.csv"}  # fmt: skip


def _paths(files: RunDir) -> dict[str, Path]:
    return {name: getattr(files, name) for name in ON_DISK}


def test_every_name_is_the_one_on_disk_and_a_checkpoint_step_round_trips(tmp_path):
    files = RunDir(tmp_path / "run")
    assert {k: p.name for k, p in _paths(files).items()} == ON_DISK
    assert all(p.parent == files.path for p in _paths(files).values())
    assert files.previous_state == previous_state_path(files.state)  # where the state writer keeps the old one
    for step in (0, 7, 12_288, 10**9):
        path = files.checkpoint(step)
        assert path.parent == files.checkpoints and checkpoint_step(path) == step
        assert RunDir.of_checkpoint(path) == files
    assert checkpoint_step("policy_final.safetensors") is None and checkpoint_step("policy_00000001.json") is None


def test_saved_checkpoints_are_by_step_and_only_checkpoints(tmp_path):
    files = RunDir(tmp_path)
    files.checkpoints.mkdir()
    for name in ("policy_00000200.safetensors", "policy_00000010.safetensors", "policy_00000010.json",
                 "policy_best.safetensors", "notes.txt"):  # fmt: skip
        (files.checkpoints / name).touch()
    assert files.saved_checkpoints() == [(10, files.checkpoint(10)), (200, files.checkpoint(200))]
    assert RunDir(tmp_path / "none").saved_checkpoints() == []


def test_a_run_writes_only_what_run_dir_names(tmp_path):
    cfg = TrainConfig(num_envs=1, num_steps=128, minibatch_size=64, update_epochs=1, checkpoint_interval=128,
                      total_timesteps=256, compile=False, progress_bar=False, tensorboard=True, min_joints=2,
                      max_joints=3, seed=1)  # fmt: skip
    files = RunDir(train(cfg, tmp_path / "run"))
    named = {p.name for p in _paths(files).values()}
    assert {p.name for p in files.path.iterdir()} <= named
    written = {"config", "progress", "tensorboard", "checkpoints", "state", "previous_state"}
    assert all(_paths(files)[k].exists() for k in written)
    assert [step for step, _ in files.saved_checkpoints()] == [128, 256]
    assert files.read_config()["seed"] == 1 and files.has_state()


def _spellings(path: Path) -> list[str]:
    """Where a module spells a run directory's file name itself: a string that is one of the names, a path
    joined with one (``run / "tb"``), or a checkpoint's name pattern. Docstrings and messages that mention a
    name in a sentence are prose, not spellings."""
    names = set(ON_DISK.values())
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            text = node.value
            if text in names or "policy_*.safetensors" in text or text.endswith(tuple(f"/{n}" for n in names)):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {text!r}")
        elif isinstance(node, ast.JoinedStr):
            parts = [v.value for v in node.values if isinstance(v, ast.Constant)]
            if parts[:1] == ["policy_"] and parts[-1:] == [".safetensors"]:
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: f'policy_...safetensors'")
    return found


def test_no_module_but_run_dir_spells_a_run_directory_file():
    sources = [p for d in ("ros2_ws/src", "bench", "scripts", "tests") for p in (ROOT / d).rglob("*.py")]
    sources = [p for p in sources if p.name not in ("run_dir.py", Path(__file__).name) and "/build/" not in str(p)]
    assert len(sources) > 100  # the tree was found
    found = [line for p in sources for line in _spellings(p)]
    assert not found, "spell these through algo.run_dir.RunDir:\n" + "\n".join(found)
