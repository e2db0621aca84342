"""Several bodies stepped together, each redrawing its body (a chain length, a tree of ``env.bodies``'
families, or a centipede) at every reset.

Observations come out padded to the largest body the families allow, with each
body's parents beside them, ready for ``ChainBatch.from_padded``: each swimmer writes its state into its row after
its step (``MorphSwimmerEnv.advance`` and ``write_observation``, the same
numbers as Gymnasium's ``step`` without its per-step dicts). Episodes end at the time limit (truncation, with
the final observation kept for bootstrapping) or when the physics diverges
(termination), or for a centipede when it falls (Ant-v5's health rule: termination); finished bodies
are reset at once.

A spec of swimmers alone steps ``MorphSwimmerEnv``s exactly as before centipedes existed (global
features 4 wide). A spec with centipedes steps a ``BodyEnv`` per slot, which draws the family and the
body from its own generator at every reset and runs a ``MorphSwimmerEnv`` or a ``MorphCentipedeEnv``;
the global features are then 12 wide, a swimmer's 4 zero-padded (``BodyMix.global_features``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import NamedTuple, TypeVar

import mujoco
import numpy as np
from gymnasium.utils import seeding

from morph_core.env.bodies import BodyMix, Centipede, is_walker, parse_bodies, swimmer_tree
from morph_core.env.centipede import MorphCentipedeEnv
from morph_core.env.legged_model import LeggedBody
from morph_core.env.mjcf_body import MjcfBody
from morph_core.env.reward import applied_action
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.policy.joint_description import NUM_DESCRIPTION_FEATURES, mujoco_descriptions

MAX_EPISODE_STEPS = 1000
R = TypeVar("R")


class EnvThreads:
    """Runs a per-swimmer function over swimmer indices on up to ``num_threads`` threads.

    MuJoCo releases the GIL inside mj_step, so swimmers step in parallel; the
    caller's thread takes one share. Results come back in the order of the
    indices asked for, whatever the thread count.
    """

    def __init__(self, num_threads: int = 1):
        if num_threads < 1:
            raise ValueError(f"num_threads must be >= 1, got {num_threads}")
        self.num_threads = num_threads
        self._pool = ThreadPoolExecutor(num_threads - 1) if num_threads > 1 else None

    def map(self, fn: Callable[[int], R], indices: Sequence[int]) -> list[R]:
        indices = list(indices)
        if self._pool is None or len(indices) < 2:
            return [fn(i) for i in indices]
        shares = min(self.num_threads, len(indices))
        positions = [range(k, len(indices), shares) for k in range(shares)]
        futures = [self._pool.submit(lambda ps: [fn(indices[p]) for p in ps], ps) for ps in positions[1:]]
        results: list = [None] * len(indices)
        for p in positions[0]:
            results[p] = fn(indices[p])
        for ps, future in zip(positions[1:], futures, strict=True):
            for p, r in zip(ps, future.result(), strict=True):
                results[p] = r
        return results

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None


class BodyEnv:
    """One slot of a vectorised env whose spec holds centipedes: at every reset it draws the family and the
    body from ``bodies`` with its own generator, then resets a ``MorphSwimmerEnv`` or a ``MorphCentipedeEnv``
    (one of each, kept, each compiled model cached) on that body, handing it the same generator, so the reset
    noise follows the draw as in the family's own env. Global features are ``bodies.global_features`` wide."""

    def __init__(self, bodies: BodyMix):
        self.bodies = bodies
        self.global_features = bodies.global_features
        self.np_random = seeding.np_random(None)[0]
        self._swimmer: MorphSwimmerEnv | None = None
        self._centipede: MorphCentipedeEnv | None = None
        self._use(bodies.first())
        self._reset_body(bodies.first())

    def _use(self, body) -> MorphSwimmerEnv | MorphCentipedeEnv:
        if is_walker(body):  # Ant-v5's task
            if self._centipede is None:
                self._centipede = MorphCentipedeEnv(leg_pairs=body.leg_pairs if isinstance(body, Centipede) else 2)
            self.env = self._centipede
        else:
            if self._swimmer is None:
                self._swimmer = MorphSwimmerEnv(num_joints=body.num_joints)
            self.env = self._swimmer
        self.env.np_random = self.np_random  # one generator across families: the draw, then the noise
        return self.env

    def _reset_body(self, body) -> None:
        env = self._use(body)
        if isinstance(body, LeggedBody | MjcfBody):
            env.reset(options={"body": body})
        else:
            env.reset(options={"leg_pairs": body.leg_pairs} if isinstance(body, Centipede) else {"tree": body})

    def reset(self, *, seed: int | None = None) -> None:
        if seed is not None:
            self.np_random = seeding.np_random(seed)[0]  # Gymnasium's seeding, as env.reset(seed=...) does
        self._reset_body(self.bodies.draw(self.np_random))

    @property
    def is_centipede(self) -> bool:
        return self.env is self._centipede

    @property
    def body(self) -> Centipede | object:
        if self.is_centipede:
            return self.env.walker if self.env.walker is not None else Centipede(self.env.leg_pairs)
        return self.env.tree

    def __getattr__(self, name):  # num_joints, parents, tree, body_label, model, data, dt
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)

    def advance(self, a: np.ndarray) -> tuple[float, bool]:
        return self.env.advance(a)

    def write_observation(self, joint_pos: np.ndarray, joint_vel: np.ndarray, global_feats: np.ndarray) -> None:
        self.env.write_observation(joint_pos, joint_vel, global_feats)
        if not self.is_centipede:
            global_feats[4:] = 0.0  # a swimmer's 4 features, padded (the row may have held a centipede's 12)

    def _observation(self) -> dict:
        obs = self.env._observation()
        obs["global"] = np.pad(obs["global"], (0, self.global_features - len(obs["global"])))
        return obs

    # -- state: the body, the generator, and what MuJoCo's integration state leaves out ---------
    def state_meta(self) -> dict:
        mjcf = self.env.walker if self.is_centipede else self.env.mjcf
        if isinstance(mjcf, MjcfBody):
            return {"mjcf": mjcf.path, "rng": self.np_random.bit_generator.state}
        if self.is_centipede and isinstance(self.env.walker, LeggedBody):
            w = self.env.walker
            return {"legged": [w.legs, w.joints_per_leg, w.torso, w.seed], "rng": self.np_random.bit_generator.state}
        if self.is_centipede:
            return {"leg_pairs": int(self.env.leg_pairs), "rng": self.np_random.bit_generator.state}
        body = {"num_joints": self.env.num_joints}
        return body | ({} if self.env.tree.is_chain else {"parents": self.env.parents.tolist()})

    def extra_arrays(self) -> dict[str, np.ndarray]:
        # A centipede's reward reads the root's xpos as the last step left it (a derived quantity, not
        # in MuJoCo's integration state): saved, so that a restored run pays the same first reward.
        return {"root_xpos": self.env.data.xpos[self.env._root].copy()} if self.is_centipede else {}

    def restore_body(self, meta: dict) -> None:
        if "legged" in meta or "mjcf" in meta:
            body = LeggedBody(*meta["legged"]) if "legged" in meta else MjcfBody(meta["mjcf"])
            self._use(body)._build(body)
        elif "leg_pairs" in meta:
            env = self._use(Centipede(int(meta["leg_pairs"])))
            env._build(int(meta["leg_pairs"]))
        else:
            env = self._use(swimmer_tree(meta.get("parents", list(range(-1, int(meta["num_joints"]) - 1)))))
            env._build(int(meta["num_joints"]) if "parents" not in meta else swimmer_tree(meta["parents"]))
        self.np_random.bit_generator.state = meta["rng"]

    def restore_extra(self, arrays: dict[str, np.ndarray], prefix: str) -> None:
        if self.is_centipede:
            self.env.data.xpos[self.env._root] = arrays[prefix + "root_xpos"]


