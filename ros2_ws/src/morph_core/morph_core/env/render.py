"""Offscreen frames of a policy swimming: chains of chosen lengths or trees, each filmed by a camera that follows it.

``choose_gl_backend`` must run before anything imports MuJoCo (it picks the
OpenGL backend, which MuJoCo and PyOpenGL fix at import): ``MUJOCO_GL`` when
set, else EGL, else OSMesa, each tried in a short child process first, so a
machine without either gets one clear line instead of a crash deep inside
OpenGL. MuJoCo (and the env, which imports it) is imported here
only inside functions for the same reason.

``Take`` steps one swimmer with a controller's deterministic action (the
policy's mean, clipped to the motors' range) and renders it with
``mujoco.Renderer`` through a tracking camera: it follows the torso's
subtree (the whole chain) from straight above, from a height at which the
chain fits the frame's width, so a 20-joint swimmer fits its tile as a
2-joint one does (each at its own scale; the floor's checks are 2.7 m). A
tree is framed by its longest branch (``bodies.tree_depth``) and, since its
branches fan out sideways, shown at least that tall.
"""

from __future__ import annotations

import math
import numbers
import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from morph_core.env.centipede_model import SEGMENT_SPACING
from morph_core.env.model import SEGMENT_LENGTH, check_num_joints

if TYPE_CHECKING:
    from morph_core.policy.tree import KinematicTree

GL_BACKENDS = ("egl", "osmesa")
"""offscreen OpenGL backends tried in this order when MUJOCO_GL is unset"""

# A child process that makes a context and draws one frame: the same path the renderer takes.
_PROBE = """
import mujoco
m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=".1"/></worldbody></mujoco>')
r = mujoco.Renderer(m, 8, 8)
d = mujoco.MjData(m)
r.update_scene(d)
r.render()
r.close()
"""
_PROBE_TIMEOUT = 120.0  # s; importing mujoco on a loaded 2-core machine can take many seconds

Controller = Callable[..., np.ndarray]
"""(joint_pos [N], joint_vel [N], global [4]) -> action [N], e.g. ``NumpyPolicy.mean``; for a tree it is also
given ``parents=`` [N] (``NumpyPolicy.mean`` takes it)"""


class RenderUnavailable(RuntimeError):
    """No offscreen OpenGL; ``str(err)`` is one line saying what was tried."""


def _last_line(text: str) -> str:
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else "no output"


def probe_gl_backend(backend: str) -> str | None:
    """None when ``backend`` renders a frame in a fresh process, else the reason it does not (one line)."""
    env = dict(os.environ, MUJOCO_GL=backend)
    env.pop("PYOPENGL_PLATFORM", None)  # MuJoCo's backend module sets the matching one
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=_PROBE_TIMEOUT
        )
    except subprocess.TimeoutExpired:
        return f"no frame within {_PROBE_TIMEOUT:.0f} s"
    return None if done.returncode == 0 else _last_line(done.stderr)


def choose_gl_backend() -> str:
    """Make ``MUJOCO_GL`` name a backend that renders here; returns it.

    A ``MUJOCO_GL`` already set is checked, not replaced; else the first of ``GL_BACKENDS`` that
    works is set. Raises ``RenderUnavailable`` when none works, or when MuJoCo was imported
    before (it fixed its backend then)."""
    chosen = os.environ.get("MUJOCO_GL", "").strip()
    if "mujoco" in sys.modules:
        if chosen:
            return chosen  # fixed at that import; the renderer will say if it fails
        raise RenderUnavailable(
            "MuJoCo was imported before an OpenGL backend was chosen: set MUJOCO_GL=egl (or osmesa) first"
        )
    if chosen:
        reason = probe_gl_backend(chosen)
        if reason is not None:
            raise RenderUnavailable(f"MUJOCO_GL={chosen} cannot render offscreen here ({reason})")
        return chosen
    reasons = []
    for backend in GL_BACKENDS:
        reason = probe_gl_backend(backend)
        if reason is None:
            os.environ["MUJOCO_GL"] = backend
            return backend
        reasons.append(f"{backend}: {reason}")
    raise RenderUnavailable(
        "no offscreen OpenGL (" + "; ".join(reasons) + "); install EGL (libegl1) or OSMesa (libosmesa6), "
        "or set MUJOCO_GL"
    )


@dataclass(frozen=True)
class CameraView:
    """How the tracking camera frames a chain: it looks at the chain's centre of mass from a distance
    at which the whole chain, stretched out along the image's width, fits with ``pad`` to spare."""

    elevation: float = -90.0
    """degrees; -90 looks straight down (the swimmer moves in the plane)"""
    azimuth: float = 90.0
    """degrees; 90 puts the world's +x (forward) to the right of the image"""
    pad: float = 1.0
    """metres left free beyond each end of a stretched chain"""
    min_extent: float = 4.0
    """metres of floor the image's height shows at least (short chains curl up)"""
    shadows: bool = False
    """shadows and floor reflections: Swimmer-v5's look, but about five times slower to render"""

    def distance(self, num_joints: int, aspect: float, fovy_deg: float, depth: int | None = None) -> float:
        """Camera distance [m] for a chain of ``num_joints`` in an image of width / height ``aspect``; for a
        tree, ``depth`` is its longest branch's joints (``bodies.tree_depth``) and the image is at least as
        tall as the tree is long (its branches fan sideways)."""
        length = ((num_joints if depth is None else depth) + 1) * SEGMENT_LENGTH
        height = max((length + 2 * self.pad) / aspect, self.min_extent)
        if depth is not None:
            height = max(height, length + 2 * self.pad)
        return height / (2 * math.tan(math.radians(fovy_deg) / 2))


