"""Policy checkpoints without torch: safetensors + JSON config -> validated NumPy arrays.

A checkpoint is ``<name>.safetensors`` (the torch policy's state dict, as
``GraphActorCritic.save`` writes it) with ``<name>.json`` beside it
(``{"policy": <PolicyConfig fields>, "metadata": {...}}``, and ``"signed_weights"``
when a trainer signed it: ``SignedWeights``). A controller
loads it here with NumPy alone (``safetensors`` parses the file; nothing is
ever unpickled) and runs it with ``numpy_actor.NumpyPolicy``.

Every way a file can be unusable (missing, not safetensors, a torch pickle,
truncated, config missing or wrong, tensors missing, extra, of the wrong
shape or type, NaN/inf) is one ``CheckpointError`` whose text names the file
and the reason, so a node can refuse it in one line.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import safetensors.numpy
from safetensors import SafetensorError

from morph_core.policy.config import PolicyConfig
from morph_core.util.atomic import atomic_write_bytes, atomic_writer

SIGNED_KEY = "signed_weights"
"""the checkpoint .json's entry for a trainer's signature: {"header": ..., "signature": ...}"""

_HEADER_ALLOWANCE = 1 << 20  # bytes a safetensors header may add to the tensors' own
# First bytes of what ``torch.save`` writes: a zip archive (current) or a bare pickle (legacy).
_PICKLE_MAGIC = (b"PK\x03\x04", b"\x80\x02", b"\x80\x03", b"\x80\x04", b"\x80\x05")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; ``path`` and ``reason`` separately, ``str(err)`` both."""

    def __init__(self, path: str | Path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")


@dataclass(frozen=True)
class PolicyWeights:
    """A policy's parameters as float32 arrays under the torch state dict's names."""

    config: PolicyConfig
    arrays: dict[str, np.ndarray]
    source: str
    """the checkpoint's path, or ``untrained (seed N)``"""
    trained: bool
    metadata: dict = field(default_factory=dict)
    data_sha256: str = ""
    """SHA-256 of the safetensors bytes ('' for weights that never were a file or message)"""
    signed: SignedWeights | None = None
    """the trainer's signature the checkpoint carries, if any (checked by ``protocol.policy_updates``)"""


@dataclass(frozen=True)
class SignedWeights:
    """A checkpoint's signature: the weights message header it was signed with, and the signature, as they
    travelled on ``policy_weights`` (``msgs.policy_weights``, ``protocol.trust``)."""

    header: str
    signature: str


def parameter_shapes(config: PolicyConfig) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every tensor in the state dict of ``GraphActorCritic(config)``."""
    shapes: dict[str, tuple[int, ...]] = {"log_std": ()}
    convs = (("conv1", 1, config.conv1_channels), ("conv2", config.conv1_channels, config.embed_channels))
    for name, c_in, c_out in convs:
        base = f"features.{name}"
        shapes[f"{base}.fwd.bias"] = (c_out,)
        shapes[f"{base}.fwd.lin.weight"] = (c_out, c_in)
        for direction in ("fwd", "bwd") if config.bidirectional else ("fwd",):
            shapes[f"{base}.{direction}.nn.weight"] = (c_in * c_out, config.edge_features)
            shapes[f"{base}.{direction}.nn.bias"] = (c_in * c_out,)
    g = config.global_hidden
    shapes.update(
        {
            "features.global_mlp.0.weight": (g, config.global_features),
            "features.global_mlp.0.bias": (g,),
            "features.global_mlp.2.weight": (config.embed_channels, g),
            "features.global_mlp.2.bias": (config.embed_channels,),
        }
    )
    h = config.head_hidden
    for head in ("actor_head", "critic_head"):
        for i, (n_in, n_out) in zip((0, 2, 4), ((config.embed_channels, h), (h, h), (h, 1)), strict=True):
            shapes[f"{head}.{i}.weight"] = (n_out, n_in)
            shapes[f"{head}.{i}.bias"] = (n_out,)
    return shapes


def load_checkpoint(path: str | Path) -> PolicyWeights:
    """The checkpoint at ``path`` (.safetensors, config .json beside it), fully checked.

    Raises ``CheckpointError`` for anything that makes it unusable; nothing else escapes.
    """
    path = Path(path)
    if path.suffix != ".safetensors":
        raise CheckpointError(path, "not a .safetensors file (the config .json must sit beside it)")
    if not path.is_file():
        raise CheckpointError(path, "no such file")
    config, metadata, signed = _read_config(path)
    expected = parameter_shapes(config)
    payload = 4 * sum(math.prod(s) for s in expected.values())
    try:
        size = path.stat().st_size
        if size > payload + _HEADER_ALLOWANCE:
            raise CheckpointError(path, f"{size} bytes, far more than this architecture's {payload} bytes of weights")
        data = path.read_bytes()
    except OSError as err:
        raise CheckpointError(path, f"cannot read it ({err.strerror or err})") from None
    if data.startswith(_PICKLE_MAGIC):
        raise CheckpointError(path, "a torch pickle, not safetensors (pickles are never loaded)")
    try:
        arrays = safetensors.numpy.load(data)
    except (SafetensorError, ValueError, TypeError, KeyError) as err:
        raise CheckpointError(path, f"not a readable safetensors file ({err})") from None
    _check_arrays(path, arrays, expected)
    digest = hashlib.sha256(data).hexdigest()
    return PolicyWeights(config, arrays, str(path), trained=True, metadata=metadata, data_sha256=digest, signed=signed)


def weights_from_arrays(
    config: dict, arrays: dict[str, np.ndarray], source: str, trained: bool = True, metadata: dict | None = None
) -> PolicyWeights:
    """Weights that arrived otherwise than as files (a trainer's ``policy_weights`` message), checked as a
    checkpoint is: the config parses and every tensor has the config's name, shape, dtype and finite values.

    Raises ``CheckpointError`` naming ``source`` and the reason.
    """
    try:
        policy_config = PolicyConfig.from_dict(config)
    except (ValueError, TypeError) as err:
        raise CheckpointError(source, f"its config is wrong ({err})") from None
    _check_arrays(source, arrays, parameter_shapes(policy_config))
    return PolicyWeights(policy_config, arrays, source, trained=trained, metadata=dict(metadata or {}))


def _read_config(path: Path) -> tuple[PolicyConfig, dict, SignedWeights | None]:
    meta_path = path.with_suffix(".json")
    try:
        text = meta_path.read_text()
    except FileNotFoundError:
        raise CheckpointError(path, f"its config {meta_path.name} is missing") from None
    except (OSError, UnicodeDecodeError) as err:
        raise CheckpointError(path, f"cannot read its config {meta_path.name} ({err})") from None
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as err:
        raise CheckpointError(path, f"its config {meta_path.name} is not valid JSON ({err})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("policy"), dict):
        raise CheckpointError(path, f'its config {meta_path.name} has no "policy" object')
    try:
        config = PolicyConfig.from_dict(meta["policy"])
    except (ValueError, TypeError) as err:
        raise CheckpointError(path, f"its config {meta_path.name} is wrong ({err})") from None
    metadata = meta.get("metadata")
    signed = meta.get(SIGNED_KEY)
    if signed is not None:
        if not (isinstance(signed, dict) and all(isinstance(signed.get(k), str) for k in ("header", "signature"))):
            raise CheckpointError(path, f'its config {meta_path.name} has a malformed "{SIGNED_KEY}" entry')
        signed = SignedWeights(signed["header"], signed["signature"])
    return config, metadata if isinstance(metadata, dict) else {}, signed


def write_checkpoint(
    path: str | Path, data: bytes, config: dict, metadata: dict | None = None, signed: SignedWeights | None = None
) -> None:
    """Write a checkpoint: ``path`` (.safetensors, the bytes ``data``) and its .json (config, metadata and the
    signature if any), each atomically. The bytes are written as given, so a signature over them still holds."""
    path = Path(path)
    meta = {"policy": config, "metadata": metadata or {}}
    if signed is not None:
        meta[SIGNED_KEY] = {"header": signed.header, "signature": signed.signature}
    atomic_write_bytes(path, data)
    with atomic_writer(path.with_suffix(".json")) as f:
        json.dump(meta, f, indent=2)


def _check_arrays(path: Path | str, arrays: dict[str, np.ndarray], expected: dict[str, tuple[int, ...]]) -> None:
    missing = sorted(set(expected) - set(arrays))
    extra = sorted(set(arrays) - set(expected))
    if missing or extra:
        parts = ([f"missing {missing}"] if missing else []) + ([f"unexpected {extra}"] if extra else [])
        raise CheckpointError(path, f"tensors do not match the config: {'; '.join(parts)}")
    for name, shape in expected.items():
        a = arrays[name]
        if a.dtype != np.float32:
            raise CheckpointError(path, f"tensor {name} is {a.dtype}, expected float32")
        if a.shape != shape:
            raise CheckpointError(path, f"tensor {name} has shape {list(a.shape)}, the config says {list(shape)}")
        if not np.isfinite(a).all():
            raise CheckpointError(path, f"tensor {name} holds NaN or inf")


def untrained_weights(config: PolicyConfig | None = None, seed: int = 0) -> PolicyWeights:
    """A freshly initialised policy, seeded (the same ``seed`` gives the same weights).

    Stable-Baselines3's scheme as ``GraphActorCritic`` uses it: orthogonal matrices, gain
    sqrt(2) for hidden layers, 0.01 for the action output (means start near 0), 1 for the value
    output, zero biases; the convolutions' root weights uniform in +-1/sqrt(fan_in). Not the torch
    policy's exact numbers (a different generator), the same kind of start.
    """
    config = config or PolicyConfig()
    rng = np.random.default_rng(seed)
    arrays: dict[str, np.ndarray] = {}
    for name, shape in parameter_shapes(config).items():
        if name == "log_std":
            value = np.array(config.log_std_init)
        elif name.endswith(".bias"):
            value = np.zeros(shape)
        elif name.endswith(".lin.weight") or not config.ortho_init:
            bound = 1.0 / math.sqrt(shape[1])
            value = rng.uniform(-bound, bound, size=shape)
        else:
            gain = {"actor_head.4.weight": 0.01, "critic_head.4.weight": 1.0}.get(name, math.sqrt(2))
            value = _orthogonal(rng, shape, gain)
        arrays[name] = np.array(value, dtype=np.float32, order="C")
    return PolicyWeights(config, arrays, f"untrained (seed {seed})", trained=False)


def _orthogonal(rng: np.random.Generator, shape: tuple[int, int], gain: float) -> np.ndarray:
    rows, cols = shape
    q, r = np.linalg.qr(rng.standard_normal((max(rows, cols), min(rows, cols))))
    q *= np.sign(np.diag(r))  # a uniformly distributed orthogonal matrix
    return gain * (q if rows >= cols else q.T)