@dataclass
class PaddedObs:
    """[E, J] joint states (zero padded), [E, G] globals (G = ``BodyMix.global_features``: 4, or 12 with
    centipedes), [E] joint counts, [E, J] parents (``index_plan``'s
    convention: -1 for the torso and at padding)."""

    joint_pos: np.ndarray
    joint_vel: np.ndarray
    global_feats: np.ndarray
    num_joints: np.ndarray
    parents: np.ndarray
    joint_desc: np.ndarray | None = None
    """[E, J, D] each joint's description (``policy.joint_description``, zero at padding), when the vector env
    was asked for them (``joint_descriptions``); else None"""

    def arrays(self) -> tuple[np.ndarray, ...]:
        """(joint_pos, joint_vel, global_feats, num_joints, parents): the policy's arguments, in order."""
        return self.joint_pos, self.joint_vel, self.global_feats, self.num_joints, self.parents


class Episode(NamedTuple):
    """A finished episode: its body's joint count (the action dimension d) and label (``env.bodies.body_label``:
    ``chain-N`` or the tree's), return and length."""

    num_joints: int
    episode_return: float
    length: int
    body: str


@dataclass
class StepResult:
    obs: PaddedObs
    reward: np.ndarray  # [E]
    terminated: np.ndarray  # [E] bool
    truncated: np.ndarray  # [E] bool
    final_obs: dict[int, dict] = field(default_factory=dict)  # env index -> last graph obs of a finished episode
    episodes: list[Episode] = field(default_factory=list)


