"""A policy node's side of live training: take trusted new weights off the wire, keep the current policy otherwise.

``PolicyUpdates`` holds the policy a node runs and its weights version.
``offer`` takes one ``policy_weights`` message's fields (``msgs.policy_weights``)
and checks them, cheapest first, so a flood of bad messages costs little:

1. the layout and header (``read_weights_message``);
2. the signature (``protocol.trust``): only weights a trusted key signed go on.
   Unsigned weights go on only with ``accept_unsigned`` (for tests);
3. the order: weights are ordered by (epoch, version) (``WeightsMessage.order``:
   a later trainer run, or a later version of the same run). Only weights
   newer than the newest this node ever took go on: the same again (the
   trainer re-publishes every second) is ignored, an older one is a replay
   and rejected;
4. the tensors, and the candidate policy built with the node's own builder
   (which checks shapes against the config, NumPy or torch alike).

A candidate is kept pending; ``current`` adopts it and returns the policy to
act with. A node calls ``current`` once at the start of answering a state, so
a new policy is taken between two answers, never within one, whatever
thread the weights arrived on. Anything refused is counted by a short reason
(``rejected``), the current policy is kept, and ``last_error`` says why.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Generic, TypeVar

from morph_core.msgs.policy_weights import (
    PolicyWeights,
    PolicyWeightsError,
    parse_weights_header,
    read_weights_message,
    with_tensors,
)
from morph_core.policy.config import PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import CheckpointError, weights_from_arrays
from morph_core.policy.weights import PolicyWeights as CheckpointWeights
from morph_core.protocol.controller import policy_error
from morph_core.protocol.trust import Signature, SignatureError, TrustedKeys

P = TypeVar("P")


@dataclass(frozen=True)
class Offer:
    """What ``offer`` did with one message."""

    outcome: str
    """"pending" (adopted at the next ``current``), "ignored" (the weights running, again) or "rejected\""""
    version: int | None
    reason: str = ""
    """why, in a sentence (rejected and ignored)"""
    code: str = ""
    """why, in a short fixed word: layout, unsigned, signature_malformed, untrusted_key, bad_signature, replayed,
    model (rejected); not_newer (ignored)"""
    signer: str = ""
    """the fingerprint of the key that signed it ('' unsigned)"""


class PolicyUpdates(Generic[P]):
    """The running policy and its version; new weights offered, checked, adopted between answers."""

    def __init__(
        self,
        build: Callable[[PolicyWeights], P],
        policy: P,
        keys: TrustedKeys | None = None,
        accept_unsigned: bool = False,
        newest: tuple[int, int] | None = None,
    ):
        """``build`` turns checked weights into a policy, raising ``ValueError`` (or ``KeyError``,
        ``RuntimeError``, ``TypeError``) when they do not fit their config; ``policy`` is the one to start
        with. ``keys``: whose signatures make weights trusted; ``accept_unsigned`` takes unsigned weights too
        (tests). ``newest``: the (epoch, version) of the running policy if it came signed (a checkpoint)."""
        self._build = build
        self._policy = policy
        self.keys = keys if keys is not None else TrustedKeys()
        self.accept_unsigned = accept_unsigned
        self.version: int | None = None
        """the running policy's weights version (None: not pushed, e.g. a checkpoint file)"""
        self.signer = ""
        """the fingerprint of the key that signed the running policy's weights"""
        self.newest = newest
        """the newest (epoch, version) ever taken: older weights are replays"""
        self._pending: tuple[P, int, str] | None = None
        self._lock = threading.Lock()
        self.adopted = 0
        self.ignored = 0
        self.rejected: Counter[str] = Counter()
        self.last_error = ""

    @property
    def enabled(self) -> bool:
        """Whether any pushed weights can be taken at all (a trusted key, or unsigned ones accepted)."""
        return bool(self.keys) or self.accept_unsigned

    def offer(self, labels: Sequence[str], sizes: Sequence[int], data) -> Offer:
        """Check one message (its layout's labels and sizes, its data) and keep it pending if trusted and newer."""
        try:
            message = read_weights_message(labels, sizes, data)
        except PolicyWeightsError as err:
            return self._reject("layout", str(err))
        try:
            signer = self.keys.verify(message.header, message.data_sha256, message.signature)
        except SignatureError as err:
            if not (err.reason == "unsigned" and self.accept_unsigned):
                return self._reject(err.reason, f"weights version {message.version} refused: {err}")
            signer = ""
        with self._lock:
            newest = self.newest
        if newest is not None and message.order <= newest:
            if message.order == newest:
                self.ignored += 1
                return Offer("ignored", message.version, f"version {message.version} is running or pending already",
                             "not_newer", signer)  # fmt: skip
            return self._reject("replayed", f"weights version {message.version} of epoch {message.epoch} are older "
                                f"than version {newest[1]} of epoch {newest[0]}, taken before: a replay")  # fmt: skip
        try:
            policy = self._build(with_tensors(message))
        except PolicyWeightsError as err:
            return self._reject("layout", str(err))
        except (ValueError, KeyError, RuntimeError, TypeError) as err:
            return self._reject("model", f"weights version {message.version} do not fit their config: {err}")
        with self._lock:
            if self.newest is not None and message.order <= self.newest:  # a newer one came in meanwhile
                self.ignored += 1
                return Offer("ignored", message.version, "a newer version came in meanwhile", "not_newer", signer)
            self._pending = (policy, message.version, signer)
            self.newest = message.order
        return Offer("pending", message.version, signer=signer)

    def _reject(self, code: str, detail: str) -> Offer:
        self.rejected[code] += 1
        self.last_error = detail
        return Offer("rejected", None, detail, code)

    def replace(self, policy: P, order: tuple[int, int] | None = None) -> None:
        """Run ``policy`` from now on (a checkpoint the node was told to load), dropping a pending one. Pushed
        weights are taken again when newer than any taken before, and than ``order`` (a signed checkpoint's)."""
        with self._lock:
            self._policy, self.version, self.signer = policy, None, ""
            self._pending = None
            if order is not None and (self.newest is None or order > self.newest):
                self.newest = order

    def current(self) -> P:
        """The policy to act with now, after adopting a pending one."""
        with self._lock:
            if self._pending is not None:
                self._policy, self.version, self.signer = self._pending
                self._pending = None
                self.adopted += 1
            return self._policy

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


