"""A policy node's side of live training: take new weights off the wire, keep the current policy on any error.

``PolicyUpdates`` holds the policy a node runs and its weights version.
``offer`` takes one ``policy_weights`` message's fields (``msgs.policy_weights``),
checks them, builds the candidate policy with the node's own builder (which
checks shapes against the config, NumPy or torch alike) and keeps it pending;
``current`` adopts a pending candidate and returns the policy to act with. A
node calls ``current`` once at the start of answering a state, so a new policy
is taken between two answers, never within one, whatever thread the weights
arrived on.

What is adopted: a version newer than the one running, or any version from
another trainer run (``metadata["run"]``: a trainer started afresh counts from 0
again, and its policy is the one the researcher wants now). The same or an
older version of the same run is ignored and counted (a re-delivered latched
sample, a reordered one). Anything that fails a check is rejected, counted
by reason and the current policy kept; ``last_error`` says why.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

from morph_core.msgs.policy_weights import PolicyWeights, PolicyWeightsError, unpack_policy_weights

P = TypeVar("P")


@dataclass(frozen=True)
class Offer:
    """What ``offer`` did with one message."""

    outcome: str
    """"pending" (adopted at the next ``current``), "ignored" (not newer) or "rejected\""""
    version: int | None
    reason: str = ""


class PolicyUpdates(Generic[P]):
    """The running policy and its version; new weights offered, checked, adopted between answers."""

    def __init__(self, build: Callable[[PolicyWeights], P], policy: P, version: int | None = None, run: str = ""):
        """``build`` turns checked weights into a policy, raising ``ValueError`` (or ``KeyError``,
        ``RuntimeError``) when they do not fit their config; ``policy`` is the one to start with, of
        ``version`` (None: not from a trainer, e.g. a checkpoint file) and trainer run ``run``."""
        self._build = build
        self._policy = policy
        self.version = version
        self.run = run
        self._pending: tuple[P, int, str] | None = None
        self._lock = threading.Lock()
        self.adopted = 0
        self.ignored = 0
        self.rejected: Counter[str] = Counter()
        self.last_error = ""

    def offer(self, labels: Sequence[str], sizes: Sequence[int], data) -> Offer:
        """Check one message (its layout's labels and sizes, its data) and keep it pending if it is newer."""
        try:
            weights = unpack_policy_weights(labels, sizes, data)
        except PolicyWeightsError as err:
            return self._reject("layout", str(err))
        run = str(weights.metadata.get("run", ""))
        with self._lock:
            newest = self._pending[1:] if self._pending is not None else (self.version, self.run)
        if run == newest[1] and newest[0] is not None and weights.version <= newest[0]:
            self.ignored += 1
            return Offer("ignored", weights.version, f"version {weights.version} is not newer than {newest[0]}")
        try:
            policy = self._build(weights)
        except (ValueError, KeyError, RuntimeError, TypeError) as err:
            return self._reject("model", f"weights version {weights.version} do not fit their config: {err}")
        with self._lock:
            self._pending = (policy, weights.version, run)
        return Offer("pending", weights.version)

    def _reject(self, reason: str, detail: str) -> Offer:
        self.rejected[reason] += 1
        self.last_error = detail
        return Offer("rejected", None, detail)

    def replace(self, policy: P, version: int | None = None, run: str = "") -> None:
        """Run ``policy`` from now on (a checkpoint the node was told to load), dropping a pending one; pushed
        weights are then taken again when newer than ``version`` of ``run``."""
        with self._lock:
            self._policy, self.version, self.run = policy, version, run
            self._pending = None

    def current(self) -> P:
        """The policy to act with now, after adopting a pending one."""
        with self._lock:
            if self._pending is not None:
                self._policy, self.version, self.run = self._pending
                self._pending = None
                self.adopted += 1
            return self._policy

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())
