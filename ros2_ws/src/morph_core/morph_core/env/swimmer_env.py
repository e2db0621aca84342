"""Gymnasium environment: the Swimmer-v5 task for a chain of any length, or a kinematic tree.

``num_joints`` is an int (fixed chain) or an inclusive range ``(lo, hi)``
from which the chain length is drawn at every reset with the env's seeded
RNG. ``bodies`` (a spec, ``env.bodies``) replaces it with body families,
trees included, one body drawn at every reset from the same RNG; a spec of
one chain range draws exactly as ``num_joints`` does. With 2 joints and
``observation_mode="flat"`` this is Swimmer-v5, step for step (see the
equivalence test).
"""

from __future__ import annotations

import numbers

import gymnasium
import mujoco
import numpy as np
from gymnasium import spaces

import morph_core.env.registration  # noqa: F401  (using an env registers the ids)
from morph_core.env.bodies import BodyMix, body_label, parse_bodies, swimmers_only
from morph_core.env.mjcf_body import MjcfBody
from morph_core.env.mjcf_robot import DIVERGENCE_WARNING
from morph_core.env.model import body_parents, check_num_joints, swimmer_model
from morph_core.env.reward import CTRL_COST_WEIGHT, FORWARD_REWARD_WEIGHT, control_cost
from morph_core.policy.tree import KinematicTree, swimmer_joint_names

OBSERVATION_MODES = ("graph", "flat")
GLOBAL_FEATURES = ("yaw", "yaw_rate", "vx", "vy")


def write_graph_observation(qpos, qvel, num_joints: int, joint_pos, joint_vel, global_feats) -> None:
    """The graph observation of a swimmer's MuJoCo state (``qpos``, ``qvel``) written into padded arrays: the
    joints' angles and velocities into the first ``num_joints`` entries of ``joint_pos`` and ``joint_vel`` (the
    rest zeroed), ``GLOBAL_FEATURES`` into ``global_feats``. One swimmer (1-D arrays) or several (a row each)."""
    n = num_joints
    joint_pos[..., :n], joint_vel[..., :n] = qpos[..., 3:], qvel[..., 3:]
    joint_pos[..., n:], joint_vel[..., n:] = 0.0, 0.0
    global_feats[..., 0], global_feats[..., 1] = qpos[..., 2], qvel[..., 2]  # yaw, yaw rate
    global_feats[..., 2], global_feats[..., 3] = qvel[..., 0], qvel[..., 1]  # vx, vy


def _check_joint_range(num_joints) -> tuple[int, int]:
    if isinstance(num_joints, numbers.Integral) and not isinstance(num_joints, bool):
        n = check_num_joints(num_joints)
        return n, n
    try:
        lo, hi = num_joints
    except (TypeError, ValueError):
        raise TypeError(f"num_joints must be an int or a (lo, hi) pair, got {num_joints!r}") from None
    lo, hi = check_num_joints(lo), check_num_joints(hi)
    if lo > hi:
        raise ValueError(f"num_joints range is empty: lo={lo} > hi={hi}")
    return lo, hi


