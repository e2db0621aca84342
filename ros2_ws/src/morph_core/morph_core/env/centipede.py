"""Gymnasium environment ``MorphCentipede-v0``: Ant-v5's locomotion task for centipedes of any size.

``leg_pairs`` is an int (a fixed body) or an inclusive range ``(lo, hi)``
from which the size is drawn at every reset with the env's seeded generator,
as the swimmer's chain length is (``env.centipede_model`` builds the bodies,
``env.reward.ant_reward`` pays them). The same task runs any other body on
legs with a free root (``env.legged_model.LeggedBody``, a user's MJCF:
``reset(options={"body": body})``, or ``body=`` at construction): its model
is the body's, its healthy heights the body's ``healthy_z_range`` (Ant-v5's
rule carried over by standing height), everything else as for a centipede. ``layout="ant"`` runs the same env on
Gymnasium's Ant body instead (``centipede_model.ant_mjcf``): with
``observation_mode="flat"`` it is Ant-v5, step for step (``test_centipede``).

Step: the action (4 per leg pair, in the tree's order) goes to the motors
(``ctrl``; MuJoCo clamps it to [-1, 1], the cost is charged on it as given,
as Ant-v5 does), then ``mj_step`` over ``ANT_FRAME_SKIP`` = 5 steps of 0.01 s
in one call, then ``mj_rnePostConstraint`` for the contact forces (skipped
when neither the contact cost nor a flat observation reads them). The episode
ends (``terminated``) when the body is unhealthy (root z outside
``ANT_HEALTHY_Z_RANGE`` or a state not finite: it fell, flipped or jumped), or
when MuJoCo had to reset a state that blew up (``info["physics_unstable"]``).

Reset: ``qpos0`` (the root 0.75 m up, every joint at 0) plus uniform(-0.1,
0.1) on every qpos entry, velocities 0.1 x standard normal: Ant-v5's noise,
drawn in its order from the same generator, after the size's draw.
"""

from __future__ import annotations

import numbers

import gymnasium
import mujoco
import numpy as np
from gymnasium import spaces

import morph_core.env.registration  # noqa: F401  (using an env registers the ids)
from morph_core.env.centipede_model import (
    ANT_ACTUATOR_ORDER,
    ant_model,
    centipede_model,
    check_leg_pairs,
)
from morph_core.env.mjcf_robot import DIVERGENCE_WARNINGS
from morph_core.env.reward import (
    ANT_CONTACT_COST_WEIGHT,
    ANT_CONTACT_FORCE_RANGE,
    ANT_CTRL_COST_WEIGHT,
    ANT_FORWARD_REWARD_WEIGHT,
    ANT_FRAME_SKIP,
    ANT_HEALTHY_REWARD,
    ANT_HEALTHY_Z_RANGE,
    ANT_RESET_NOISE_SCALE,
    ant_reward,
)
from morph_core.msgs.joint_state import write_global_features
from morph_core.policy.tree import KinematicTree

OBSERVATION_MODES = ("graph", "flat")
LAYOUTS = ("centipede", "ant")
GLOBAL_FEATURES = ("yaw", "yaw_rate", "vx", "vy", "vz", "z", "gravity_x", "gravity_y", "gravity_z", "wx", "wy", "wz")
"""the root segment's state: the swimmer's four first (heading about z, its rate, world-frame velocity in x
and y), then world vz, height, the unit gravity direction in the root's frame (tilt: roll and pitch without
yaw, no angle wraps) and the root's angular velocity in its own frame (what a gyroscope reads)"""
NUM_GLOBAL_FEATURES = len(GLOBAL_FEATURES)


def check_leg_pair_range(leg_pairs) -> tuple[int, int]:
    """``leg_pairs`` (an int, or a (lo, hi) pair) as an inclusive range, or ValueError saying why not."""
    if isinstance(leg_pairs, numbers.Integral) and not isinstance(leg_pairs, bool):
        n = check_leg_pairs(leg_pairs)
        return n, n
    if isinstance(leg_pairs, str | bytes) or not isinstance(leg_pairs, tuple | list):
        raise ValueError(f"leg_pairs must be an integer or a (lo, hi) pair of integers, got {leg_pairs!r:.60}")
    if len(leg_pairs) != 2:
        raise ValueError(f"leg_pairs range must be (lo, hi), got {len(leg_pairs)} entries: {leg_pairs!r:.60}")
    lo, hi = check_leg_pairs(leg_pairs[0]), check_leg_pairs(leg_pairs[1])
    if lo > hi:
        raise ValueError(f"leg_pairs range is empty: lo={lo} > hi={hi}")
    return lo, hi


