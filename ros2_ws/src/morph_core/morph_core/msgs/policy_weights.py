"""The layout of the weights topic: a whole policy (safetensors bytes + JSON config) with a version number.

A live trainer publishes each new policy on ``policy_weights`` and every policy
node adopts it. On the wire it is a standard ``std_msgs/msg/UInt8MultiArray``
(every ROS tool can record, replay and show it; no custom interface package to
build and install on each robot):

    data                the policy's safetensors file, byte for byte
    layout.dim[0]       label "safetensors", size = stride = len(data)
    layout.dim[1]       label: one JSON object, size = stride = 0:
                        {"format": "morph_policy_weights/1", "version": <int >= 0>,
                         "policy": <PolicyConfig as a dict, as the checkpoint's .json>,
                         "metadata": {...}}

The checkpoint's two files travel together in one message, so a node can never
take weights with another policy's config. safetensors holds only tensors and a
JSON header: nothing is unpickled, and it parses with NumPy alone (no torch on
the robot). Versions count the trainer's updates (0 = the initial policy); a
policy node reports the version it runs in every ``policy_info`` it publishes,
as ``header.frame_id`` = ``weights@<version>`` (``policy_version_frame_id``),
so a trainer can tell stale samples.

``unpack_policy_weights`` checks everything that can be checked without the
model: the labels, the JSON, the version, the config being an object, the
safetensors header and every tensor being a finite float array. Whether the
shapes fit the config is the model builder's check (``protocol.policy_updates``).
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

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
class PolicyWeights:
    """One policy as it travels: checked tensors (NumPy) plus the raw bytes and config."""

    version: int
    config: dict
    """the policy's config (``PolicyConfig`` fields), as in a checkpoint's .json under "policy\""""
    data: bytes
    """the safetensors file"""
    tensors: dict[str, np.ndarray] = field(repr=False, compare=False)
    metadata: dict = field(default_factory=dict)


def pack_policy_weights(
    version: int, config: dict, data: bytes, metadata: dict | None = None
) -> tuple[list[tuple[str, int, int]], bytes]:
    """The message's fields: (layout dims as (label, size, stride), data bytes).

    Checks the content as ``unpack_policy_weights`` would, so a trainer never sends what a node refuses.
    """
    header = json.dumps(
        {"format": FORMAT, "version": version, "policy": config, "metadata": metadata or {}}, sort_keys=True
    )
    dims = [(DATA_LABEL, len(data), len(data)), (header, 0, 0)]
    unpack_policy_weights([d[0] for d in dims], [d[1] for d in dims], data)
    return dims, bytes(data)


def unpack_policy_weights(labels: Sequence[str], sizes: Sequence[int], data: bytes | Sequence[int]) -> PolicyWeights:
    """The policy in a message, from its layout's labels and sizes and its data; raises ``PolicyWeightsError``."""
    if len(labels) != 2 or len(sizes) != 2:
        raise PolicyWeightsError(f"expected 2 layout dimensions (data, header), got {len(labels)}")
    if labels[0] != DATA_LABEL:
        raise PolicyWeightsError(f"first layout dimension must be labelled {DATA_LABEL!r}, got {labels[0][:40]!r}")
    data = bytes(data)
    if len(data) > MAX_WEIGHTS_BYTES:
        raise PolicyWeightsError(f"{len(data)} bytes of weights, more than the limit of {MAX_WEIGHTS_BYTES}")
    if sizes[0] != len(data):
        raise PolicyWeightsError(f"layout says {sizes[0]} bytes, the message holds {len(data)}")
    if len(labels[1]) > MAX_CONFIG_CHARS:
        raise PolicyWeightsError(f"header of {len(labels[1])} characters, more than {MAX_CONFIG_CHARS}")
    try:
        header = json.loads(labels[1])
    except ValueError as err:
        raise PolicyWeightsError(f"header is not JSON: {err}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise PolicyWeightsError(f"header is not a {FORMAT} object")
    version = header.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise PolicyWeightsError(f"version must be an integer >= 0, got {version!r}")
    config, metadata = header.get("policy"), header.get("metadata", {})
    if not isinstance(config, dict) or not isinstance(metadata, dict):
        raise PolicyWeightsError("header's 'policy' and 'metadata' must be JSON objects")
    return PolicyWeights(version, config, data, read_tensors(data), metadata)


def read_tensors(data: bytes) -> dict[str, np.ndarray]:
    """The tensors of a safetensors file as float arrays, NumPy only; raises ``PolicyWeightsError`` on a
    file that does not parse, holds no tensor, a non-float tensor, or NaN/inf."""
    from safetensors import SafetensorError
    from safetensors.numpy import load

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