class SwimmerVecEnv:
    """``num_envs`` bodies drawn from ``bodies``: a (lo, hi) range of chain lengths, or an ``env.bodies``
    spec or ``BodyMix`` (chains, trees, centipedes); body i is reset first with ``seed + i``.
    ``global_features``: the width of the global observation (4 for swimmers, 12 with centipedes)."""

    def __init__(
        self,
        num_envs: int,
        bodies: tuple[int, int] | str | BodyMix,
        seed: int,
        max_episode_steps: int = MAX_EPISODE_STEPS,
        num_threads: int = 1,
        joint_descriptions: bool = False,
    ):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if isinstance(bodies, tuple):
            bodies = f"{bodies[0]}-{bodies[1]}"
        self.bodies = parse_bodies(bodies) if isinstance(bodies, str) else bodies
        if self.bodies.swimmers_only:  # the swimmers' own envs, stepped as before centipedes existed
            self.envs = [MorphSwimmerEnv(bodies=self.bodies) for _ in range(num_envs)]
        else:
            self.envs = [BodyEnv(self.bodies) for _ in range(num_envs)]
        self.global_features = self.bodies.global_features
        self.max_joints = self.bodies.max_joints
        self.max_episode_steps = max_episode_steps
        self.num_envs = num_envs
        J, G = self.max_joints, self.global_features
        self._padded = PaddedObs(
            np.zeros((num_envs, J), np.float32), np.zeros((num_envs, J), np.float32),
            np.zeros((num_envs, G), np.float32), np.zeros(num_envs, np.int64), np.full((num_envs, J), -1, np.int64),
        )  # fmt: skip
        if joint_descriptions:  # written per body at each reset (``_write_body``)
            self._padded.joint_desc = np.zeros((num_envs, J, NUM_DESCRIPTION_FEATURES), np.float32)
        for i, env in enumerate(self.envs):
            env.reset(seed=seed + i)
            self._write_body(i)
            self._write(i)
        self.episode_steps = np.zeros(num_envs, dtype=np.int64)
        self.episode_returns = np.zeros(num_envs, dtype=np.float64)
        self._threads = EnvThreads(min(num_threads, num_envs))

    def observations(self) -> PaddedObs:
        desc = self._padded.joint_desc
        return PaddedObs(*(x.copy() for x in self._padded.arrays()), None if desc is None else desc.copy())

    def _write(self, i: int) -> None:
        """Swimmer i's observation into row i."""
        env, p = self.envs[i], self._padded
        env.write_observation(p.joint_pos[i], p.joint_vel[i], p.global_feats[i])

    def _write_body(self, i: int) -> None:
        """Swimmer i's body (joint count, parents) into row i: after each of its resets."""
        env, p = self.envs[i], self._padded
        p.num_joints[i] = env.num_joints
        p.parents[i] = -1
        p.parents[i, : env.num_joints] = env.parents
        if p.joint_desc is not None:
            p.joint_desc[i] = 0.0
            p.joint_desc[i, : env.num_joints] = model_descriptions(env.model)

    def live_observations(self) -> PaddedObs:
        """The rows the bodies write their observations into (views, not copies): what ``observations()``
        would copy, valid until the next ``step`` or reset. For a loop that copies them on itself (a rollout
        stores every step's observation anyway)."""
        return self._padded

    def step(self, actions: np.ndarray, copy_obs: bool = True) -> StepResult:
        """``actions``: [E, J] padded; each swimmer takes its first N entries, clipped to the ctrl range.
        ``copy_obs`` False: the result's ``obs`` is ``live_observations()`` rather than a copy."""
        applied = applied_action(actions).astype(np.float64)  # all swimmers' at once: one call, not E
        if self._threads.num_threads == 1:  # the default: no pool to hand the swimmers to
            outcomes = [self._advance(i, applied[i]) for i in range(self.num_envs)]
        else:
            outcomes = self._threads.map(lambda i: self._advance(i, applied[i]), range(self.num_envs))
        reward = np.array([r for r, _ in outcomes])
        terminated = np.array([term for _, term in outcomes])
        self.episode_steps += 1
        self.episode_returns += reward
        truncated = ~terminated & (self.episode_steps >= self.max_episode_steps)
        result = StepResult(obs=None, reward=reward, terminated=terminated, truncated=truncated)  # type: ignore[arg-type]
        if terminated.any() or truncated.any():
            for i in np.flatnonzero(terminated | truncated).tolist():
                env = self.envs[i]
                result.final_obs[i] = env._observation()
                if self._padded.joint_desc is not None:
                    result.final_obs[i]["joint_desc"] = self._padded.joint_desc[i, : env.num_joints].copy()
                ret, length = float(self.episode_returns[i]), int(self.episode_steps[i])
                result.episodes.append(Episode(env.num_joints, ret, length, env.body_label))
                self.episode_steps[i], self.episode_returns[i] = 0, 0.0
                env.reset()
                self._write_body(i)
                self._write(i)
        result.obs = self.observations() if copy_obs else self._padded
        return result

    def _advance(self, i: int, applied: np.ndarray) -> tuple[float, bool]:
        """Swimmer i's step: (reward, physics diverged), its observation written into row i."""
        env = self.envs[i]
        outcome = env.advance(applied[: env.num_joints])
        self._write(i)
        return outcome

    def close(self) -> None:
        self._threads.close()

    # -- exact save/restore, for checkpoints that resume bit for bit ---------
    def get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """(JSON-able scalars, arrays): bodies (joint counts, and a tree's parents; a centipede's leg pairs), RNG
        states, full MuJoCo integration states (and a centipede's root position, ``BodyEnv.extra_arrays``)."""
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        arrays, meta = {}, {"envs": []}
        for i, env in enumerate(self.envs):
            state = np.empty(mujoco.mj_stateSize(env.model, spec))
            mujoco.mj_getState(env.model, env.data, state, spec)
            arrays[f"env{i}.mj_state"] = state
            if isinstance(env, BodyEnv):
                meta["envs"].append(env.state_meta() | {"rng": env.np_random.bit_generator.state})
                arrays |= {f"env{i}.{k}": v for k, v in env.extra_arrays().items()}
                continue
            body = {"num_joints": env.num_joints} | ({} if env.tree.is_chain else {"parents": env.parents.tolist()})
            if env.mjcf is not None:
                body = {"mjcf": env.mjcf.path}
            meta["envs"].append(body | {"rng": env.np_random.bit_generator.state})
        arrays["episode_steps"] = self.episode_steps.copy()
        arrays["episode_returns"] = self.episode_returns.copy()
        return meta, arrays

    def set_state(self, meta: dict, arrays: dict[str, np.ndarray]) -> None:
        if len(meta["envs"]) != self.num_envs:
            raise ValueError(f"checkpoint holds {len(meta['envs'])} envs, this run has {self.num_envs}")
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        for i, (env, m) in enumerate(zip(self.envs, meta["envs"], strict=True)):
            if isinstance(env, BodyEnv):
                env.restore_body(m)
            elif "leg_pairs" in m or "legged" in m:
                raise ValueError("checkpoint holds a centipede; this run's bodies are swimmers")
            elif "mjcf" in m:
                env._build(MjcfBody(m["mjcf"]))
                env.np_random.bit_generator.state = m["rng"]
            else:
                n = int(m["num_joints"])
                env._build(n if "parents" not in m else swimmer_tree(m["parents"]))
                env.np_random.bit_generator.state = m["rng"]
            mujoco.mj_setState(env.model, env.data, np.asarray(arrays[f"env{i}.mj_state"], dtype=np.float64), spec)
            if isinstance(env, BodyEnv):
                env.restore_extra(arrays, f"env{i}.")
            # No mj_forward here: it would overwrite the restored solver warm start and the
            # trajectories would drift apart at solver tolerance.
            self._write_body(i)
            self._write(i)
        self.episode_steps[:] = arrays["episode_steps"]
        self.episode_returns[:] = arrays["episode_returns"]


