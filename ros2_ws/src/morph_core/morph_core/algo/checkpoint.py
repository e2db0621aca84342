"""Full training state in one safetensors file: weights, optimizer, learner state, RNGs, the trainer's own.

Tensors go in the file's tensor section, everything else (step counters,
optimizer hyper-parameters, NumPy RNG states) as JSON in its metadata, so
loading never unpickles anything. What a trainer keeps beside the learner
(the simulator's swimmers, the bag trainer's data round, the live trainer's
run id) is a named, versioned section: JSON under ``sections[name]`` with its
``version``, arrays as ``section.<name>.<key>`` tensors (``state_section``
reads one; states written before sections kept one under ``env``, read as the
section of the trainer that wrote it, version 1). The file is replaced atomically: a run
killed at any moment leaves the previous checkpoint intact, and the one it
replaces is kept beside it (``previous_state_path``: the last two states
are always on disk). A SHA-256 of every tensor's bytes travels in the
metadata, so a file damaged on disk (truncated, bytes flipped) is told from
a good one; ``resume_training_state`` takes the newest good one and says
which file it skipped and why.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save as safetensors_bytes

from morph_core.algo.run_dir import previous_state_path
from morph_core.util.atomic import atomic_write_bytes

log = logging.getLogger(__name__)


class TrainingStateError(ValueError):
    """No usable training state; ``str(err)`` names each file tried and why it is unusable."""


def _digest(tensors: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for key in sorted(tensors):
        t = tensors[key].detach().contiguous().cpu()
        h.update(key.encode())
        h.update(str(t.dtype).encode() + str(list(t.shape)).encode())
        h.update(t.view(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def save_training_state(
    path: str | Path,
    policy: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
    sections: dict[str, dict],
    arrays: dict[str, np.ndarray],
    counters: dict,
    learner_state: dict[str, torch.Tensor] | None = None,
    more_rngs: dict[str, torch.Tensor] | None = None,
) -> None:
    """``sections``: the trainer's own state by section name, each JSON with its ``version``; ``arrays``: their
    arrays as ``<section>.<key>``. ``learner_state``: further tensors by their full key
    (``learner.Learner.state_tensors``, e.g. the KL penalty's beta), stored bit for bit and given back by
    ``load_training_state`` as they are.
    ``more_rngs``: further generator states by name (a helper process's noise), stored as ``rng.<name>``."""
    tensors = {f"policy.{k}": v.detach().contiguous() for k, v in policy.state_dict().items()}
    for k, v in (learner_state or {}).items():
        if k in tensors or not k.startswith("learner."):
            raise ValueError(f"learner state key {k!r} must start with 'learner.' and be new")
        tensors[k] = v.detach().contiguous()
    opt = optimizer.state_dict()
    for idx, state in opt["state"].items():
        for name, value in state.items():
            tensors[f"optim.{idx}.{name}"] = torch.as_tensor(value).contiguous()
    tensors["rng.torch"] = generator.get_state()
    for k, v in (more_rngs or {}).items():
        if f"rng.{k}" in tensors:
            raise ValueError(f"generator name {k!r} is taken")
        tensors[f"rng.{k}"] = v
    for name, section in sections.items():
        if not isinstance(section.get("version"), int):
            raise ValueError(f"state section {name!r} needs an int version")
    for k, v in arrays.items():
        if k.split(".", 1)[0] not in sections:
            raise ValueError(f"array {k!r} is of no section (keys are <section>.<key>)")
        tensors[f"section.{k}"] = torch.from_numpy(np.ascontiguousarray(v))
    meta = {"param_groups": opt["param_groups"], "sections": sections, "counters": counters}
    metadata = {"state": json.dumps(meta), "sha256": _digest(tensors)}
    atomic_write_bytes(path, safetensors_bytes(tensors, metadata=metadata), previous=previous_state_path(path))


def load_training_state(path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """(tensors by key, JSON metadata) of a checkpoint written by ``save_training_state``."""
    with safe_open(str(path), framework="pt") as f:
        meta = json.loads(f.metadata()["state"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 (safe_open has no __iter__)
    return tensors, meta


def check_training_state(path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """``load_training_state`` of a file that may be damaged: raises ``TrainingStateError`` with the reason
    (missing, unreadable, truncated, metadata not JSON, no counters, bytes that do not match the digest,
    NaN/inf in the policy's weights)."""
    path = Path(path)
    if not path.is_file():
        raise TrainingStateError(f"{path}: no such file")
    try:
        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118
        meta = json.loads(header["state"])
        counters = meta["counters"]
        [int(counters[k]) for k in ("global_step", "iteration", "last_ckpt")]
    except (OSError, ValueError, KeyError, TypeError, RuntimeError, SafetensorError) as err:
        raise TrainingStateError(f"{path}: not a readable training state ({type(err).__name__}: {err})") from None
    digest = header.get("sha256")
    if digest is not None and digest != _digest(tensors):
        raise TrainingStateError(f"{path}: its bytes do not match the checksum written with it (damaged on disk)")
    for key, t in tensors.items():
        if key.startswith("policy.") and t.is_floating_point() and not torch.isfinite(t).all():
            raise TrainingStateError(f"{path}: NaN or inf in {key}")
    return tensors, meta


@dataclass(frozen=True)
class ResumedState:
    tensors: dict[str, torch.Tensor]
    meta: dict
    path: Path
    """the file resumed from"""
    skipped: tuple[str, ...]
    """why each newer file was not used"""


def resume_training_state(path: str | Path) -> ResumedState:
    """The newest good state among ``path`` and ``previous_state_path(path)``: a damaged newest one is skipped
    with a warning naming it and the reason. Raises ``TrainingStateError`` when neither is usable."""
    path = Path(path)
    skipped: list[str] = []
    for candidate in (path, previous_state_path(path)):
        try:
            tensors, meta = check_training_state(candidate)
        except TrainingStateError as err:
            skipped.append(str(err))
            continue
        if skipped:
            step = meta["counters"]["global_step"]
            log.warning("resume: skipped %s; resuming from %s (step %d)", "; ".join(skipped), candidate, step)
        return ResumedState(tensors, meta, candidate, tuple(skipped))
    raise TrainingStateError("no usable training state to resume from: " + "; ".join(skipped))


LEGACY_SECTIONS = {"envs": "swimmers", "round": "data", "run": "live"}
"""a state before sections: the section its ``env`` field is, told by a key only that trainer's has"""


def state_section(
    meta: dict, tensors: dict[str, torch.Tensor], name: str, version: int, path: str | Path = "the state"
) -> tuple[dict, dict[str, torch.Tensor]]:
    """(JSON, arrays by key) of the section ``name`` of a state, whose layout this reader knows as
    ``version``. A state before sections has its trainer's section under ``env`` and arrays as ``env.<key>``:
    read as version 1. Raises ``TrainingStateError`` for a state without the section (another trainer's) or
    with a newer version than ``version``."""
    if "sections" in meta:
        sections, prefix = meta["sections"], f"section.{name}."
    elif isinstance(meta.get("env"), dict):
        legacy = next((s for key, s in LEGACY_SECTIONS.items() if key in meta["env"]), None)
        sections, prefix = ({legacy: {**meta["env"], "version": 1}} if legacy else {}), "env."
    else:
        sections, prefix = {}, ""
    if name not in sections:
        held = ", ".join(sorted(sections)) or "none"
        raise TrainingStateError(f"{path}: no {name!r} section (it holds: {held}): a state of another trainer")
    section = dict(sections[name])
    found = section.pop("version", None)
    if not isinstance(found, int) or found > version:
        raise TrainingStateError(f"{path}: its {name!r} section is version {found}, this trainer reads up to "
                                 f"{version}: written by a newer trainer")  # fmt: skip
    return section, sub_dict(tensors, prefix)


def restore_optimizer(optimizer: torch.optim.Optimizer, tensors: dict, meta: dict) -> None:
    state: dict[int, dict] = {}
    for key, value in tensors.items():
        if key.startswith("optim."):
            _, idx, name = key.split(".", 2)
            state.setdefault(int(idx), {})[name] = value
    optimizer.load_state_dict({"state": state, "param_groups": meta["param_groups"]})


def sub_dict(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
