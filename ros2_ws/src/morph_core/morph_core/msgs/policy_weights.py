"""The layout of the weights topic: a whole policy (safetensors bytes + JSON config) with a version number.

A live trainer publishes each new policy on ``policy_weights`` and every policy
node adopts it. On the wire it is a standard ``std_msgs/msg/UInt8MultiArray``
(every ROS tool can record, replay and show it; no custom interface package to
build and install on each robot):

    data                the policy's safetensors file, byte for byte
    layout.dim[0]       label "safetensors", size = stride = len(data)
    layout.dim[1]       label: one JSON object, size = stride = 0:
                        {"format": "morph_policy_weights/1", "version": <int >= 0>,
                         "epoch": <int >= 0, ns>, "policy": <PolicyConfig as a dict,
                         as the checkpoint's .json>, "metadata": {"run": ..., ...}}
    layout.dim[2]       (signed weights) label: the signature, size = stride = 0
                        (``protocol.trust``: Ed25519 over dim[1]'s exact text and
                        the SHA-256 of data)

The checkpoint's two files travel together in one message, so a node can never
take weights with another policy's config. safetensors holds only tensors and a
JSON header: nothing is unpickled, and it parses with NumPy alone (no torch on
the robot). Versions count the trainer's updates (0 = the initial policy); a
policy node reports the version it runs in every ``policy_info`` it publishes,
as ``header.frame_id`` = ``weights@<version>`` (``policy_version_frame_id``),
so a trainer can tell stale samples.

``epoch`` is when the trainer's run began (kept across ``--resume``): ordered
by (epoch, version), a later run's weights are newer than an earlier run's,
which is what lets a node refuse a replayed old message (``protocol.trust``).

``read_weights_message`` checks the labels, the JSON, the version and epoch
and the config being an object, without parsing the tensors;
``unpack_policy_weights`` also parses the safetensors file and checks every
tensor is a finite float array. Whether the shapes fit the config is the
model builder's check (``protocol.policy_updates``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from safetensors import SafetensorError
from safetensors.numpy import load

TOPIC = "policy_weights"
"""the weights topic's name, relative to a pair's namespace"""
FORMAT = "morph_policy_weights/1"
DATA_LABEL = "safetensors"
MAX_WEIGHTS_BYTES = 64 * 1024 * 1024
"""refuse larger payloads outright (the GNN's weights are ~70 KB)"""
MAX_CONFIG_CHARS = 64 * 1024
_VERSION_TAG = re.compile(r"weights@(\d+)")


class PolicyWeightsError(ValueError):
    """A weights message that does not fit the layout; ``str(err)`` is the reason."""


@dataclass(frozen=True)
class WeightsMessage:
    """A weights message as it arrived: its header read and checked, its tensors not yet parsed (a node parses
    them only once the signature says who sent them)."""

    version: int
    epoch: int
    """when the trainer's run began (ns since 1970, kept on resume); (epoch, version) orders weights across runs"""
    config: dict
    """the policy's config (``PolicyConfig`` fields), as in a checkpoint's .json under "policy\""""
    metadata: dict
    header: str = field(repr=False)
    """the header's JSON text as it travelled: what a signature covers (``protocol.trust``)"""
    data: bytes = field(repr=False)
    """the safetensors file"""
    signature: str | None = field(default=None, repr=False)
    """the third layout dimension's label (``protocol.trust.Signature``), None when unsigned"""

    @property
    def order(self) -> tuple[int, int]:
        """Newer weights compare greater: a later run, or a later version of the same run."""
        return (self.epoch, self.version)

    @cached_property
    def data_sha256(self) -> str:
        return hashlib.sha256(self.data).hexdigest()


@dataclass(frozen=True)
class PolicyWeights(WeightsMessage):
    """One policy as it travels: the message plus its checked tensors (NumPy)."""

    tensors: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)


def weights_header(version: int, config: dict, metadata: dict | None = None, epoch: int = 0) -> str:
    """The header's JSON text (what the second layout dimension carries and a signature covers)."""
    return json.dumps(
        {"format": FORMAT, "version": version, "epoch": epoch, "policy": config, "metadata": metadata or {}},
        sort_keys=True,
    )


def pack_policy_weights(
    version: int, config: dict, data: bytes, metadata: dict | None = None, epoch: int = 0, signer=None
) -> tuple[list[tuple[str, int, int]], bytes]:
    """The message's fields: (layout dims as (label, size, stride), data bytes); signed when a
    ``protocol.trust.Signer`` is given (a third dimension carries the signature).

    Checks the content as ``unpack_policy_weights`` would, so a trainer never sends what a node refuses.
    """
    header = weights_header(version, config, metadata, epoch)
    dims = [(DATA_LABEL, len(data), len(data)), (header, 0, 0)]
    if signer is not None:
        dims.append((signer.sign(header, hashlib.sha256(data).hexdigest()).label, 0, 0))
    unpack_policy_weights([d[0] for d in dims], [d[1] for d in dims], data)
    return dims, bytes(data)


