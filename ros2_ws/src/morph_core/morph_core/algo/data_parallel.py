"""Simulator training on several processes: the swimmers and every minibatch's gradient shared out.

Threads cannot share this work: a rollout steps six small swimmers and a
minibatch step is a few hundred small operations, so handing pieces to a
thread costs about what it saves (a second env thread added 4%, a second
torch thread nothing). Processes each own a share of the swimmers and a part
of every minibatch, and meet once per minibatch step:

- **Collect.** Process r steps swimmers lo..hi-1 under a NumPy snapshot of
  the policy and writes their columns of one rollout in shared memory, with
  its own action-noise generator: a ``rollout_workers.RolloutWorker`` in each
  process, the rollout workers of the ``HelperPool``.
- **Update.** Process 0 computes the advantages over the whole rollout, draws
  each epoch's permutation, normalises each minibatch's advantages over the
  whole minibatch and hands the helpers the epoch's minibatches at once. Each
  process computes the gradient of its part of the minibatch, its loss scaled
  by the part's share, so the parts' gradients add up to the whole
  minibatch's. Process 0 adds them in rank order, clips, steps Adam and
  publishes the new parameters, which every helper takes before its next
  part. Every process gathers its next part's samples while the others still
  compute or step, and process 0's part is the smaller
  (``minibatches.PROCESS0_WEIGHT``), as it alone adds, clips and steps. The update
  equals the one-process update to float rounding (``test_data_parallel``).
- Process 0 alone keeps the optimizer, logs and checkpoints; it asks the
  helpers for their swimmers' and generators' states when it saves. The
  helpers start their next rollout as soon as an update ends, while process
  0 logs and saves.

The two jobs are two objects in each helper (``_Helper``): its rollout
worker, called once per iteration, and its gradient peer (``_GradientPeer``),
called once per minibatch. The data stays in one block of shared memory;
commands are small dataclasses through a pipe per helper, each answered by
the helper's method of that name, and within an epoch two semaphores per helper say
"your part's gradient is ready" and "the new parameters are", polled before
a process blocks on them (a pipe message cost ~30 µs each way). A helper
that dies closes its pipe, and process 0 stops with ``HelperError`` instead
of waiting for it.

A run's random streams depend on the process count: one process draws
every swimmer's noise from the run's generator, several draw each helper's
share's from its own (``rollout_workers.worker_seed``). So ``processes`` is part of a run's config;
a run resumes bit for bit with the count it was started with.
"""

from __future__ import annotations

import dataclasses
import functools
import multiprocessing
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory

import numpy as np
import torch

from morph_core.algo.learner import Learner
from morph_core.algo.minibatches import MinibatchPart, part_gradient, part_inputs, update_terms
from morph_core.algo.rollout import Rollout, rollout_layout
from morph_core.algo.rollout_workers import RolloutSpec, RolloutWorker, WorkerState, env_bounds, worker_seed
from morph_core.algo.update_config import UpdateConfig
from morph_core.env.vec_env import Episode
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig

__all__ = ["HelperError", "HelperPool", "HelperSpec", "Helpers", "env_bounds", "helper_seed"]


def helper_seed(seed: int, rank: int) -> int:
    """The action-noise seed of helper ``rank`` (process 0 uses the run's generator): its worker's seed."""
    return worker_seed(seed, rank)


class HelperError(RuntimeError):
    """A helper process failed or died; the message says which and why."""


SPIN_SECONDS = 0.002
"""how long a process polls a pipe or a semaphore without sleeping before it blocks on it: during an update the other
side answers within a minibatch step (~3 ms), and waking from a blocking read cost ~0.1 ms of every step
(docs/benchmarks.md); between updates the wait is longer, and after 2 ms the process sleeps"""


def poll_spinning(conn: Connection, spin: float = SPIN_SECONDS) -> bool:
    """Whether ``conn`` has something to read within ``spin`` seconds, polled without sleeping."""
    deadline = time.perf_counter() + spin
    while True:
        if conn.poll():
            return True
        if time.perf_counter() >= deadline:
            return False


def take_spinning(semaphore, check: Callable[[], None], spin: float = SPIN_SECONDS) -> None:
    """Take ``semaphore``, polled without sleeping for ``spin`` seconds, then waited for in 1-second slices,
    each followed by ``check()``, which raises if the other side has gone. A semaphore synchronises memory:
    what a process wrote before it posted is what the taker reads after."""
    deadline = time.perf_counter() + spin
    while not semaphore.acquire(False):
        if time.perf_counter() >= deadline:
            while not semaphore.acquire(timeout=1.0):
                check()
            return