class MorphCentipedeEnv(gymnasium.Env):
    """A centipede on a floor, paid Ant-v5's reward (forward speed, staying healthy, control and contact costs).

    Graph observations are a dict: ``joint_pos`` and ``joint_vel`` (one entry per actuated hinge, in the tree's
    order: per segment left hip, left ankle, right hip, right ankle), ``global`` (``GLOBAL_FEATURES``, 12) and
    ``parents`` ([4N] int64: each ankle's parent is its hip, each hip's -1, the root segment). Flat
    observations are Ant-v5's: qpos without x and y, qvel, the clipped contact forces of every body but the world.

    ``tree`` is the current body's ``KinematicTree.from_mujoco(model)`` (root link ``torso_0``; the welded
    segments merge into it), ``parents`` its read-only parent array; ``info`` carries ``leg_pairs``, ``body``
    (``centipede-N``, ``ant``) and ``topology_hash``.
    """

    metadata = {"render_modes": [], "render_fps": 20}

    def __init__(
        self,
        leg_pairs: int | tuple[int, int] = 2,
        observation_mode: str = "graph",
        layout: str = "centipede",
        frame_skip: int = ANT_FRAME_SKIP,
        forward_reward_weight: float = ANT_FORWARD_REWARD_WEIGHT,
        ctrl_cost_weight: float = ANT_CTRL_COST_WEIGHT,
        contact_cost_weight: float = ANT_CONTACT_COST_WEIGHT,
        healthy_reward: float = ANT_HEALTHY_REWARD,
        terminate_when_unhealthy: bool = True,
        healthy_z_range: tuple[float, float] = ANT_HEALTHY_Z_RANGE,
        contact_force_range: tuple[float, float] = ANT_CONTACT_FORCE_RANGE,
        reset_noise_scale: float = ANT_RESET_NOISE_SCALE,
        body=None,
    ):
        if observation_mode not in OBSERVATION_MODES:
            raise ValueError(f"observation_mode must be one of {OBSERVATION_MODES}, got {observation_mode!r}")
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
        if isinstance(frame_skip, bool) or not isinstance(frame_skip, numbers.Integral) or frame_skip < 1:
            raise ValueError(f"frame_skip must be an integer >= 1, got {frame_skip!r}")
        self.leg_pair_range = check_leg_pair_range(leg_pairs)
        if layout == "ant" and self.leg_pair_range != (2, 2):
            raise ValueError(f"the ant layout has 2 leg pairs, got leg_pairs={leg_pairs!r}")
        self.observation_mode = observation_mode
        self.layout = layout
        self.frame_skip = int(frame_skip)
        self.forward_reward_weight = forward_reward_weight
        self.ctrl_cost_weight = ctrl_cost_weight
        self.contact_cost_weight = contact_cost_weight
        self.healthy_reward = healthy_reward
        self.terminate_when_unhealthy = terminate_when_unhealthy
        self.healthy_z_range = tuple(healthy_z_range)
        self._centipede_healthy_z_range = self.healthy_z_range  # a walker body brings its own
        self.contact_force_range = tuple(contact_force_range)
        self.reset_noise_scale = reset_noise_scale
        # cfrc_ext costs a pass over the bodies per step: computed only when something reads it
        self._needs_contact_forces = contact_cost_weight != 0 or observation_mode == "flat"
        self.leg_pairs = 0
        self.walker = None
        """the body when it is not a centipede (``walker_body``'s kinds), else None"""
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._build(self.leg_pair_range[0] if body is None else self._check_walker(body))

    # -- body ----------------------------------------------------------------
    def _check_walker(self, body):
        if self.layout == "ant":
            raise ValueError("the ant layout runs Ant's body alone")
        if not all(hasattr(body, a) for a in ("model", "label", "healthy_z_range")):
            raise ValueError(f"a walker body has model(), label and healthy_z_range, got {type(body).__name__}")
        return body

    def _build(self, leg_pairs) -> None:
        """Build (or reset, when it is the current one) the centipede of ``leg_pairs`` or the walker body."""
        walker = None if isinstance(leg_pairs, numbers.Integral) else leg_pairs
        if (walker is None and self.walker is None and leg_pairs == self.leg_pairs) or (
            walker is not None and walker == self.walker
        ):
            mujoco.mj_resetData(self.model, self.data)
            return
        if walker is not None:
            model = walker.model()
            self.leg_pairs, self.walker = 0, walker
            self.healthy_z_range = tuple(walker.healthy_z_range)
        else:
            model = ant_model() if self.layout == "ant" else centipede_model(leg_pairs)
            self.leg_pairs, self.walker = leg_pairs, None
            self.healthy_z_range = self._centipede_healthy_z_range
        self.model, self.data = model, mujoco.MjData(model)
        self.tree = KinematicTree.from_mujoco(model)
        self.parents = self.tree.parents
        self.num_joints = self.tree.num_joints
        if walker is not None:
            self.body_label = walker.label
        else:
            self.body_label = "ant" if self.layout == "ant" else f"centipede-{leg_pairs}"
        self.topology_hash = self.tree.topology_hash
        # The tree's joints are the hinges after the root's free joint, in qpos order: checked, not assumed.
        names = tuple(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(1, model.njnt))
        if names != self.tree.names or model.nq != 7 + self.num_joints:
            raise AssertionError(f"{self.body_label}: qpos order {names} is not the tree's {self.tree.names}")
        joint_of = {name: k for k, name in enumerate(self.tree.names)}
        motors = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, int(j)) for j in model.actuator_trnid[:, 0]]
        order = np.array([joint_of[name] for name in motors], dtype=np.int64)
        # ctrl[i] = action[order[i]]; None when the motors are in the tree's order (every centipede)
        self._ctrl_order = None if np.array_equal(order, np.arange(self.num_joints)) else order
        # a user's MJCF: ctrl = action[order] * its ctrl range's far end (``MjcfBody.ctrl_map``), cost on the action
        self._ctrl_scale = None
        if walker is not None and hasattr(walker, "ctrl_map"):
            self._ctrl_order, self._ctrl_scale = walker.ctrl_map()
        if self.layout == "ant" and walker is None:
            assert tuple(motors) == ANT_ACTUATOR_ORDER
        self._root = 1  # the root segment's body id
        self._qpos, self._qvel, self._ctrl = self.data.qpos, self.data.qvel, self.data.ctrl
        self._xpos_root = self.data.xpos[self._root]  # a view: what MuJoCo left after the step
        self._warnings = [self.data.warning[w] for w in DIVERGENCE_WARNINGS]
        self._no_forces = np.zeros((model.nbody, 6))
        self.dt = model.opt.timestep * self.frame_skip
        self.action_space = spaces.Box(-1.0, 1.0, shape=(self.num_joints,), dtype=np.float32)
        self.observation_space = self._observation_space()

    def _observation_space(self) -> spaces.Space:
        n, m = self.num_joints, self.model
        if self.observation_mode == "flat":
            size = (m.nq - 2) + m.nv + 6 * (m.nbody - 1)
            return spaces.Box(-np.inf, np.inf, shape=(size,), dtype=np.float64)
        return spaces.Dict(
            {
                "joint_pos": spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64),
                "joint_vel": spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64),
                "global": spaces.Box(-np.inf, np.inf, shape=(NUM_GLOBAL_FEATURES,), dtype=np.float64),
                "parents": spaces.Box(-1, n - 1, shape=(n,), dtype=np.int64),
            }
        )

    # -- gymnasium API -------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Reset; ``options={"leg_pairs": n}`` forces this episode's size (nothing is drawn then),
        ``options={"body": body}`` runs a walker body (``LeggedBody``, ...) instead; without options, the
        current walker body stays, or a centipede's size is drawn."""
        super().reset(seed=seed)
        if options and "body" in options:
            n = self._check_walker(options["body"])
        elif not options and self.walker is not None:
            n = self.walker
        elif options and "leg_pairs" in options:
            n = check_leg_pairs(options["leg_pairs"])
            if self.layout == "ant" and n != 2:
                raise ValueError(f"the ant layout has 2 leg pairs, got {n}")
        else:
            lo, hi = self.leg_pair_range
            n = lo if lo == hi else int(self.np_random.integers(lo, hi + 1))
        self._build(n)
        m, d, s = self.model, self.data, self.reset_noise_scale
        # Ant-v5's noise, in its order from the same generator (its set_state: qpos, qvel, then mj_forward)
        qpos = m.qpos0 + self.np_random.uniform(low=-s, high=s, size=m.nq)
        qvel = s * self.np_random.standard_normal(m.nv)
        d.qpos[:] = qpos
        d.qvel[:] = qvel
        mujoco.mj_forward(m, d)
        return self._observation(), self._info_position()

    def step(self, action):
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (self.num_joints,):
            raise ValueError(f"action must have shape ({self.num_joints},) for {self.body_label}, got {a.shape}")
        reward, terminated = self.advance(a)
        x_velocity, y_velocity, terms, unstable = self._last_step
        info = {
            **self._info_position(),
            "x_velocity": x_velocity,
            "y_velocity": y_velocity,
            **terms,
            "physics_unstable": unstable,
        }
        return self._observation(), reward, terminated, False, info

    def advance(self, a: np.ndarray) -> tuple[float, bool]:
        """``step``'s physics and reward alone: (reward, terminated). ``a``: ``num_joints`` float64 entries
        (``step`` checks the shape); NaN or inf raises ``ValueError``. For loops that read the state
        themselves (``write_observation``: the vectorised env, the sim) instead of Gymnasium's dicts."""
        if not np.isfinite(a).all():
            raise ValueError(f"action contains NaN or inf: {a}")
        m, d = self.model, self.data
        x_before, y_before = self._xpos_root[0], self._xpos_root[1]
        if self._ctrl_scale is None:
            self._ctrl[:] = a if self._ctrl_order is None else a[self._ctrl_order]
        else:
            self._ctrl[:] = a[self._ctrl_order] * self._ctrl_scale
        before = [w.number for w in self._warnings]
        mujoco.mj_step(m, d, nstep=self.frame_skip)
        if self._needs_contact_forces:
            mujoco.mj_rnePostConstraint(m, d)
        unstable = any(w.number > b for w, b in zip(self._warnings, before, strict=True))
        x_velocity = (self._xpos_root[0] - x_before) / self.dt
        y_velocity = (self._xpos_root[1] - y_before) / self.dt
        healthy = self.is_healthy
        cfrc = d.cfrc_ext if self._needs_contact_forces else self._no_forces
        charged = self._ctrl if self._ctrl_scale is None else a  # a user's MJCF: the cost on the action
        reward, terms = ant_reward(
            x_velocity, healthy, charged, cfrc, self.forward_reward_weight, self.healthy_reward,
            self.ctrl_cost_weight, self.contact_cost_weight, self.contact_force_range,
        )  # fmt: skip
        self._last_step = (x_velocity, y_velocity, terms, unstable)
        self.unstable = unstable
        return reward, bool((not healthy and self.terminate_when_unhealthy) or unstable)

    @property
    def is_healthy(self) -> bool:
        """Ant-v5's: every qpos and qvel entry finite and the root's z within ``healthy_z_range``."""
        lo, hi = self.healthy_z_range
        finite = np.isfinite(self._qpos).all() and np.isfinite(self._qvel).all()
        return bool(finite and lo <= self._qpos[2] <= hi)

    # -- observations --------------------------------------------------------
    def _observation(self):
        qpos, qvel = self._qpos, self._qvel
        if self.observation_mode == "flat":
            forces = np.clip(self.data.cfrc_ext[1:], *self.contact_force_range)
            return np.concatenate((qpos[2:], qvel, forces.ravel()))
        glob = np.empty(NUM_GLOBAL_FEATURES)
        write_global_features(qpos, qvel, glob)
        return {"joint_pos": qpos[7:].copy(), "joint_vel": qvel[6:].copy(), "global": glob,
                "parents": self.parents.copy()}  # fmt: skip

    def write_observation(self, joint_pos: np.ndarray, joint_vel: np.ndarray, global_feats: np.ndarray) -> None:
        """The graph observation written into one row of padded arrays (the first ``num_joints`` entries, the
        rest zeroed; ``global_feats`` 12 wide), the same values as the dict's, for a vectorised loop."""
        n = self.num_joints
        joint_pos[:n], joint_vel[:n] = self._qpos[7:], self._qvel[6:]
        joint_pos[n:], joint_vel[n:] = 0.0, 0.0
        write_global_features(self._qpos, self._qvel, global_feats)

    def _info_position(self) -> dict:
        qpos = self._qpos
        return {
            "x_position": qpos[0],
            "y_position": qpos[1],
            "distance_from_origin": np.linalg.norm(qpos[0:2], ord=2),
            "leg_pairs": self.leg_pairs,
            "body": self.body_label,
            "topology_hash": self.topology_hash,
        }