@dataclass(frozen=True)
class CheckpointTrust:
    """What a checkpoint's signature says, for the node to report when it loads the file."""

    description: str
    """e.g. ``unsigned``, ``signed by <key> (trusted), version N``, ``signed by <key>, not a trusted key (not checked)``
    """
    signer: str = ""
    order: tuple[int, int] | None = None
    """(epoch, version) of weights a trusted key signed: pushed weights must be newer"""


def checkpoint_trust(weights: CheckpointWeights, keys: TrustedKeys) -> CheckpointTrust:
    """Check a checkpoint's signature against ``keys``. A file on the robot's own disk runs whether signed or
    not; one that claims a trusted key's signature that does not hold (altered bytes, another config) raises
    ``CheckpointError``: it is not the file the trainer wrote."""
    signed = weights.signed
    if signed is None:
        return CheckpointTrust("unsigned")
    try:
        version, epoch, config, _ = parse_weights_header(signed.header)
        key = Signature.parse(signed.signature).key
    except (PolicyWeightsError, SignatureError) as err:
        raise CheckpointError(weights.source, f"its signature entry is malformed ({err})") from None
    if key not in keys.keys:
        return CheckpointTrust(f"signed by {key}, not a trusted key (not checked)", key)
    try:
        keys.verify(signed.header, weights.data_sha256, signed.signature)
        same_config = PolicyConfig.from_dict(config) == weights.config
    except (SignatureError, ValueError, TypeError):
        same_config = False
    if not same_config:
        raise CheckpointError(weights.source, f"signed by trusted key {key}, but the signature does not match the "
                              "file (altered since it was signed)")  # fmt: skip
    return CheckpointTrust(f"signed by {key} (trusted), version {version}", key, (epoch, version))


def drivable(weights: CheckpointWeights) -> CheckpointWeights:
    """``weights`` if a controller can build their inputs from the topics (``protocol.controller``), else
    ``CheckpointError``."""
    error = policy_error(weights.config)
    if error is not None:
        raise CheckpointError(weights.source, f"the policy {error}")
    return weights


def numpy_policy(weights: PolicyWeights) -> tuple[CheckpointWeights, NumpyPolicy]:
    """A trainer's weights, checked like a checkpoint (``CheckpointError``, a ``ValueError``, if they do not fit
    their config or read global features no controller builds), and the NumPy policy that runs them: the
    builder a policy node gives ``PolicyUpdates``."""
    source = f"policy_weights version {weights.version}"
    checked = weights_from_arrays(
        weights.config, weights.tensors, source, trained=weights.version > 0, metadata=weights.metadata
    )
    return drivable(checked), NumpyPolicy(checked)
