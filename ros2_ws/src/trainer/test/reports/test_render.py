"""morph-render end to end: real MuJoCo rendering offscreen, real GIF and MP4 files read back.

The CLI runs in a child process: the OpenGL backend is fixed when MuJoCo is
first imported, and this test process may already have imported it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
from PIL import Image

from morph_core.algo.run_dir import RunDir
from morph_core.policy.weights import load_checkpoint, untrained_weights
from trainer.cli.render import VideoConfig, caption, training_rule

BIN = Path(sys.executable).parent
# The shipped policy swims from its first steps, so consecutive frames surely differ.
SHIPPED = (
    Path(__file__).resolve().parents[3]
    / "morph_policy_node"
    / "morph_policy_node"
    / "models"
    / "swimmer_gnn.safetensors"
)


def _render(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(BIN / "morph-render"), *args], capture_output=True, text=True, timeout=600, env=env or dict(os.environ)
    )


def _gif_frames(path: Path) -> list[np.ndarray]:
    frames = []
    with Image.open(path) as im:
        for k in range(im.n_frames):
            im.seek(k)
            frames.append(np.asarray(im.convert("RGB")))
    return frames


def _check_frames(frames: list[np.ndarray], shape: tuple[int, int]) -> None:
    for f in frames:
        assert f.shape == (*shape, 3)
        assert f.std() > 20  # a scene (checkered floor, swimmer, caption), not a blank image
    # the swimmers move and the tracking camera follows: no two consecutive frames alike
    assert all(np.abs(a.astype(int) - b).mean() > 0.5 for a, b in zip(frames, frames[1:], strict=False))


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_tiled_gif_and_mp4_read_back(tmp_path):
    gif, mp4 = tmp_path / "out" / "swim.gif", tmp_path / "out" / "swim.mp4"
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}  # the default choice: EGL, else OSMesa
    done = _render(
        "--checkpoint", str(SHIPPED), "--joints", "2", "5", "--seconds", "0.4", "--frame-every", "2",
        "--layout", "tiled", "--columns", "2", "--width", "96", "--height", "64", "--gif", str(gif), "--mp4", str(mp4),
        env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    cfg = VideoConfig(seconds=0.4, frame_every=2)
    expected = cfg.frames_per_take()
    assert expected == 6  # 10 control steps: the initial state and every second step after it
    frames = _gif_frames(gif)
    assert len(frames) == expected
    _check_frames(frames, (64, 2 * 96 + 2))
    with Image.open(gif) as im:
        assert im.info["duration"] == 80  # ms: 12.5 frames per sim second, played in real time
    # each view has its own swimmer: the two halves differ
    assert np.abs(frames[-1][:, :96].astype(int) - frames[-1][:, 98:]).mean() > 1

    reader = imageio_ffmpeg.read_frames(str(mp4))
    meta = reader.__next__()
    assert tuple(meta["size"]) == (2 * 96 + 2, 64)
    assert meta["fps"] == pytest.approx(12.5)
    decoded = [np.frombuffer(b, np.uint8).reshape(64, 194, 3) for b in reader]
    assert len(decoded) == expected
    _check_frames(decoded, (64, 194))
    # the MP4 shows what the GIF shows (lossy: close, not equal)
    assert np.abs(decoded[-1].astype(int) - frames[-1]).mean() < 12
    assert not list((tmp_path / "out").glob(".*.tmp"))  # atomic writes leave no temporaries


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_sequence_of_lengths_one_after_another(tmp_path):
    gif = tmp_path / "seq.gif"
    done = _render(
        "--checkpoint", str(SHIPPED), "--joints", "1", "3", "--seconds", "0.24", "--frame-every", "1",
        "--layout", "sequence", "--width", "80", "--height", "48", "--gif", str(gif),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    frames = _gif_frames(gif)
    assert len(frames) == 2 * VideoConfig(seconds=0.24, frame_every=1).frames_per_take() == 14
    _check_frames(frames, (48, 80))


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_untrained_policy_mp4(tmp_path):
    mp4 = tmp_path / "untrained.mp4"
    done = _render(
        "--untrained", "--joints", "4", "--seconds", "0.2", "--width", "64", "--height", "48", "--mp4", str(mp4)
    )
    assert done.returncode == 0, done.stderr
    n_frames, _ = imageio_ffmpeg.count_frames_and_secs(str(mp4))
    assert n_frames == VideoConfig(seconds=0.2).frames_per_take() == 3


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_trees_are_filmed_beside_chains_and_captioned_with_their_label(tmp_path):
    gif = tmp_path / "trees.gif"
    done = _render(
        "--checkpoint", str(SHIPPED), "--joints", "3", "--bodies", "star:3x1,y:1x2", "--seconds", "0.24",
        "--frame-every", "2", "--width", "96", "--height", "64", "--gif", str(gif),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "star-3x1: return" in done.stderr and "y-1x2: return" in done.stderr and "3 joints: return" in done.stderr
    frames = _gif_frames(gif)
    assert len(frames) == VideoConfig(seconds=0.24, frame_every=2).frames_per_take() == 4
    _check_frames(frames, (3 * 64 + 2 * 2, 96))  # three views in one column
    views = [frames[-1][k * 66 : k * 66 + 64] for k in range(3)]
    assert all(np.abs(a.astype(int) - b).mean() > 1 for a, b in zip(views, views[1:], strict=False))


def test_bodies_are_filmed_after_the_lengths():
    from morph_core.env.bodies import body_label

    takes = VideoConfig(lengths=[4], bodies="star:2x1,2-3").takes()
    assert takes[0] == 4 and [body_label(t) for t in takes[1:]] == ["star-2x1", "chain-2", "chain-3"]
    with pytest.raises(ValueError, match="nothing to film"):
        VideoConfig(lengths=[]).check()


def test_a_broken_backend_is_one_clear_line(tmp_path):
    # glvnd with no EGL vendor: EGL cannot make a display on any machine.
    env = dict(os.environ, MUJOCO_GL="egl", __EGL_VENDOR_LIBRARY_FILENAMES=str(tmp_path / "none.json"))
    done = _render("--untrained", "--seconds", "0.2", "--gif", str(tmp_path / "x.gif"), env=env)
    assert done.returncode == 1
    assert done.stderr.strip().startswith("morph-render: error: MUJOCO_GL=egl cannot render offscreen here")
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x.gif").exists()

    # Unset: EGL fails the same way, then OSMesa is tried; it works or the one line names both.
    env.pop("MUJOCO_GL")
    done = _render("--untrained", "--seconds", "0.2", "--gif", str(tmp_path / "y.gif"), env=env)
    if done.returncode == 0:
        assert (tmp_path / "y.gif").exists()  # this machine has OSMesa
    else:
        line = done.stderr.strip()
        assert len(line.splitlines()) == 1 and "egl:" in line and "osmesa:" in line


@pytest.mark.parametrize(
    "args, message",
    [
        (["--untrained", "--gif", "x.gif", "--joints", "0"], "lengths"),
        (["--untrained", "--gif", "x.gif", "--layout", "grid"], "layout"),
        (["--untrained"], "--gif"),
        (["--checkpoint", "nowhere.safetensors", "--gif", "x.gif"], "no such file"),
        (["--untrained", "--gif", "x.gif", "--width", "5000"], "frame size"),
        (["--untrained", "--gif", "x.gif", "--bodies", "random:3-5"], "no fixed members"),
        (["--untrained", "--gif", "x.gif", "--bodies", "octopus:3"], "unknown body family"),
    ],
)
def test_bad_input_is_refused_in_one_line(tmp_path, args, message):
    done = subprocess.run([str(BIN / "morph-render"), *args], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode in (1, 2)
    assert message in done.stderr
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "x.gif").exists()


def test_training_rule_from_metadata_or_run_config(tmp_path):
    shipped = load_checkpoint(SHIPPED)
    assert training_rule(shipped) == f"{shipped.metadata['clip_mode']} clipping"
    assert training_rule(untrained_weights()) == "untrained"

    # A training checkpoint carries only its step; the rule is in its run's config.json.
    run = tmp_path / "run"
    RunDir(run).checkpoints.mkdir(parents=True)
    ckpt = RunDir(run).checkpoints / "policy_00006000.safetensors"
    ckpt.write_bytes(SHIPPED.read_bytes())
    meta = json.loads(SHIPPED.with_suffix(".json").read_text())
    meta["metadata"] = {"global_step": 6000}
    ckpt.with_suffix(".json").write_text(json.dumps(meta))
    assert training_rule(load_checkpoint(ckpt)) == "rule unknown"
    RunDir(run).config.write_text(json.dumps({"clip_mode": "fixed"}))
    assert training_rule(load_checkpoint(ckpt)) == "fixed clipping"


def test_caption_text():
    assert caption(1, "fixed clipping", 0.04, False) == "1 joint, fixed clipping, return +0.0"
    assert caption(20, "untrained", -3.25, True) == "20 joints, untrained, return -3.2 (physics diverged)"
    assert caption(6, "fixed clipping", 1.0, False, "star-3x2") == "star-3x2 (6 joints), fixed clipping, return +1.0"
    assert caption(4, "untrained", 0.0, False, "chain-4") == "4 joints, untrained, return +0.0"
