"""Rollout workers on Ray actors: ``morph-train --rollout-workers N``.

Each actor is a ``RolloutWorker`` of the core (``morph_core.algo.rollout_workers``): it owns a share of the
swimmers (``env_bounds``) and its noise generator (``worker_seed(seed, rank)``), steps them under the
parameters the learner sends each iteration and sends its columns of the rollout back; the learner (the
process that calls ``train``) computes the advantages and updates. The pool is the train loop's
``RolloutPool``: the core never imports Ray, the CLI hands it this pool.

A worker that dies (its process killed, its node lost) is restarted by Ray (``max_restarts``); the pool
restores its swimmers and generator from the states of the last checkpoint, which it keeps, collects the
interrupted rollout again and logs a warning saying what went back. The other workers' swimmers go on, so
from there the run is no longer bit for bit an uninterrupted one; a run resumed from its checkpoint is.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable

import numpy as np
import ray
import torch
from ray.exceptions import ActorUnavailableError, RayActorError

from morph_core.algo.rollout import Rollout
from morph_core.algo.rollout_workers import (
    RolloutPool,
    RolloutSpec,
    RolloutWorker,
    RolloutWorkerError,
    WorkerSpec,
    WorkerState,
)
from morph_core.env.vec_env import Episode

log = logging.getLogger(__name__)

MAX_RESTARTS = 3
"""restarts Ray gives each worker actor over a run before the run stops with ``RolloutWorkerError``"""


RESTART_TIMEOUT = 120.0
"""seconds a restarted worker may take to come back (a new process importing torch and MuJoCo: ~5 s here)"""


class NotRestored(RuntimeError):
    """A restarted worker was asked to collect or save before its state was restored."""


class RolloutActor(RolloutWorker):
    """A ``RolloutWorker`` as a Ray actor: one torch thread, its process id (to be told apart, or killed by a
    test), and no collecting before it has been given its state. Ray restarts a dead actor by building it
    again from its spec, on fresh swimmers; were it to collect on those without a word, a worker killed
    between two calls would go on from the start of the run. So its swimmers must come from the pool first:
    ``initial_state`` once, or ``set_state``."""

    def __init__(self, spec: WorkerSpec):
        torch.set_num_threads(1)  # one core per actor: Ray reserves one CPU for it
        super().__init__(spec)
        self.restored = False

    def initial_state(self) -> WorkerState:
        """A new pool's worker: its state as it starts, which it collects from."""
        self.restored = True
        return self.get_state()

    def set_state(self, state: WorkerState) -> None:
        super().set_state(state)
        self.restored = True

    def collect_columns(self, theta):
        self._check_restored()
        return super().collect_columns(theta)

    def get_state(self) -> WorkerState:
        self._check_restored()
        return super().get_state()

    def _check_restored(self) -> None:
        if not self.restored:
            raise NotRestored(f"rollout worker {self.spec.rank} was restarted and has not been restored")

    def pid(self) -> int:
        return os.getpid()


