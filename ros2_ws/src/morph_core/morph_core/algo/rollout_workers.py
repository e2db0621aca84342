"""Rollout workers: who steps which swimmers of a run, and one class that does it wherever it runs.

A rollout worker owns swimmers lo..hi-1 of a run and an action-noise
generator. Once per iteration it steps them under a NumPy snapshot of the
policy into its columns of the rollout and gives back their finished
episodes; it gives and restores its state (swimmers, generator) for
checkpoints. ``RolloutWorker`` is that one mechanism, and it runs

- in the learner's process (``LocalPool``: every swimmer, with the run's own
  generator: the one-process loop),
- in the helper processes of ``algo.data_parallel`` (each helper's share,
  its columns in shared memory),
- in a Ray actor (``trainer.sim.ray_rollouts``), which sends its columns back.

The train loop sees a ``RolloutPool``: start a collection under the current
parameters, finish it (the whole rollout filled, the episodes), the workers'
states for a checkpoint and back. The core defines the in-process pool; a
pool on Ray lives in the trainer package, as the core never imports Ray.

Reproducibility: worker ``rank`` of a run that shares its swimmers out
draws its noise from ``worker_seed(seed, rank)`` (what ``--processes``'
helpers have always used); the run's own generator draws the noise of the
swimmers the learner's process steps itself, if any. Swimmer i is first
reset with ``seed + i`` wherever it runs. So a run's random streams depend
on how its swimmers are shared out (the config's ``processes`` and
``rollout_workers``), and a run resumes bit for bit with the split it was
started with.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np
import torch

from morph_core.algo.param_buffer import FlatParameters
from morph_core.algo.rollout import Rollout, collect
from morph_core.env.bodies import parse_bodies
from morph_core.env.vec_env import Episode, SwimmerVecEnv
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy


class RolloutWorkerError(RuntimeError):
    """A rollout worker died and could not be brought back; the message says which and why."""


def env_bounds(num_envs: int, workers: int) -> list[tuple[int, int]]:
    """(lo, hi) of the swimmers each of ``workers`` steps: as even a split as the count allows."""
    edges = np.linspace(0, num_envs, workers + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def worker_seed(seed: int, rank: int) -> int:
    """The action-noise seed of worker ``rank`` of a run seeded ``seed``."""
    return int(np.random.SeedSequence([seed, rank]).generate_state(1)[0])


@dataclasses.dataclass(frozen=True)
class RolloutSpec:
    """A run's rollout: what every worker of it builds its swimmers and policy from."""

    bodies: str
    """the swimmers' bodies, an ``env.bodies`` spec"""
    num_envs: int
    num_steps: int
    seed: int
    """swimmer i is first reset with seed + i"""
    env_threads: int
    policy: dict
    """the policy's ``PolicyConfig`` as a dict"""

    @property
    def max_joints(self) -> int:
        """The largest body's joint count: the rollout's width."""
        return parse_bodies(self.bodies).max_joints

    @property
    def global_features(self) -> int:
        """The width of the rollout's global observations (12 with centipedes, else the swimmer's 4)."""
        return parse_bodies(self.bodies).global_features

    @property
    def joint_features(self) -> int:
        """The width of the joints' descriptions the policy reads (0: none; then the rollout has none)."""
        return int(self.policy.get("joint_features", 0))

    def worker(self, rank: int, workers: int) -> WorkerSpec:
        """Worker ``rank`` of ``workers`` sharing the swimmers out (``env_bounds``)."""
        lo, hi = env_bounds(self.num_envs, workers)[rank]
        return WorkerSpec(self, rank, lo, hi, worker_seed(self.seed, rank))


@dataclasses.dataclass(frozen=True)
class WorkerSpec:
    """One worker: its swimmers lo..hi-1 of the run's rollout and its noise seed."""

    rollout: RolloutSpec
    rank: int
    lo: int
    hi: int
    noise_seed: int


@dataclasses.dataclass
class WorkerState:
    """What a checkpoint keeps of a worker: its swimmers (``SwimmerVecEnv.get_state``) and its generator's
    state (None on a restore: the generator is left as it is, e.g. the run's own, restored with the run)."""

    env_meta: dict
    env_arrays: dict[str, np.ndarray]
    rng: torch.Tensor | None