def read_weights_message(labels: Sequence[str], sizes: Sequence[int], data: bytes | Sequence[int]) -> WeightsMessage:
    """A message's header and payload, checked as far as can be without parsing the tensors; raises
    ``PolicyWeightsError``."""
    if len(labels) not in (2, 3) or len(sizes) != len(labels):
        raise PolicyWeightsError(f"expected 2 or 3 layout dimensions (data, header, signature), got {len(labels)}")
    if labels[0] != DATA_LABEL:
        raise PolicyWeightsError(f"first layout dimension must be labelled {DATA_LABEL!r}, got {labels[0][:40]!r}")
    data = bytes(data)
    if len(data) > MAX_WEIGHTS_BYTES:
        raise PolicyWeightsError(f"{len(data)} bytes of weights, more than the limit of {MAX_WEIGHTS_BYTES}")
    if sizes[0] != len(data):
        raise PolicyWeightsError(f"layout says {sizes[0]} bytes, the message holds {len(data)}")
    version, epoch, config, metadata = parse_weights_header(labels[1])
    signature = labels[2] if len(labels) == 3 else None
    return WeightsMessage(version, epoch, config, metadata, labels[1], data, signature)


def parse_weights_header(text: str) -> tuple[int, int, dict, dict]:
    """(version, epoch, policy config, metadata) of a header's JSON text; raises ``PolicyWeightsError``."""
    if len(text) > MAX_CONFIG_CHARS:
        raise PolicyWeightsError(f"header of {len(text)} characters, more than {MAX_CONFIG_CHARS}")
    try:
        header = json.loads(text)
    except ValueError as err:
        raise PolicyWeightsError(f"header is not JSON: {err}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise PolicyWeightsError(f"header is not a {FORMAT} object")
    version, epoch = header.get("version"), header.get("epoch", 0)
    for name, value in (("version", version), ("epoch", epoch)):
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2**63:
            raise PolicyWeightsError(f"{name} must be an integer in 0..2^63-1, got {str(value)[:40]}")
    config, metadata = header.get("policy"), header.get("metadata", {})
    if not isinstance(config, dict) or not isinstance(metadata, dict):
        raise PolicyWeightsError("header's 'policy' and 'metadata' must be JSON objects")
    return version, epoch, config, metadata


def unpack_policy_weights(labels: Sequence[str], sizes: Sequence[int], data: bytes | Sequence[int]) -> PolicyWeights:
    """The policy in a message, from its layout's labels and sizes and its data; raises ``PolicyWeightsError``.
    The signature, if any, is not checked here (``protocol.trust``)."""
    return with_tensors(read_weights_message(labels, sizes, data))


def with_tensors(message: WeightsMessage) -> PolicyWeights:
    """The message with its tensors parsed (``read_tensors``); raises ``PolicyWeightsError``."""
    fields = {f.name: getattr(message, f.name) for f in dataclasses.fields(WeightsMessage)}
    return PolicyWeights(**fields, tensors=read_tensors(message.data))


def read_tensors(data: bytes) -> dict[str, np.ndarray]:
    """The tensors of a safetensors file as float arrays, NumPy only; raises ``PolicyWeightsError`` on a
    file that does not parse, holds no tensor, a non-float tensor, or NaN/inf."""
    try:
        tensors = load(data)
    except (SafetensorError, ValueError, TypeError) as err:
        raise PolicyWeightsError(f"not a safetensors file: {err}") from None
    if not tensors:
        raise PolicyWeightsError("the safetensors file holds no tensor")
    for name, a in tensors.items():
        if a.dtype.kind != "f":
            raise PolicyWeightsError(f"tensor {name!r} has dtype {a.dtype}, expected floats")
        if not np.isfinite(a).all():
            raise PolicyWeightsError(f"NaN or inf in tensor {name!r}")
    return tensors


def policy_version_frame_id(version: int | None) -> str:
    """``policy_info``'s ``header.frame_id``: the weights version that produced the sample ('' if unknown)."""
    return "" if version is None else f"weights@{version}"


def parse_policy_version(frame_id: str) -> int | None:
    """The version in a ``policy_info``'s ``header.frame_id``, or None (a node that does not say)."""
    m = _VERSION_TAG.fullmatch(frame_id)
    return None if m is None else int(m.group(1))