class RayRolloutPool:
    """``workers`` Ray actors sharing out the swimmers of ``spec``'s rollout (a ``RolloutPool``)."""

    def __init__(self, spec: RolloutSpec, workers: int, max_restarts: int = MAX_RESTARTS, shutdown: bool = False):
        """``shutdown``: ``close`` also shuts Ray down (the pool started it)."""
        self.spec, self.max_restarts, self._shutdown = spec, max_restarts, shutdown
        self.workers = [spec.worker(rank, workers) for rank in range(workers)]
        self.bounds = [(w.lo, w.hi) for w in self.workers]
        self.rng_names: list[str | None] = [f"worker{w.rank}" for w in self.workers]
        self.rollout = Rollout(
            spec.num_steps, spec.num_envs, spec.max_joints, global_features=spec.global_features,
            joint_features=spec.joint_features,
        )  # fmt: skip
        self.collecting = False
        self.restarts = 0
        """workers restarted so far (each logged)"""
        # max_task_retries=0: a call in flight when its worker dies fails here, where the worker's swimmers
        # are restored before it is called again (Ray would re-run it on the fresh actor's swimmers).
        actor = ray.remote(RolloutActor).options(num_cpus=1, max_restarts=max_restarts, max_task_retries=0)
        self.actors = [actor.remote(w) for w in self.workers]
        self._theta = None
        self._calls: list = []
        try:
            self.saved = self._call_all("initial_state")
            """each worker's state as the last checkpoint saved it (at first: as it started), what a worker that
            dies is restored to"""
        except BaseException:
            self.close()
            raise
        self.since_saved = 0
        """rollouts collected since the states in ``saved``"""

    # -- RolloutPool ---------------------------------------------------------------------------------------
    def start(self, theta: torch.Tensor) -> None:
        self._theta = ray.put(theta.detach().numpy().copy())  # one copy in the object store for every worker
        self._calls = [actor.collect_columns.remote(self._theta) for actor in self.actors]
        self.collecting = True

    def finish(self) -> list[Episode]:
        episodes = []
        for rank, call in enumerate(self._calls):
            columns, theirs = self._get(rank, call, "collect_columns", self._theta)
            part = self.rollout.columns(*self.bounds[rank])
            for name, array in columns.items():
                getattr(part, name)[...] = array
            episodes += theirs
        self._calls, self.collecting = [], False
        self.since_saved += 1
        return episodes

    def get_states(self) -> list[WorkerState]:
        # A checkpoint saves these, and a worker that dies comes back to them. Ray hands arrays back read-only.
        states = self._call_all("get_state")
        self.saved = [WorkerState(s.env_meta, {k: np.array(v) for k, v in s.env_arrays.items()}, s.rng) for s in states]
        self.since_saved = 0
        return self.saved

    def set_states(self, states: list[WorkerState]) -> None:
        if len(states) != len(self.actors):
            raise ValueError(f"{len(states)} worker states for {len(self.actors)} rollout workers")
        ray.get([actor.set_state.remote(state) for actor, state in zip(self.actors, states, strict=True)])
        self.saved, self.since_saved = list(states), 0

    def close(self) -> None:
        for actor in self.actors:
            ray.kill(actor, no_restart=True)
        self.actors = []
        if self._shutdown and ray.is_initialized():
            ray.shutdown()

    # -- calls that survive a worker's death ---------------------------------------------------------------
    def pids(self) -> list[int]:
        """The workers' process ids."""
        return self._call_all("pid")

    def _call_all(self, method: str, *args) -> list:
        calls = [getattr(actor, method).remote(*args) for actor in self.actors]
        return [self._get(rank, call, method, *args) for rank, call in enumerate(calls)]

    def _get(self, rank: int, call, method: str, *args):
        """The result of ``call`` (worker ``rank``'s ``method(*args)``); if the worker died (in this call, or
        since the last one: it answers ``NotRestored``), it is restored once Ray has restarted it and asked
        again."""
        while True:
            try:
                return ray.get(call)
            except (RayActorError, NotRestored) as err:  # Ray raises a task's error as an instance of its type
                self._restore(rank, method, err)
                call = getattr(self.actors[rank], method).remote(*args)

    def _restore(self, rank: int, method: str, err: Exception) -> None:
        worker = self.workers[rank]
        swimmers, steps = worker.hi - worker.lo, self.spec.num_steps
        deadline = time.monotonic() + RESTART_TIMEOUT
        while True:
            try:
                ray.get(self.actors[rank].set_state.remote(self.saved[rank]))
                break
            except ActorUnavailableError:  # still restarting: its new process is starting up
                if time.monotonic() > deadline:
                    raise RolloutWorkerError(f"rollout worker {rank} died during {method} and was not back "
                                             f"within {RESTART_TIMEOUT:g} s") from None  # fmt: skip
                time.sleep(0.2)
            except RayActorError:
                raise RolloutWorkerError(
                    f"rollout worker {rank} died during {method} and Ray could not restart it (max_restarts "
                    f"{self.max_restarts}): {str(err).splitlines()[0]}"
                ) from None
        self.restarts += 1
        undone = self.since_saved * steps * swimmers
        log.warning(
            "rollout worker %d (swimmers %d..%d) died during %s; Ray restarted it and its swimmers and noise "
            "generator went back to the last checkpoint's states: lost for them are the %d rollouts of %d steps "
            "since then (%d env-steps, already trained on, now undone)%s; the run goes on, no longer bit for "
            "bit an uninterrupted one",
            rank, worker.lo, worker.hi - 1, method, self.since_saved, steps, undone,
            ", and the rollout in flight, collected again" if method == "collect_columns" else "",
        )  # fmt: skip


def ray_rollout_pool(address: str | None = None, **init) -> Callable[[RolloutSpec, int], RolloutPool]:
    """The pool factory ``train(rollout_pool=...)`` takes: Ray started on first use (local, or joined to the
    cluster at ``address``) unless it already runs, then shut down with the pool."""

    def make(spec: RolloutSpec, workers: int) -> RayRolloutPool:
        started = not ray.is_initialized()
        if started:
            if address is None:  # a local Ray: a CPU per worker, as many as asked even beyond the cores
                init.setdefault("num_cpus", max(workers, os.cpu_count() or 1))
            ray.init(address=address, include_dashboard=False, **init)
        cpus = ray.cluster_resources().get("CPU", 0)
        if cpus < workers:  # each actor takes a CPU: more workers than CPUs would wait for one forever
            if started:
                ray.shutdown()
            raise RolloutWorkerError(f"{workers} rollout workers need {workers} CPUs; the Ray cluster has {cpus:g}")
        return RayRolloutPool(spec, workers, shutdown=started)

    return make