class RolloutWorker:
    """Steps swimmers lo..hi-1 of a run into its columns of a rollout.

    ``policy``: the torch policy whose parameters it acts with (the learner's own, or a helper's that takes
    the learner's parameters); without one it builds its own from the spec, whose parameters ``collect``
    takes from the flat vector it is given. ``rollout``: where its columns go (by default its own
    [T, hi-lo] rollout). ``generator``: its noise (by default seeded with ``spec.noise_seed``).
    """

    def __init__(
        self,
        spec: WorkerSpec,
        policy: GraphActorCritic | None = None,
        rollout: Rollout | None = None,
        generator: torch.Generator | None = None,
    ):
        run = spec.rollout
        self.spec = spec
        self.envs = SwimmerVecEnv(spec.hi - spec.lo, run.bodies, seed=run.seed + spec.lo, num_threads=run.env_threads,
                                  joint_descriptions=run.joint_features > 0)  # fmt: skip
        self._params = None
        if policy is None:
            policy = GraphActorCritic(PolicyConfig.from_dict(run.policy))
            self._params = FlatParameters(policy)  # the parameters as one vector, as the learner sends them
        self.policy = policy
        if rollout is None:
            rollout = Rollout(run.num_steps, spec.hi - spec.lo, run.max_joints, global_features=run.global_features,
                              joint_features=run.joint_features)  # fmt: skip
        self.rollout = rollout
        self.generator = torch.Generator().manual_seed(spec.noise_seed) if generator is None else generator
        self.obs = self.envs.observations()

    def collect(self, theta: np.ndarray | torch.Tensor | None = None) -> list[Episode]:
        """Fill this worker's columns under the policy (with the flat parameters ``theta``, if given); the
        episodes that finished."""
        if theta is not None:
            if self._params is None:
                raise ValueError("this worker acts with a policy it was given: set its parameters there")
            self._params.theta.data.copy_(torch.as_tensor(np.asarray(theta)))
        self.obs, episodes = collect(self.envs, NumpyPolicy(self.policy), self.rollout, self.obs, self.generator)
        return episodes

    def collect_columns(self, theta: np.ndarray) -> tuple[dict[str, np.ndarray], list[Episode]]:
        """``collect``, and this worker's columns by array name: what a worker in another process sends."""
        episodes = self.collect(theta)
        return {name: getattr(self.rollout, name) for name in self.rollout.names()}, episodes

    def get_state(self) -> WorkerState:
        return WorkerState(*self.envs.get_state(), self.generator.get_state())

    def set_state(self, state: WorkerState) -> None:
        self.envs.set_state(state.env_meta, state.env_arrays)
        if state.rng is not None:
            self.generator.set_state(state.rng)
        self.obs = self.envs.observations()

    def close(self) -> None:
        self.envs.close()


class RolloutPool(Protocol):
    """What the train loop asks of the workers that fill its rollout, once per iteration."""

    rollout: Rollout
    """the whole [T, E] rollout the learner reads once ``finish`` returns"""
    bounds: list[tuple[int, int]]
    """each worker's swimmers (lo, hi), in order"""
    rng_names: list[str | None]
    """each worker's generator's name in a checkpoint (``rng.<name>``); None: the run's own generator"""
    collecting: bool
    """``start`` was called and ``finish`` not yet"""

    def start(self, theta: torch.Tensor) -> None:
        """Start collecting under the policy with the flat parameters ``theta`` (which may not change
        before ``finish``)."""

    def finish(self) -> list[Episode]:
        """Wait for the collection: the rollout filled; the episodes that finished, in worker order."""

    def get_states(self) -> list[WorkerState]:
        """Each worker's state, in order, for a checkpoint (between ``finish`` and the next ``start``)."""

    def set_states(self, states: list[WorkerState]) -> None:
        """Restore each worker (a resumed run)."""

    def close(self) -> None: ...


class LocalPool:
    """Every swimmer stepped in the learner's process by one worker, with the learner's policy and the
    run's generator: the one-process loop. It collects in ``finish``, as the loop asks for the rollout."""

    def __init__(self, worker: RolloutWorker):
        self.worker = worker
        self.rollout = worker.rollout
        self.bounds = [(worker.spec.lo, worker.spec.hi)]
        self.rng_names: list[str | None] = [None]
        self.collecting = False

    def start(self, theta: torch.Tensor) -> None:
        self.collecting = True  # the worker shares the learner's policy: nothing to send

    def finish(self) -> list[Episode]:
        self.collecting = False
        return self.worker.collect()

    def get_states(self) -> list[WorkerState]:
        return [self.worker.get_state()]

    def set_states(self, states: list[WorkerState]) -> None:
        (state,) = states
        self.worker.set_state(state)

    def close(self) -> None:
        self.worker.close()
