"""``morph-render``: a video of a policy swimming, offscreen, as GIF and/or MP4.

Each chain length, and each body of ``--bodies`` (a spec of the
``morph_core.env.bodies`` grammar whose families are finite: chains and named
trees, e.g. ``star:3x2,y:1x2,comb:4``), is one swimmer driven by the policy's
mean action (no sampling; a tree's policy is given its parent array), filmed
from above by a camera that follows it; several swimmers play side by side
in one frame (``--layout tiled``, one column by default: chains are long and
thin) or one after another (``--layout sequence``). Each view is captioned
with its chain length (a tree: its body label and joints), the trust-region
rule the policy was trained with (the checkpoint's ``clip_mode`` metadata,
else its run's ``config.json``) and the return so far. With ``--bodies`` and
no ``--joints``, only the bodies are filmed.

    morph-render --checkpoint runs/compensated-s1/checkpoints/policy_00743424.safetensors \\
        --joints 2 6 10 20 --gif swim.gif --mp4 swim.mp4
    morph-render --untrained --joints 3 --seconds 4 --gif untrained.gif
    morph-render --checkpoint policy.safetensors --bodies star:3x2,y:1x2,comb:4 --gif trees.gif
    morph-render --checkpoint centipedes/checkpoints/policy_00004096.safetensors --bodies centipede:3,centipede:5 \\
        --height 240 --seconds 4 --gif centipedes.gif

Centipedes (``--bodies centipede:N``) are filmed from the side and above, following the front segment;
a centipede that falls stops there (its caption says so), as its episode would end in training. A
policy's global input is the width it was trained with: a swimmer's 4 features are zero-padded for a
policy that reads 12 (trained with centipedes); a swimmer policy (4) cannot drive a centipede (refused).

Rendering needs offscreen OpenGL: ``MUJOCO_GL`` when set, else EGL, else
OSMesa (``morph_core.env.render.choose_gl_backend``).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path

from morph_core.algo.run_dir import RunDir
from morph_core.constants import MAX_JOINTS, MIN_JOINTS
from morph_core.env.bodies import is_chain_label, parse_bodies
from morph_core.policy.weights import CheckpointError, PolicyWeights, load_checkpoint, untrained_weights
from morph_core.util.config_cli import (
    BoolAction,
    CommandLineParser,
    add_dataclass_options,
    overrides_from_args,
    replace_nested,
)

LAYOUTS = ("tiled", "sequence")
CONTROL_HZ = 25  # the env's control period is 0.04 s


@dataclass
class VideoConfig:
    """What to film and how."""

    lengths: list[int] = field(default_factory=lambda: [2, 6, 10, 20])
    """chain lengths (joints), one swimmer each"""
    bodies: str = ""
    """named bodies to film after the chains of ``lengths``: a spec of finite families (env.bodies), e.g.
    star:3x2,y:1x2,comb:4; every member is one swimmer"""
    seconds: float = 10.0
    """sim time each swimmer swims"""
    layout: str = "tiled"
    """tiled: all lengths side by side in one frame; sequence: one length after another"""
    columns: int = 1
    """views per row when tiled"""
    width: int = 480
    """pixels of one view (at most 640)"""
    height: int = 180
    """pixels of one view (at most 480)"""
    frame_every: int = 2
    """render every k-th control step (k = 2: 12.5 frames per sim second, played in real time)"""
    seed: int = 0
    """reset seed of every swimmer's initial state"""
    gif_colors: int = 256
    """palette size of each GIF frame (fewer: a smaller file)"""

    def check(self) -> None:
        if any(not MIN_JOINTS <= n <= MAX_JOINTS for n in self.lengths):
            raise ValueError(f"lengths must be chain lengths in {MIN_JOINTS}..{MAX_JOINTS}, got {self.lengths}")
        if not self.lengths and not self.bodies:
            raise ValueError("nothing to film: give chain lengths or bodies")
        self.trees()
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {self.layout!r}")
        if not self.seconds > 0 or self.columns < 1 or self.frame_every < 1:
            raise ValueError("seconds must be > 0, columns and frame_every >= 1")
        if not 2 <= self.gif_colors <= 256:
            raise ValueError(f"gif_colors must be in 2..256, got {self.gif_colors}")

    def trees(self) -> list:
        """The ``KinematicTree`` of every body of ``bodies`` (ValueError when the spec is bad or random)."""
        if not self.bodies:
            return []
        members = parse_bodies(self.bodies).members()
        if members is None:
            raise ValueError(f"bodies {self.bodies!r}: a random family has no fixed members to film")
        return members

    def takes(self) -> list:
        """What each swimmer is: chain lengths first, then the bodies' trees."""
        return [*self.lengths, *self.trees()]

    @property
    def steps(self) -> int:
        """control steps each swimmer takes"""
        return max(1, round(self.seconds * CONTROL_HZ))

    @property
    def fps(self) -> float:
        return CONTROL_HZ / self.frame_every

    def frames_per_take(self) -> int:
        """frames of one swimmer: its initial state, then one every ``frame_every`` steps"""
        return self.steps // self.frame_every + 1


def training_rule(weights: PolicyWeights) -> str:
    """The trust-region rule a policy was trained with, as far as its files tell."""
    if not weights.trained:
        return "untrained"
    rule = weights.metadata.get("clip_mode")
    if rule is None:
        # A training checkpoint: the config of the run it belongs to.
        try:
            rule = RunDir.of_checkpoint(weights.source).read_config().get("clip_mode")
        except (OSError, ValueError, AttributeError):
            rule = None
    return f"{rule} clipping" if isinstance(rule, str) and rule else "rule unknown"