CENTIPEDE_VIEW = CameraView(elevation=-25.0, azimuth=90.0, pad=1.0, min_extent=3.0, shadows=True)
"""a centipede walks on a floor: filmed from the side and above (forward to the right), with shadows so that
its feet's contacts show"""


class Take:
    """One body driven by ``controller``, filmed at ``width`` x ``height``: ``body`` a chain length
    (``num_joints``), a ``KinematicTree`` (reset as ``reset(options={"tree": body})``) or a
    ``bodies.Centipede`` (a ``MorphCentipedeEnv`` of its leg pairs); ``label`` is its ``bodies.body_label``.
    A centipede that falls (Ant-v5's health rule) ends its take like a diverged swimmer: ``fell``.

    ``reset_seed`` seeds the env's reset noise. ``step()`` advances one control period and adds the
    reward to ``episode_return``; after the physics diverges (``diverged``) the swimmer stays where
    it was and ``step()`` does nothing. ``frame()`` is the current view as uint8 [height, width, 3].
    """

    def __init__(
        self,
        body: int | KinematicTree,
        controller: Controller,
        width: int,
        height: int,
        reset_seed: int = 0,
        view: CameraView | None = None,
    ):
        import mujoco  # MuJoCo and the envs load after the GL backend is chosen (MUJOCO_GL is read at load)

        from morph_core.env.bodies import Centipede, is_walker, tree_depth
        from morph_core.env.centipede import MorphCentipedeEnv
        from morph_core.env.mjcf_body import MjcfBody
        from morph_core.env.swimmer_env import MorphSwimmerEnv

        centipede = is_walker(body)
        tree = not isinstance(body, numbers.Integral)
        self.num_joints = body.num_joints if tree else check_num_joints(body)
        self._controller = controller
        if centipede:
            self.env = (MorphCentipedeEnv(leg_pairs=body.leg_pairs) if isinstance(body, Centipede)
                        else MorphCentipedeEnv(body=body))  # fmt: skip
            self._obs, _ = self.env.reset(seed=reset_seed)
        else:
            self.env = MorphSwimmerEnv(num_joints=self.num_joints)
            options = {"body": body} if isinstance(body, MjcfBody) else {"tree": body} if tree else None
            self._obs, _ = self.env.reset(seed=reset_seed, options=options)
        self.tree, self.label = self.env.tree, self.env.body_label
        self._parents = None if self.tree.is_chain else self.env.parents
        model = self.env.model
        limit_w, limit_h = model.vis.global_.offwidth, model.vis.global_.offheight
        if not (16 <= width <= limit_w and 16 <= height <= limit_h):
            raise ValueError(f"frame size must be 16..{limit_w} x 16..{limit_h} pixels, got {width} x {height}")
        self._renderer = mujoco.Renderer(model, height=height, width=width)
        view = view or (CENTIPEDE_VIEW if centipede else CameraView())
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        self.camera.trackbodyid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, self.tree.root_link)
        if centipede:  # the body's length along x: its segments, framed like a chain of that length
            # a legged body: framed as a 3-pair centipede (its torso and legs span about as much)
            length = getattr(body, "leg_pairs", 3) * SEGMENT_SPACING + 1.0  # and a leg's reach at each end
            extent = max((length + 2 * view.pad) / (width / height), view.min_extent)
            self.camera.distance = extent / (2 * math.tan(math.radians(model.vis.global_.fovy) / 2))
        else:
            depth = None if self._parents is None else tree_depth(self._parents)
            self.camera.distance = view.distance(self.num_joints, width / height, model.vis.global_.fovy, depth)
        self.camera.elevation = view.elevation
        self.camera.azimuth = view.azimuth
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
            self._renderer.scene.flags[flag] = view.shadows
        self.episode_return = 0.0
        self.steps = 0
        self.diverged = False
        self.fell = False

    def step(self) -> None:
        if self.diverged or self.fell:
            return
        o = self._obs
        if self._parents is None:
            action = self._controller(o["joint_pos"], o["joint_vel"], o["global"])
        else:
            action = self._controller(o["joint_pos"], o["joint_vel"], o["global"], parents=self._parents)
        action = np.clip(action, -1.0, 1.0)
        self._obs, reward, terminated, _, info = self.env.step(np.asarray(action, dtype=np.float64))
        self.episode_return += float(reward)
        self.steps += 1
        self.diverged = bool(terminated and info.get("physics_unstable"))
        self.fell = bool(terminated and not self.diverged)

    def frame(self) -> np.ndarray:
        self._renderer.update_scene(self.env.data, camera=self.camera)
        return self._renderer.render().copy()

    def close(self) -> None:
        self._renderer.close()

    def __enter__(self) -> Take:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