_DESCRIPTIONS: dict[int, tuple[object, np.ndarray]] = {}


def model_descriptions(model) -> np.ndarray:
    """``joint_description.mujoco_descriptions`` of a compiled body, computed once per model (the envs' models
    are cached and shared; each entry keeps its model alive, so its id is not reused)."""
    hit = _DESCRIPTIONS.get(id(model))
    if hit is None:
        if len(_DESCRIPTIONS) >= 4096:
            _DESCRIPTIONS.clear()
        hit = _DESCRIPTIONS[id(model)] = (model, mujoco_descriptions(model).astype(np.float32))
    return hit[1]


def merge_env_states(parts: list[tuple[dict, dict[str, np.ndarray]]]) -> tuple[dict, dict[str, np.ndarray]]:
    """One ``get_state`` of the swimmers of several vector envs in order (processes' shares of one run)."""
    meta, arrays, offset = {"envs": []}, {}, 0
    for part_meta, part_arrays in parts:
        for i in range(len(part_meta["envs"])):
            arrays |= {f"env{offset + i}.{k}": v for k, v in _env_arrays(part_arrays, i).items()}
        meta["envs"] += part_meta["envs"]
        offset += len(part_meta["envs"])
    for name in ("episode_steps", "episode_returns"):
        arrays[name] = np.concatenate([a[name] for _, a in parts])
    return meta, arrays


def split_env_state(meta: dict, arrays: dict[str, np.ndarray], bounds: list[tuple[int, int]]):
    """The inverse of ``merge_env_states``: the state of swimmers lo..hi-1 for each (lo, hi) of ``bounds``."""
    if len(meta["envs"]) != bounds[-1][1]:
        raise ValueError(f"checkpoint holds {len(meta['envs'])} envs, this run has {bounds[-1][1]}")
    parts = []
    for lo, hi in bounds:
        part = {f"env{i - lo}.{k}": v for i in range(lo, hi) for k, v in _env_arrays(arrays, i).items()}
        part |= {name: arrays[name][lo:hi] for name in ("episode_steps", "episode_returns")}
        parts.append(({"envs": meta["envs"][lo:hi]}, part))
    return parts


def _env_arrays(arrays: dict[str, np.ndarray], i: int) -> dict[str, np.ndarray]:
    """Env i's arrays of a ``get_state``, by their names after ``env{i}.`` (mj_state, and a centipede's more)."""
    prefix = f"env{i}."
    return {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)}