def caption(
    num_joints: int, rule: str, episode_return: float, diverged: bool, label: str | None = None, fell: bool = False
) -> str:
    """A view's caption; ``label`` (``bodies.body_label``) names a tree in front of its joint count."""
    joints = f"{num_joints} joint{'s' * (num_joints != 1)}"
    if label is not None and not is_chain_label(label):
        joints = f"{label} ({joints})"
    text = f"{joints}, {rule}, return {episode_return:+.1f}"
    return text + " (physics diverged)" if diverged else text + " (fell)" if fell else text


def _name(take) -> str:
    return f"{take.num_joints} joints" if is_chain_label(take.label) else take.label


def render_video(weights: PolicyWeights, cfg: VideoConfig, gif: Path | None, mp4: Path | None, log=print) -> int:
    """Film ``weights`` as ``cfg`` says into ``gif`` and/or ``mp4``; returns the number of frames.
    ``choose_gl_backend`` must have run (before MuJoCo was imported)."""
    # MuJoCo and the envs load after choose_gl_backend (MUJOCO_GL is read when MuJoCo loads)
    import numpy as np

    from morph_core.env.bodies import is_walker
    from morph_core.env.render import Take
    from morph_core.policy.numpy_actor import NumpyPolicy
    from trainer.reports.video import VideoWriter, add_caption, caption_font, tile

    cfg.check()
    policy = NumpyPolicy(weights)
    global_width = weights.config.global_features
    if global_width < 12 and any(is_walker(b) for b in cfg.takes()):
        raise ValueError(f"this policy reads {global_width} global features, a walker 12: train it on walkers")

    def mean(pos, vel, glob, **kw):  # a swimmer's 4 globals, zero-padded to a 12-wide policy's input
        return policy.mean(pos, vel, np.pad(glob, (0, global_width - len(glob))), **kw)

    rule = training_rule(weights)
    font = caption_font(max(10, cfg.height // 12))
    writer = VideoWriter(cfg.fps, gif=gif, mp4=mp4, gif_colors=cfg.gif_colors)
    bodies = cfg.takes()
    groups = [bodies] if cfg.layout == "tiled" else [[body] for body in bodies]
    try:
        for group in groups:
            takes = [Take(body, mean, cfg.width, cfg.height, reset_seed=cfg.seed) for body in group]
            try:
                for step in range(cfg.steps + 1):
                    if step % cfg.frame_every == 0:
                        views = [
                            add_caption(
                                t.frame(),
                                caption(t.num_joints, rule, t.episode_return, t.diverged, t.label, t.fell),
                                font,
                            )
                            for t in takes
                        ]
                        writer.add(tile(views, cfg.columns))
                    if step < cfg.steps:
                        for t in takes:
                            t.step()
            finally:
                for t in takes:
                    t.close()
            log(", ".join(f"{_name(t)}: return {t.episode_return:+.1f}" for t in takes))
        frames = writer.frames
        for path in writer.close():
            log(f"wrote {path}")
        return frames
    except BaseException:
        writer.abort()
        raise


def main(argv: list[str] | None = None) -> None:
    parser = CommandLineParser(
        prog="morph-render", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", type=Path, help="policy checkpoint (.safetensors, its .json beside it)")
    source.add_argument("--untrained", action=BoolAction, default=False, help="a freshly initialised policy instead")
    parser.add_argument("--policy-seed", type=int, default=0, help="seed of the untrained policy's weights")
    parser.add_argument("--gif", type=Path, default=None, help="write an animated GIF here")
    parser.add_argument("--mp4", type=Path, default=None, help="write an H.264 MP4 here")
    add_dataclass_options(parser, VideoConfig, skip=("lengths",))
    parser.add_argument("--joints", dest="lengths", type=int, nargs="+", default=None, metavar="N",
                        help="chain lengths, joints per swimmer (default: 2 6 10 20)")  # fmt: skip
    parser.add_deprecated_alias("--lengths", "--joints")
    args = parser.parse_args(argv)
    if not args.untrained and args.checkpoint is None:
        parser.error("give --checkpoint PATH or --untrained")
    if args.gif is None and args.mp4 is None:
        parser.error("give --gif PATH, --mp4 PATH or both")
    overrides = overrides_from_args(args, VideoConfig)
    if args.lengths is not None:
        overrides["lengths"] = args.lengths
    elif args.bodies:
        overrides["lengths"] = []  # --bodies alone films the bodies alone
    cfg = replace_nested(VideoConfig(), overrides)
    try:
        cfg.check()
    except ValueError as err:
        parser.error(str(err))

    from morph_core.env.render import RenderUnavailable, choose_gl_backend  # imports no MuJoCo
    from trainer.reports.video import VideoError, ffmpeg_exe

    try:
        weights = untrained_weights(seed=args.policy_seed) if args.untrained else load_checkpoint(args.checkpoint)
        if args.mp4 is not None:
            ffmpeg_exe()  # fail before rendering, not after
        choose_gl_backend()
        render_video(weights, cfg, args.gif, args.mp4, log=lambda text: print(text, file=sys.stderr))
    except (CheckpointError, RenderUnavailable, VideoError) as err:
        print(f"morph-render: error: {err}", file=sys.stderr)
        sys.exit(1)
    except ValueError as err:  # e.g. a view larger than MuJoCo's offscreen buffer
        print(f"morph-render: error: {err}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
