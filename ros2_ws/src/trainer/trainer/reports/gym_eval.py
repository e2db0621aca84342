"""A policy on Gymnasium's own MuJoCo env, its inputs built as the policy node builds them.

    python -m trainer.reports.gym_eval --policy P.safetensors --env Ant-v5 --episodes 5 --seed 10000

``gymnasium.make(ENV)`` is stepped with its own physics, reward and termination. At each step its MjData
is read as the sim node publishes a robot (``env.mjcf_robot.MjcfRobot``: the actuated hinges in the tree's
order, the root's 3-D pose and body-frame twist), turned into the records the node receives
(``JointStateRecord``, ``OdometryRecord.of``), and handed to the policy node's own
``protocol.controller.Controller`` after the ``robot_description`` the sim node would publish for this
model (``env.urdf.robot_urdf``): the joint map by name, the global features, and, for a policy of
``joint_features`` 11, the joint descriptions read off that URDF. The answer's efforts (deterministic:
the mean) become the env's action by the sim's rule (``MjcfRobot.ctrl``: each actuator its joint's
effort scaled to its ctrl range).

Per episode: the return, the length and the root's forward distance in x; then the median over
episodes. A policy whose global features do not fit the body (a swimmer's 4 on a body with a free root)
is refused in one line.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from morph_core.msgs.joint_state import LEGGED_GLOBAL_FEATURES
from morph_core.msgs.records import JointStateRecord, OdometryRecord
from morph_core.policy.config import NUM_GLOBAL_FEATURES
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import TreeError
from morph_core.policy.weights import CheckpointError, load_checkpoint
from morph_core.protocol.controller import Controller, policy_error
from morph_core.util.config_cli import CommandLineParser, add_dataclass_options, overrides_from_args, replace_nested

CONTROL_PERIOD_NS = 50_000_000
"""stamps advance by this much per step (Ant-v5's 0.05 s); only their order matters to the controller"""


@dataclass
class GymEvalConfig:
    policy: str = ""
    """policy checkpoint (.safetensors, its .json beside it)"""
    env: str = "Ant-v5"
    """a Gymnasium MuJoCo env id"""
    episodes: int = 5
    """episodes to run"""
    seed: int = 10000
    """the first episode's reset seed; episode i resets with seed + i"""
    max_steps: int = 1000
    """steps per episode at most (the env's own time limit ends it too)"""


@dataclass(frozen=True)
class Episode:
    ret: float
    length: int
    forward: float
    """the root's x at the end minus at the start, metres"""


class GymEvalError(ValueError):
    """A policy or env this tool cannot run; ``str(err)`` is one line."""


def body_global_features(model) -> int:
    """The global features a controller builds for a body: a walker's 12 when its root body hangs from a free
    joint (a 3-D pose), a swimmer's 4 otherwise (planar)."""
    # MuJoCo and Gymnasium (the sim extra) load when an env runs, not for --help
    import mujoco

    free = any(model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE for j in range(model.njnt))
    return LEGGED_GLOBAL_FEATURES if free else NUM_GLOBAL_FEATURES


class GymRun:
    """One Gymnasium env and one policy node's controller over it (module docstring)."""

    def __init__(self, weights, env_id: str):
        # MuJoCo and Gymnasium (the sim extra) load when an env runs, not for --help
        import gymnasium

        from morph_core.env.mjcf_robot import MjcfRobot
        from morph_core.env.urdf import robot_urdf

        error = policy_error(weights.config)
        if error is not None:
            raise GymEvalError(f"the policy {error}")
        try:
            self.env = gymnasium.make(env_id)
        except Exception as err:  # an unknown id, a missing dependency: one line all the same
            raise GymEvalError(f"--env {env_id}: {type(err).__name__}: {err}") from None
        model = getattr(self.env.unwrapped, "model", None)
        if model is None:
            raise GymEvalError(f"--env {env_id} is not a MuJoCo env (no model to describe)")
        width, body = weights.config.global_features, body_global_features(model)
        if width != body:
            kind = "a walker's (a free root)" if body == 12 else "a swimmer's (a planar root)"
            raise GymEvalError(
                f"the policy reads {width} global features; {env_id}'s body is {kind}: its policy reads {body}"
            )
        try:
            self.robot = MjcfRobot(model)  # the sim node's reading of a model; its data: the env's, below
        except TreeError as err:
            raise GymEvalError(f"--env {env_id}: {err}") from None
        self.robot.data = self.env.unwrapped.data
        self.urdf = robot_urdf(model)
        self.controller = Controller(NumpyPolicy(weights), deterministic=True)
        offer = self.controller.description(self.urdf)
        if offer.outcome != "adopted":
            raise GymEvalError(f"{env_id}'s robot_description was refused: {offer.reason}")
        self.stamp_ns = 0
        self.answers = []
        """the last episode's answers (``Controller.answer``), for a caller that checks them"""

    def records(self):
        """The odometry and joint state of the env's state now, as the sim node publishes them."""
        root = self.robot.root_state()
        odom = OdometryRecord.of(0, self.stamp_ns, root.position, root.orientation, root.linear, root.angular)
        pos, vel = self.robot.joint_positions.copy(), self.robot.joint_velocities.copy()
        state = JointStateRecord(0, self.stamp_ns, self.robot.tree.names, pos, vel, np.empty(0))
        return odom, state

    def act(self) -> np.ndarray:
        """The env's action for its state now (stamped one period after the last): the controller's answer,
        applied by the sim's rule."""
        self.stamp_ns += CONTROL_PERIOD_NS
        odom, state = self.records()
        self.controller.odometry(odom)
        (ready,) = self.controller.state(state, 0.0)
        answer = self.controller.answer(ready)
        self.answers.append(answer)
        return self.robot.ctrl(answer.efforts)  # in the state's order, which is the tree's (``records``)

    def episode(self, seed: int, max_steps: int) -> Episode:
        self.env.reset(seed=seed)
        self.answers = []
        self.controller.episode_start(self.stamp_ns + CONTROL_PERIOD_NS)  # its first state's stamp
        x0 = self.robot.root_state().position[0]
        total, steps = 0.0, 0
        while steps < max_steps:
            _, reward, terminated, truncated, _ = self.env.step(self.act())
            total += float(reward)
            steps += 1
            if terminated or truncated:
                break
        return Episode(total, steps, self.robot.root_state().position[0] - x0)


def run(cfg: GymEvalConfig, out=sys.stdout) -> list[Episode]:
    if not cfg.policy:
        raise GymEvalError("give --policy PATH (a .safetensors checkpoint)")
    if cfg.episodes < 1 or cfg.max_steps < 1:
        raise GymEvalError("--episodes and --max-steps must be >= 1")
    try:
        weights = load_checkpoint(cfg.policy)
    except CheckpointError as err:
        raise GymEvalError(str(err)) from None
    gym = GymRun(weights, cfg.env)
    described = ", joint descriptions from its URDF" if weights.config.joint_features else ""
    print(f"{cfg.env}: {cfg.policy} through the policy node's controller ({gym.robot.num_joints} joints{described})",
          file=out, flush=True)  # fmt: skip
    episodes = []
    for i in range(cfg.episodes):
        e = gym.episode(cfg.seed + i, cfg.max_steps)
        episodes.append(e)
        print(f"episode {i} (seed {cfg.seed + i}): return {e.ret:.1f}, length {e.length}, forward {e.forward:+.2f} m",
              file=out, flush=True)  # fmt: skip
    rets, lengths, forwards = zip(*((e.ret, e.length, e.forward) for e in episodes), strict=True)
    print(f"median over {len(episodes)}: return {np.median(rets):.1f}, length {np.median(lengths):.0f}, "
          f"forward {np.median(forwards):+.2f} m", file=out, flush=True)  # fmt: skip
    gym.env.close()
    return episodes


def main(argv: list[str] | None = None) -> int:
    parser = CommandLineParser(prog="python -m trainer.reports.gym_eval", description=__doc__)
    add_dataclass_options(parser, GymEvalConfig)
    args = parser.parse_args(argv)
    cfg = replace_nested(GymEvalConfig(), overrides_from_args(args, GymEvalConfig))
    try:
        run(cfg)
    except GymEvalError as err:
        print(f"gym_eval: error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
