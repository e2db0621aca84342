"""A user's MJCF as a body of the body spec (``mjcf:PATH``): trained, evaluated and filmed like a generated body.

The file is read by ``mjcf_robot.load_robot``, so it is refused for the reasons the sim node's
``model_file`` is (one line, ``RobotModelError``: no such file, not MJCF, does not compile, not a
tree of 1..64 actuated hinges). Its root decides the task:

- a free joint on the root body: a walker, Ant-v5's task (``env.centipede.MorphCentipedeEnv``), healthy
  while the root's height stays within ``legged_model.HEALTHY_FRACTIONS`` of its standing height
  (``legged_model.settled_height``: Gymnasium's ``ant.xml`` gets Ant-v5's own (0.2, 1.0));
- a planar root (slide along x, slide along y, hinge about z, Swimmer-v5's ``rootx, rooty, rootz``):
  the swimmer's task (``env.swimmer_env.MorphSwimmerEnv``).

Anything else is refused, and so is a model whose joints below the root are not exactly its actuated
hinges in the tree's order (the envs read qpos after the root's entries as the joint state; passive
joints are not supported). Actions map to ``ctrl`` as ``MjcfRobot`` maps efforts (``ctrl_map``): each
actuator gets its joint's action times its ctrl range's far end, so +-1 reaches the range's end.

No MuJoCo import at this module's top: a spec parser (the policy node's bring-up) may name the class
without loading MuJoCo; the file is loaded when a body is first asked for its model.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from morph_core.env.legged_model import HEALTHY_FRACTIONS, settled_height

if TYPE_CHECKING:
    import mujoco

TASKS = ("walker", "swimmer")


@dataclass(frozen=True)
class MjcfBody:
    """The robot of the MJCF file at ``path`` (as given: relative paths are the process's)."""

    path: str

    @property
    def label(self) -> str:
        return "mjcf-" + os.path.splitext(os.path.basename(self.path))[0]

    def model(self) -> mujoco.MjModel:
        """The compiled model, loaded and checked once per path (``RobotModelError`` when refused)."""
        return _loaded(self.path)[0]

    @property
    def task(self) -> str:
        """``walker`` (free root: Ant-v5's task) or ``swimmer`` (planar root: Swimmer-v5's)."""
        return _loaded(self.path)[1]

    @property
    def num_joints(self) -> int:
        return int(_loaded(self.path)[2].num_joints)

    @property
    def tree(self):
        return _loaded(self.path)[2]

    @property
    def standing_height(self) -> float:
        """``legged_model.settled_height`` of a walker's model (NaN for a swimmer)."""
        return _standing(self.path) if self.task == "walker" else float("nan")

    @property
    def healthy_z_range(self) -> tuple[float, float]:
        h = self.standing_height
        return HEALTHY_FRACTIONS[0] * h, HEALTHY_FRACTIONS[1] * h

    def ctrl_map(self) -> tuple[np.ndarray, np.ndarray]:
        """(order, scale): ``ctrl = action[order] * scale``, one entry per actuator."""
        return _loaded(self.path)[3]


@lru_cache(maxsize=64)
def _standing(path: str) -> float:
    return settled_height(_loaded(path)[0])


@lru_cache(maxsize=64)
def _loaded(path: str):
    import mujoco  # MuJoCo (and mjcf_robot, which loads it) only to read a file: env.bodies parses specs without

    from morph_core.env.mjcf_robot import RobotModelError, load_robot

    robot = load_robot(path)
    model, tree = robot.model, robot.tree
    root = robot.root_body
    t = mujoco.mjtJoint
    first = [j for j in range(model.njnt) if model.jnt_bodyid[j] == root and j not in _hinge_ids(model, tree)]
    kinds = [int(model.jnt_type[j]) for j in first]
    if kinds == [t.mjJNT_FREE] and model.jnt_qposadr[first[0]] == 0:
        task, skip = "walker", 7
    elif (
        kinds == [t.mjJNT_SLIDE, t.mjJNT_SLIDE, t.mjJNT_HINGE]
        and np.allclose(np.abs(model.jnt_axis[first]), np.eye(3)[[0, 1, 2]])
        and list(model.jnt_qposadr[first]) == [0, 1, 2]
    ):
        task, skip = "swimmer", 3
    else:
        raise RobotModelError(
            f"model file {path!r}: its root has neither a free joint (the legged task) nor a planar root (slide x, "
            "slide y, hinge z: the swimmer task)"
        )
    names = tuple(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(len(first), model.njnt))
    if names != tree.names or model.nq != skip + tree.num_joints:
        raise RobotModelError(
            f"model file {path!r}: its joints below the root must be exactly its actuated hinges, in depth-first "
            "order (passive joints are not supported in training)"
        )
    return model, task, tree, (robot._actuator_joint.copy(), robot._actuator_scale.copy())


def _hinge_ids(model, tree) -> set[int]:
    import mujoco  # as in _loaded

    return {mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in tree.names}