class SharedArrays:
    """Named NumPy arrays in one block of shared memory: created by process 0, attached by name elsewhere."""

    def __init__(self, layout: dict[str, tuple[tuple[int, ...], type]], name: str | None = None):
        offsets, size = {}, 0
        for key, (shape, dtype) in layout.items():
            offsets[key] = size
            size += -(-int(np.prod(shape)) * np.dtype(dtype).itemsize // 64) * 64  # 64-byte aligned
        self._shm = SharedMemory(name=name, create=name is None, size=max(size, 64))
        self.name = self._shm.name
        self.arrays = {
            key: np.ndarray(shape, dtype, buffer=self._shm.buf, offset=offsets[key])
            for key, (shape, dtype) in layout.items()
        }
        if name is None:
            for array in self.arrays.values():
                array.fill(0)

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    def close(self, unlink: bool = False) -> None:
        self.arrays.clear()  # the views must go before the mapping can
        self._shm.close()
        if unlink:
            self._shm.unlink()


def shared_layout(
    num_steps: int,
    num_envs: int,
    max_joints: int,
    num_params: int,
    processes: int,
    global_features: int,
    joint_features: int = 0,
) -> dict:
    """Everything the processes share: the rollout, its advantages and returns, the parameters, the current
    epoch's minibatches and, per helper, one gradient and its part's size and statistics."""
    n, helpers = num_steps * num_envs, processes - 1
    return {
        **{
            f"rollout.{k}": v
            for k, v in rollout_layout(num_steps, num_envs, max_joints, global_features, joint_features).items()
        },
        "advantages": ((num_steps, num_envs), np.float32),
        "returns": ((num_steps, num_envs), np.float32),
        "theta": ((num_params,), np.float32),
        "mb": ((n,), np.int64),
        "mb_advantages": ((n,), np.float32),
        "grad": ((helpers, num_params), np.float32),
        "part_size": ((helpers, 2), np.int64),  # samples, whether the clip share was written
        "part_losses": ((helpers, 3), np.float32),
        "part_log_ratio": ((helpers, n), np.float32),
        "part_clip_share": ((helpers, n), np.float32),
    }


def shared_rollout(shared: SharedArrays, run: RolloutSpec) -> Rollout:
    return Rollout(
        run.num_steps, run.num_envs, run.max_joints, lambda name, shape, dtype: shared[f"rollout.{name}"],
        run.global_features, run.joint_features,
    )  # fmt: skip


@dataclasses.dataclass(frozen=True)
class HelperSpec:
    """What the helpers of a run start from (each builds everything else itself)."""

    processes: int
    rollout: RolloutSpec
    """the run's rollout: helper r steps worker r's share of it (``RolloutSpec.worker``)"""
    update: UpdateConfig
    compile: bool


# -- the commands process 0 sends a helper; each is answered by the helper's method of its name ------------
@dataclasses.dataclass(frozen=True)
class Ready:
    """Answered once the helper has built its swimmers and policy."""


@dataclasses.dataclass(frozen=True)
class Collect:
    """Step the helper's swimmers into its columns under the published parameters; answered with the
    episodes that finished."""


@dataclasses.dataclass(frozen=True)
class GetState:
    """Answered with the helper's ``WorkerState``."""


@dataclasses.dataclass(frozen=True)
class SetState:
    state: WorkerState


@dataclasses.dataclass(frozen=True)
class Begin:
    """An update begins on the shared rollout, its advantages and the published parameters."""

    kl_beta: torch.Tensor | None


@dataclasses.dataclass(frozen=True)
class Epoch:
    """The epoch's minibatches (their permutation and advantages in shared memory) end at ``cuts``; not
    answered: the helper signals each part's gradient through its semaphores."""

    cuts: list[int]


@dataclasses.dataclass(frozen=True)
class Close:
    """Leave (not answered)."""


def _command_name(command) -> str:
    # a tuple is named by its first item, as the string protocol before these classes was
    return str(command[0]) if isinstance(command, tuple) and command else type(command).__name__


class Helpers:
    """Process 0's side: starts the helpers, shares the rollout with them and takes their parts of every
    minibatch (a ``minibatches.MinibatchPeers``)."""

    def __init__(self, spec: HelperSpec, learner: Learner):
        self.world = spec.processes
        self.collecting = False
        """the helpers are collecting (``start_collect`` without ``finish_collect`` yet)"""
        run = spec.rollout
        self.bounds = env_bounds(run.num_envs, spec.processes)
        self.theta = learner.params.theta
        layout = shared_layout(
            run.num_steps,
            run.num_envs,
            run.max_joints,
            self.theta.numel(),
            spec.processes,
            run.global_features,
            run.joint_features,
        )
        self.shared = SharedArrays(layout)
        self.rollout = shared_rollout(self.shared, run)
        self._theta = torch.from_numpy(self.shared["theta"])
        self._grads = torch.from_numpy(self.shared["grad"])
        context = multiprocessing.get_context("spawn")  # fork would copy torch's and MuJoCo's threads' locks
        self._procs, self._conns = [], []
        # per helper: its part's gradient is ready (helper -> 0), the new parameters are (0 -> helper)
        self._done = [context.Semaphore(0) for _ in range(1, spec.processes)]
        self._go = [context.Semaphore(0) for _ in range(1, spec.processes)]
        try:
            for rank in range(1, spec.processes):
                ours, theirs = context.Pipe()
                signals = (self._done[rank - 1], self._go[rank - 1])
                proc = context.Process(
                    target=helper_main,
                    args=(spec, rank, (self.shared.name, layout), theirs, signals),
                    name=f"morph-train-helper{rank}",
                    daemon=True,
                )
                proc.start()
                theirs.close()  # only the helper holds its end now: its death reads as EOF here
                self._procs.append(proc)
                self._conns.append(ours)
            self._call_all(Ready())
        except BaseException:
            self.close()
            raise

    # -- talking to the helpers ------------------------------------------------
    def _send(self, rank: int, command) -> None:
        try:
            self._conns[rank - 1].send(command)
        except (BrokenPipeError, ConnectionResetError, OSError):
            raise HelperError(self._gone(rank)) from None

    def _receive(self, rank: int):
        """Helper ``rank``'s answer to its last command."""
        conn, proc = self._conns[rank - 1], self._procs[rank - 1]
        try:
            while not (poll_spinning(conn) or conn.poll(1.0)):
                if not proc.is_alive():
                    raise HelperError(self._gone(rank))
            outcome, value = conn.recv()
        except (EOFError, ConnectionResetError, OSError):
            raise HelperError(self._gone(rank)) from None
        if outcome == "error":
            raise HelperError(f"training helper {rank} failed:\n{value}")
        return value

    def _check(self, rank: int) -> None:
        """Raise ``HelperError`` if helper ``rank`` has died or reported an error while process 0 waits."""
        if self._conns[rank - 1].poll() or not self._procs[rank - 1].is_alive():
            self._receive(rank)
            raise HelperError(f"training helper {rank} spoke out of turn")

    def _gone(self, rank: int) -> str:
        proc = self._procs[rank - 1]
        proc.join(timeout=1.0)
        return f"training helper {rank} (pid {proc.pid}) died (exit code {proc.exitcode})"

    def _call_all(self, command) -> list:
        for rank in range(1, self.world):
            self._send(rank, command)
        return [self._receive(rank) for rank in range(1, self.world)]

    # -- collection ------------------------------------------------------------
    def publish_parameters(self) -> None:
        self._theta.copy_(self.theta.detach())

    def start_collect(self) -> None:
        """The helpers start collecting their swimmers under the current parameters."""
        self.publish_parameters()
        for rank in range(1, self.world):
            self._send(rank, Collect())
        self.collecting = True

    def finish_collect(self) -> list[Episode]:
        """Wait for the helpers' columns; their finished episodes."""
        episodes = [episode for rank in range(1, self.world) for episode in self._receive(rank)]
        self.collecting = False
        return episodes

    def publish_advantages(self, advantages: torch.Tensor, returns: torch.Tensor) -> None:
        self.shared["advantages"][:] = advantages.numpy()
        self.shared["returns"][:] = returns.numpy()

    # -- the update (minibatches.MinibatchPeers) ------------------------------------
    def begin(self, kl_beta: torch.Tensor | None) -> None:
        self.publish_parameters()
        self._call_all(Begin(None if kl_beta is None else kl_beta.clone()))

    def epoch(self, perm: torch.Tensor, cuts: list[int], advantages: torch.Tensor) -> None:
        n = len(perm)
        self.shared["mb"][:n] = perm.numpy()
        self.shared["mb_advantages"][:n] = advantages.numpy()
        for rank in range(1, self.world):
            self._send(rank, Epoch(cuts))

    def gather(self, grad: torch.Tensor) -> list[MinibatchPart]:
        parts = []
        for rank in range(1, self.world):
            take_spinning(self._done[rank - 1], functools.partial(self._check, rank))
            slot = rank - 1
            size, has_clip_share = self.shared["part_size"][slot]
            grad += self._grads[slot]
            losses = torch.from_numpy(self.shared["part_losses"][slot].copy())
            log_ratio = torch.from_numpy(self.shared["part_log_ratio"][slot, :size].copy())
            clip_share = (
                torch.from_numpy(self.shared["part_clip_share"][slot, :size].copy()) if has_clip_share else None
            )
            parts.append(MinibatchPart(losses[0], losses[1], losses[2], log_ratio, clip_share))
        return parts

    def stepped(self) -> None:
        self.publish_parameters()
        for go in self._go:
            go.release()

    # -- checkpoints ----------------------------------------------------------------
    def get_states(self) -> list[WorkerState]:
        """Each helper's swimmers and noise generator, in rank order."""
        return self._call_all(GetState())

    def set_states(self, states: list[WorkerState]) -> None:
        for rank, state in enumerate(states, start=1):
            self._send(rank, SetState(state))
        for rank in range(1, self.world):
            self._receive(rank)

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(Close())
            except OSError:
                pass
        for proc in self._procs:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.kill()
                proc.join()
        for conn in self._conns:
            conn.close()
        self._procs, self._conns = [], []
        if self.shared is not None:
            self.rollout = None
            self.shared.close(unlink=True)
            self.shared = None


class HelperPool:
    """The rollout workers of a several-process run (a ``rollout_workers.RolloutPool``): process 0's own
    worker (the learner's policy, the run's generator) and the helpers'. ``start`` sets the helpers off;
    ``finish`` steps process 0's share meanwhile, then waits for theirs."""

    def __init__(self, worker: RolloutWorker, helpers: Helpers):
        self.worker, self.helpers = worker, helpers
        self.rollout = helpers.rollout
        self.bounds = helpers.bounds
        self.rng_names: list[str | None] = [None] + [f"helper{rank}" for rank in range(1, helpers.world)]

    @property
    def collecting(self) -> bool:
        return self.helpers.collecting

    def start(self, theta: torch.Tensor) -> None:
        self.helpers.start_collect()  # publishes the learner's parameters, which are ``theta``

    def finish(self) -> list[Episode]:
        episodes = self.worker.collect()
        return episodes + self.helpers.finish_collect()

    def get_states(self) -> list[WorkerState]:
        return [self.worker.get_state(), *self.helpers.get_states()]

    def set_states(self, states: list[WorkerState]) -> None:
        self.worker.set_state(states[0])
        self.helpers.set_states(states[1:])

    def close(self) -> None:
        self.worker.close()  # the helpers are the update's peers too: their owner closes them


class _Closed(Exception):
    """Process 0 closed the helpers while this one waited within an epoch."""


def helper_main(spec: HelperSpec, rank: int, shared: tuple[str, dict], conn: Connection, signals: tuple) -> None:
    """A helper process: steps its swimmers and computes its parts of the minibatches, as told."""
    try:
        _Helper(spec, rank, shared, conn, *signals).serve()
    except (_Closed, EOFError, BrokenPipeError, ConnectionResetError, KeyboardInterrupt):
        pass  # process 0 has gone or stopped: nothing left to do
    except BaseException:
        try:
            conn.send(("error", traceback.format_exc()))
        except OSError:
            pass


class _GradientPeer:
    """A helper's part of every minibatch: its gradient and statistics written to its slot of the shared
    block, signalled through ``done``; the next parameters awaited on ``go``."""

    def __init__(self, spec: HelperSpec, rank: int, learner: Learner, shared: SharedArrays, rollout: Rollout):
        self.spec, self.rank, self.slot = spec, rank, rank - 1
        self.learner, self.shared, self.rollout = learner, shared, rollout
        self.grad = torch.from_numpy(shared["grad"][self.slot])
        self.batch = self.terms = None

    def begin(self, kl_beta: torch.Tensor | None) -> None:
        advantages, returns = (torch.from_numpy(self.shared[k]) for k in ("advantages", "returns"))
        self.batch = self.rollout.batch(advantages, returns)
        self.terms = update_terms(self.learner, self.batch, self.spec.update, kl_beta)

    def epoch(self, cuts: list[int], done, go, take_parameters: Callable[[], None], check: Callable[[], None]):
        perm = torch.from_numpy(self.shared["mb"][: cuts[-1]].copy())
        advantages = torch.from_numpy(self.shared["mb_advantages"][: cuts[-1]].copy())

        def inputs(k: int):  # this helper's part of minibatch k
            lo, hi = cuts[k], cuts[k + 1]
            return part_inputs(self.terms, self.batch, perm[lo:hi], advantages[lo:hi], self.rank, self.spec.processes)

        own = inputs(0)
        for k in range(len(cuts) - 1):
            self._write(*part_gradient(self.learner, self.terms, own))
            done.release()
            if k + 2 < len(cuts):
                own = inputs(k + 1)  # gathered while process 0 adds, clips and steps Adam
            take_spinning(go, check)
            take_parameters()

    def _write(self, grad: torch.Tensor, part: MinibatchPart) -> None:
        shared, slot = self.shared, self.slot
        self.grad.copy_(grad)
        size = len(part.log_ratio)
        shared["part_size"][slot] = [size, part.clip_share is not None]
        shared["part_losses"][slot] = [float(part.pg_loss), float(part.v_loss), float(part.entropy)]
        shared["part_log_ratio"][slot, :size] = part.log_ratio.numpy()
        if part.clip_share is not None:
            shared["part_clip_share"][slot, :size] = part.clip_share.numpy()


class _Helper:
    """A helper process's two jobs, a rollout worker and a gradient peer, on one policy whose parameters
    it takes from the shared block; each command answered by the method of its name."""

    def __init__(self, spec: HelperSpec, rank: int, shared: tuple[str, dict], conn: Connection, done, go):
        torch.set_num_threads(1)
        name, layout = shared
        self.conn, self.done, self.go = conn, done, go
        policy = GraphActorCritic(PolicyConfig.from_dict(spec.rollout.policy))
        self.learner = Learner.create(policy, 0.0, 1e-8, spec.compile)  # its optimizer never steps: process 0's does
        (num_params,) = layout["theta"][0]
        if (mine := self.learner.params.theta.numel()) != num_params:
            raise ValueError(f"the helper's policy has {mine} parameters, not {num_params}")
        self.shared = SharedArrays(layout, name=name)
        run = spec.rollout
        rollout = shared_rollout(self.shared, run)
        worker = run.worker(rank, spec.processes)
        self.worker = RolloutWorker(worker, policy, rollout.columns(worker.lo, worker.hi))
        self.peer = _GradientPeer(spec, rank, self.learner, self.shared, rollout)
        self.theta = torch.from_numpy(self.shared["theta"])
        self._handlers = {
            Ready: self.ready, Collect: self.collect, GetState: self.get_state, SetState: self.set_state,
            Begin: self.begin, Epoch: self.epoch,
        }  # fmt: skip

    def serve(self) -> None:
        while True:
            poll_spinning(self.conn)  # within an update the next epoch comes at once; between updates recv blocks
            command = self.conn.recv()
            if isinstance(command, Close):
                break
            handler = self._handlers.get(type(command))
            if handler is None:
                raise ValueError(f"unknown command {_command_name(command)!r}")
            answer = handler(command)
            if not isinstance(command, Epoch):  # an epoch answers through its semaphores
                self.conn.send(("ok", answer))
        self.worker.close()
        self.shared.close()

    def take_parameters(self) -> None:
        self.learner.params.theta.data.copy_(self.theta)

    def check(self) -> None:
        """Within an epoch process 0 only ever says ``Close``; its death reads as EOF."""
        if self.conn.poll():
            raise _Closed(self.conn.recv())

    # -- the commands ------------------------------------------------------------
    def ready(self, _: Ready) -> None:
        return None

    def collect(self, _: Collect) -> list[Episode]:
        self.take_parameters()
        return self.worker.collect()

    def get_state(self, _: GetState) -> WorkerState:
        return self.worker.get_state()

    def set_state(self, command: SetState) -> None:
        self.worker.set_state(command.state)

    def begin(self, command: Begin) -> None:
        self.take_parameters()
        self.peer.begin(command.kl_beta)

    def epoch(self, command: Epoch) -> None:
        self.peer.epoch(command.cuts, self.done, self.go, self.take_parameters, self.check)
