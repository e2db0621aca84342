"""Simulator training on several processes: the swimmers and every minibatch's gradient shared out.

Threads cannot share this work: a rollout steps six small swimmers and a
minibatch step is a few hundred small operations, so handing pieces to a
thread costs about what it saves (a second env thread added 4%, a second
torch thread nothing). Processes each own a share of the swimmers and a part
of every minibatch, and meet once per minibatch step:

- **Collect.** Process r steps swimmers lo..hi-1 under a NumPy snapshot of
  the policy and writes their columns of one rollout in shared memory, with
  its own action-noise generator.
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

The data stays in one block of shared memory; commands are small tuples
through a pipe per helper, and within an epoch two semaphores per helper say
"your part's gradient is ready" and "the new parameters are", polled before
a process blocks on them (a pipe message cost ~30 µs each way). A helper
that dies closes its pipe, and process 0 stops with ``HelperError`` instead
of waiting for it.

A run's random streams depend on the process count: one process draws
every swimmer's noise from the run's generator, several draw each share's
from its own (``helper_seed``). So ``processes`` is part of a run's config;
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
from morph_core.algo.rollout import Rollout, collect, rollout_layout
from morph_core.algo.update_config import UpdateConfig
from morph_core.env.vec_env import SwimmerVecEnv
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy


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


def env_bounds(num_envs: int, processes: int) -> list[tuple[int, int]]:
    """(lo, hi) of the swimmers each process steps: as even a split as the count allows."""
    edges = np.linspace(0, num_envs, processes + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def helper_seed(seed: int, rank: int) -> int:
    """The action-noise seed of helper ``rank`` (process 0 uses the run's generator)."""
    return int(np.random.SeedSequence([seed, rank]).generate_state(1)[0])


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


def shared_layout(num_steps: int, num_envs: int, max_joints: int, num_params: int, processes: int) -> dict:
    """Everything the processes share: the rollout, its advantages and returns, the parameters, the current
    epoch's minibatches and, per helper, one gradient and its part's size and statistics."""
    n, helpers = num_steps * num_envs, processes - 1
    return {
        **{f"rollout.{k}": v for k, v in rollout_layout(num_steps, num_envs, max_joints).items()},
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


def shared_rollout(shared: SharedArrays, num_steps: int, num_envs: int, max_joints: int) -> Rollout:
    return Rollout(num_steps, num_envs, max_joints, alloc=lambda name, shape, dtype: shared[f"rollout.{name}"])


@dataclasses.dataclass(frozen=True)
class HelperSpec:
    """What a helper needs to start (it builds everything else itself)."""

    rank: int
    processes: int
    shm_name: str
    num_steps: int
    num_envs: int
    bodies: str
    """the swimmers' bodies, an ``env.bodies`` spec"""
    max_joints: int
    """the largest of them: the rollout's width"""
    seed: int
    env_threads: int
    num_params: int
    policy: dict
    compile: bool
    update: UpdateConfig


class Helpers:
    """Process 0's side: starts the helpers, shares the rollout with them and takes their parts of every
    minibatch (a ``minibatches.MinibatchPeers``)."""

    def __init__(self, spec: HelperSpec, learner: Learner):
        self.world = spec.processes
        self.collecting = False
        """the helpers are collecting (``start_collect`` without ``finish_collect`` yet)"""
        self.bounds = env_bounds(spec.num_envs, spec.processes)
        self.theta = learner.params.theta
        layout = shared_layout(spec.num_steps, spec.num_envs, spec.max_joints, self.theta.numel(), spec.processes)
        self.shared = SharedArrays(layout)
        self.rollout = shared_rollout(self.shared, spec.num_steps, spec.num_envs, spec.max_joints)
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
                    args=(dataclasses.replace(spec, rank=rank, shm_name=self.shared.name), theirs, signals),
                    name=f"morph-train-helper{rank}",
                    daemon=True,
                )
                proc.start()
                theirs.close()  # only the helper holds its end now: its death reads as EOF here
                self._procs.append(proc)
                self._conns.append(ours)
            self._call_all(("ready",))
        except BaseException:
            self.close()
            raise

    # -- talking to the helpers ------------------------------------------------
    def _send(self, rank: int, message: tuple) -> None:
        try:
            self._conns[rank - 1].send(message)
        except (BrokenPipeError, ConnectionResetError, OSError):
            raise HelperError(self._gone(rank)) from None

    def _receive(self, rank: int):
        conn, proc = self._conns[rank - 1], self._procs[rank - 1]
        try:
            while not (poll_spinning(conn) or conn.poll(1.0)):
                if not proc.is_alive():
                    raise HelperError(self._gone(rank))
            reply = conn.recv()
        except (EOFError, ConnectionResetError, OSError):
            raise HelperError(self._gone(rank)) from None
        if reply[0] == "error":
            raise HelperError(f"training helper {rank} failed:\n{reply[1]}")
        return reply[1:]

    def _check(self, rank: int) -> None:
        """Raise ``HelperError`` if helper ``rank`` has died or reported an error while process 0 waits."""
        if self._conns[rank - 1].poll() or not self._procs[rank - 1].is_alive():
            self._receive(rank)
            raise HelperError(f"training helper {rank} spoke out of turn")

    def _gone(self, rank: int) -> str:
        proc = self._procs[rank - 1]
        proc.join(timeout=1.0)
        return f"training helper {rank} (pid {proc.pid}) died (exit code {proc.exitcode})"

    def _call_all(self, message: tuple) -> list:
        for rank in range(1, self.world):
            self._send(rank, message)
        return [self._receive(rank) for rank in range(1, self.world)]

    # -- collection ------------------------------------------------------------
    def publish_parameters(self) -> None:
        self._theta.copy_(self.theta.detach())

    def start_collect(self) -> None:
        """The helpers start collecting their swimmers under the current parameters."""
        self.publish_parameters()
        for rank in range(1, self.world):
            self._send(rank, ("collect",))
        self.collecting = True

    def finish_collect(self) -> list[tuple[int, float, int]]:
        """Wait for the helpers' columns; their finished episodes."""
        episodes = [episode for rank in range(1, self.world) for episode in self._receive(rank)[0]]
        self.collecting = False
        return episodes

    def publish_advantages(self, advantages: torch.Tensor, returns: torch.Tensor) -> None:
        self.shared["advantages"][:] = advantages.numpy()
        self.shared["returns"][:] = returns.numpy()

    # -- the update (minibatches.MinibatchPeers) ------------------------------------
    def begin(self, kl_beta: torch.Tensor | None) -> None:
        self.publish_parameters()
        beta = None if kl_beta is None else kl_beta.clone()
        self._call_all(("begin", beta))

    def epoch(self, perm: torch.Tensor, cuts: list[int], advantages: torch.Tensor) -> None:
        n = len(perm)
        self.shared["mb"][:n] = perm.numpy()
        self.shared["mb_advantages"][:n] = advantages.numpy()
        for rank in range(1, self.world):
            self._send(rank, ("epoch", cuts))

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
    def get_states(self) -> list[tuple[dict, dict[str, np.ndarray], torch.Tensor]]:
        """Each helper's (env meta, env arrays, noise generator state), in rank order."""
        return [tuple(reply) for reply in self._call_all(("get_state",))]

    def set_states(self, states: list[tuple[dict, dict[str, np.ndarray], torch.Tensor | None]]) -> None:
        for rank, state in enumerate(states, start=1):
            self._send(rank, ("set_state", *state))
        for rank in range(1, self.world):
            self._receive(rank)

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(("close",))
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


class _Closed(Exception):
    """Process 0 closed the helpers while this one waited within an epoch."""


def helper_main(spec: HelperSpec, conn: Connection, signals: tuple) -> None:
    """A helper process: steps its swimmers and computes its parts of the minibatches, as told."""
    try:
        _serve(spec, conn, *signals)
    except (_Closed, EOFError, BrokenPipeError, ConnectionResetError, KeyboardInterrupt):
        pass  # process 0 has gone or stopped: nothing left to do
    except BaseException:
        try:
            conn.send(("error", traceback.format_exc()))
        except OSError:
            pass


def _serve(spec: HelperSpec, conn: Connection, done, go) -> None:
    torch.set_num_threads(1)
    lo, hi = env_bounds(spec.num_envs, spec.processes)[spec.rank]
    envs = SwimmerVecEnv(hi - lo, spec.bodies, seed=spec.seed + lo, num_threads=spec.env_threads)
    policy = GraphActorCritic(PolicyConfig.from_dict(spec.policy))
    learner = Learner.create(policy, 0.0, 1e-8, spec.compile)  # its optimizer never steps: process 0's does
    if learner.params.theta.numel() != spec.num_params:
        raise ValueError(f"the helper's policy has {learner.params.theta.numel()} parameters, not {spec.num_params}")
    layout = shared_layout(spec.num_steps, spec.num_envs, spec.max_joints, spec.num_params, spec.processes)
    shared = SharedArrays(layout, name=spec.shm_name)
    rollout = shared_rollout(shared, spec.num_steps, spec.num_envs, spec.max_joints)
    mine = rollout.columns(lo, hi)
    slot = spec.rank - 1
    theta, grad = torch.from_numpy(shared["theta"]), torch.from_numpy(shared["grad"][slot])
    generator = torch.Generator().manual_seed(helper_seed(spec.seed, spec.rank))
    obs = envs.observations()
    batch = terms = None
    cuts: list[int] = []

    def prepare(k: int):
        """The inputs of this helper's part of the epoch's minibatch k."""
        lo, hi = cuts[k], cuts[k + 1]
        return part_inputs(terms, batch, perm[lo:hi], perm_advantages[lo:hi], spec.rank, spec.processes)

    def take_parameters():
        learner.params.theta.data.copy_(theta)

    def check():  # within an epoch process 0 only ever says "close"; its death reads as EOF
        if conn.poll():
            raise _Closed(conn.recv())

    while True:
        poll_spinning(conn)  # within an update the next epoch comes at once; between updates recv blocks
        command, *args = conn.recv()
        if command == "close":
            break
        if command == "collect":
            take_parameters()
            obs, episodes = collect(envs, NumpyPolicy(policy), mine, obs, generator)
            conn.send(("collected", episodes))
        elif command == "begin":
            take_parameters()
            advantages, returns = (torch.from_numpy(shared[k]) for k in ("advantages", "returns"))
            batch = rollout.batch(advantages, returns)
            terms = update_terms(learner, batch, spec.update, args[0])
            conn.send(("begun",))
        elif command == "epoch":
            cuts = args[0]
            perm = torch.from_numpy(shared["mb"][: cuts[-1]].copy())
            perm_advantages = torch.from_numpy(shared["mb_advantages"][: cuts[-1]].copy())
            own = prepare(0)
            for k in range(len(cuts) - 1):
                part_grad, part = part_gradient(learner, terms, own)
                grad.copy_(part_grad)
                size = len(part.log_ratio)
                shared["part_size"][slot] = [size, part.clip_share is not None]
                shared["part_losses"][slot] = [float(part.pg_loss), float(part.v_loss), float(part.entropy)]
                shared["part_log_ratio"][slot, :size] = part.log_ratio.numpy()
                if part.clip_share is not None:
                    shared["part_clip_share"][slot, :size] = part.clip_share.numpy()
                done.release()
                if k + 2 < len(cuts):
                    own = prepare(k + 1)  # gathered while process 0 adds, clips and steps Adam
                take_spinning(go, check)
                take_parameters()
        elif command == "get_state":
            meta, arrays = envs.get_state()
            conn.send(("state", meta, arrays, generator.get_state()))
        elif command == "set_state":
            meta, arrays, generator_state = args
            envs.set_state(meta, arrays)
            if generator_state is not None:
                generator.set_state(generator_state)
            obs = envs.observations()
            conn.send(("set",))
        elif command == "ready":
            conn.send(("ready",))
        else:
            raise ValueError(f"unknown command {command!r}")
    envs.close()
    shared.close()