class MorphSwimmerEnv(gymnasium.Env):
    """Planar swimmer in a viscous medium; reward = forward speed - 1e-4 |a|^2.

    Episodes never terminate, except when the physics diverges (MuJoCo's bad
    acceleration warning, ``info["physics_unstable"]``).

    Graph observations are a dict: ``joint_pos`` and ``joint_vel`` (one entry
    per joint, in the tree's order: torso to tail for a chain), ``global``
    (yaw, yaw rate, vx, vy of the torso frame) and ``parents`` ([N] int64:
    joint j's parent joint, -1 when it hangs off the torso; a chain's is
    [-1, 0, ..., N-2]).

    ``tree`` is the current body (a ``KinematicTree`` with the swimmer's joint
    names, root link ``torso``: ``KinematicTree.from_mujoco(model)``), ``parents``
    its read-only parent array; ``info`` carries ``body`` (``bodies.body_label``)
    and ``topology_hash``.
    """

    metadata = {"render_modes": [], "render_fps": 25}

    def __init__(
        self,
        num_joints: int | tuple[int, int] = 2,
        observation_mode: str = "graph",
        frame_skip: int = 4,
        forward_reward_weight: float = FORWARD_REWARD_WEIGHT,
        ctrl_cost_weight: float = CTRL_COST_WEIGHT,
        reset_noise_scale: float = 0.1,
        bodies: str | BodyMix | None = None,
    ):
        if observation_mode not in OBSERVATION_MODES:
            raise ValueError(f"observation_mode must be one of {OBSERVATION_MODES}, got {observation_mode!r}")
        if frame_skip < 1:
            raise ValueError(f"frame_skip must be >= 1, got {frame_skip}")
        if bodies is not None:
            self.bodies: BodyMix | None = parse_bodies(bodies) if isinstance(bodies, str) else bodies
            if not isinstance(self.bodies, BodyMix):
                raise TypeError(f"bodies must be a spec string or a BodyMix, got {type(bodies).__name__}")
            swimmers_only(self.bodies, "MorphSwimmerEnv")
            self.joint_range = self.bodies.joint_range
        else:
            self.bodies = None
            self.joint_range = _check_joint_range(num_joints)
        self.observation_mode = observation_mode
        self.frame_skip = int(frame_skip)
        self.forward_reward_weight = forward_reward_weight
        self.ctrl_cost_weight = ctrl_cost_weight
        self.reset_noise_scale = reset_noise_scale
        self.num_joints = 0
        self.tree: KinematicTree | None = None
        self._shape: tuple[int, ...] = ()
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._build(self.joint_range[0] if self.bodies is None else self.bodies.first())

    # -- body ----------------------------------------------------------------
    def _build(self, body: int | KinematicTree | MjcfBody) -> None:
        """Switch to a body: a chain length or a tree (a ``KinematicTree`` or a parent array; the compiled
        model is cached per shape), or a user's MJCF of a planar root (``env.mjcf_body``)."""
        mjcf = body if isinstance(body, MjcfBody) else None
        parents = ("mjcf", mjcf.path) if mjcf is not None else body_parents(body)
        if parents == self._shape:
            mujoco.mj_resetData(self.model, self.data)
            return
        if mjcf is not None:
            if mjcf.task != "swimmer":
                raise ValueError(f"{mjcf.path!r} has a free root: a walker (MorphCentipedeEnv runs it)")
            self.tree, self.body_label, self.model = mjcf.tree, mjcf.label, mjcf.model()
            self._ctrl_map = mjcf.ctrl_map()
        else:
            self.tree = KinematicTree(swimmer_joint_names(len(parents)), np.array(parents, dtype=np.int64), "torso")
            self.body_label = body_label(self.tree)
            self.model = swimmer_model(parents)
            self._ctrl_map = None
        self.mjcf = mjcf
        num_joints = self.tree.num_joints
        self.num_joints = num_joints
        self.parents = self.tree.parents  # read-only int64 [N]
        self.topology_hash = self.tree.topology_hash
        self._shape = parents
        self.data = mujoco.MjData(self.model)
        # Views into this MjData, taken once: each attribute read builds a new array (~0.1 µs, and the
        # step reads them for every swimmer at every step).
        self._qpos, self._qvel, self._ctrl = self.data.qpos, self.data.qvel, self.data.ctrl
        self._badqacc = self.data.warning[DIVERGENCE_WARNING]
        self.dt = self.model.opt.timestep * self.frame_skip
        self.action_space = spaces.Box(-1.0, 1.0, shape=(num_joints,), dtype=np.float32)
        self.observation_space = self._observation_space(num_joints)

    def _observation_space(self, n: int) -> spaces.Space:
        if self.observation_mode == "flat":
            return spaces.Box(-np.inf, np.inf, shape=(2 * n + 4,), dtype=np.float64)
        return spaces.Dict(
            {
                "joint_pos": spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64),
                "joint_vel": spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64),
                "global": spaces.Box(-np.inf, np.inf, shape=(len(GLOBAL_FEATURES),), dtype=np.float64),
                "parents": spaces.Box(-1, max(n - 1, 0), shape=(n,), dtype=np.int64),  # parents[j] in -1..j-1
            }
        )

    # -- gymnasium API -------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset; ``options`` may force this episode's body (nothing is drawn then): ``{"num_joints": n}`` a
        chain, ``{"tree": KinematicTree}`` or ``{"parents": [...]}`` a tree (parents in pre-order, see
        ``model.check_parents``; a tree's own joint names are not kept, the swimmer's are)."""
        super().reset(seed=seed)
        forced = [key for key in ("num_joints", "tree", "parents", "body") if options and key in options]
        if len(forced) > 1:
            raise ValueError(f"reset options force the body twice: {forced}")
        if forced == ["num_joints"]:
            body = check_num_joints(options["num_joints"])
        elif forced == ["tree"]:
            if not isinstance(options["tree"], KinematicTree):
                raise TypeError(f"options['tree'] must be a KinematicTree, got {type(options['tree']).__name__}")
            body = options["tree"]
        elif forced == ["parents"]:
            body = options["parents"]
        elif forced == ["body"]:  # a user's MJCF (``env.mjcf_body.MjcfBody``)
            body = options["body"]
        elif self.bodies is not None:
            body = self.bodies.draw(self.np_random)
        else:
            lo, hi = self.joint_range
            body = lo if lo == hi else int(self.np_random.integers(lo, hi + 1))
        self._build(body)
        # Swimmer-v5's reset noise, drawn in the same order from the same RNG.
        m, d, s = self.model, self.data, self.reset_noise_scale
        qpos = m.qpos0 + self.np_random.uniform(low=-s, high=s, size=m.nq)
        qvel = self.np_random.uniform(low=-s, high=s, size=m.nv)
        d.qpos[:] = qpos
        d.qvel[:] = qvel
        mujoco.mj_forward(m, d)
        return self._observation(), self._reset_info()

    def step(self, action):
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (self.num_joints,):
            raise ValueError(f"action must have shape ({self.num_joints},) for this body, got {a.shape}")
        reward, unstable = self.advance(a)
        xy_after, (x_velocity, y_velocity), forward_reward, ctrl_cost = self._last_step
        info = {
            "x_position": xy_after[0],
            "y_position": xy_after[1],
            "distance_from_origin": np.linalg.norm(np.array(xy_after), ord=2),
            "x_velocity": x_velocity,
            "y_velocity": y_velocity,
            "reward_forward": forward_reward,
            "reward_ctrl": -ctrl_cost,
            "num_joints": self.num_joints,
            "body": self.body_label,
            "topology_hash": self.topology_hash,
            "physics_unstable": unstable,
        }
        return self._observation(), reward, unstable, False, info

    def advance(self, a: np.ndarray) -> tuple[float, bool]:
        """``step``'s physics and reward alone: (reward, physics diverged). ``a``: ``num_joints`` float64
        entries (``step`` checks the shape); NaN or inf raises ``ValueError``. For loops that read the state
        themselves (``write_observation``) instead of Gymnasium's dicts."""
        if not np.isfinite(a).all():
            raise ValueError(f"action contains NaN or inf: {a}")
        qpos, badqacc = self._qpos, self._badqacc
        x_before, y_before = qpos[0], qpos[1]  # scalars: this runs for every swimmer at every step
        if self._ctrl_map is None:
            self._ctrl[:] = a
        else:  # a user's MJCF: its actuators' order and ctrl ranges
            self._ctrl[:] = a[self._ctrl_map[0]] * self._ctrl_map[1]
        unstable_before = badqacc.number
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        # MuJoCo resets the state itself when it diverges (seen on chains of
        # 50+ joints at Swimmer-v5's timestep): end the episode instead of
        # carrying on from a silently reset swimmer.
        unstable = badqacc.number > unstable_before
        x_after, y_after = qpos[0], qpos[1]
        velocity = ((x_after - x_before) / self.dt, (y_after - y_before) / self.dt)
        forward_reward = self.forward_reward_weight * velocity[0]
        ctrl_cost = control_cost(a, self.ctrl_cost_weight)
        self._last_step = ((x_after, y_after), velocity, forward_reward, ctrl_cost)
        return forward_reward - ctrl_cost, unstable  # == swimmer_reward(x, x', dt, a): tested bit for bit

    # -- observations --------------------------------------------------------
    def _observation(self):
        qpos, qvel = self.data.qpos, self.data.qvel
        if self.observation_mode == "flat":
            return np.concatenate([qpos[2:], qvel])
        return {
            "joint_pos": qpos[3:].copy(),
            "joint_vel": qvel[3:].copy(),
            "global": np.array([qpos[2], qvel[2], qvel[0], qvel[1]]),
            "parents": self.parents.copy(),
        }

    def write_observation(self, joint_pos: np.ndarray, joint_vel: np.ndarray, global_feats: np.ndarray) -> None:
        """The graph observation written into one row of padded arrays (``policy.chains.pad_observations``'s
        layout, any float dtype): the first ``num_joints`` entries of ``joint_pos`` and ``joint_vel`` (the rest
        zeroed) and the 4 global features. The same values as ``_observation()`` padded, without its dict."""
        write_graph_observation(self._qpos, self._qvel, self.num_joints, joint_pos, joint_vel, global_feats)

    def _reset_info(self) -> dict:
        return {
            "x_position": self.data.qpos[0],
            "y_position": self.data.qpos[1],
            "distance_from_origin": np.linalg.norm(self.data.qpos[0:2], ord=2),
            "num_joints": self.num_joints,
            "body": self.body_label,
            "topology_hash": self.topology_hash,
        }
