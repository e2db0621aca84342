"""Full training state in one safetensors file: weights, optimizer, learner state, RNGs, env states.

Tensors go in the file's tensor section, everything else (step counters,
optimizer hyper-parameters, NumPy RNG states) as JSON in its metadata, so
loading never unpickles anything. The file is replaced atomically: a run
killed at any moment leaves the previous checkpoint intact.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save as safetensors_bytes

from morph_core.util.atomic import atomic_write_bytes


def save_training_state(
    path: str | Path,
    policy: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
    env_meta: dict,
    env_arrays: dict[str, np.ndarray],
    counters: dict,
    learner_state: dict[str, torch.Tensor] | None = None,
) -> None:
    """``learner_state``: further tensors by their full key (``update.Learner.state_tensors``, e.g. the
    KL penalty's beta), stored bit for bit and given back by ``load_training_state`` as they are."""
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
    for k, v in env_arrays.items():
        tensors[f"env.{k}"] = torch.from_numpy(np.ascontiguousarray(v))
    meta = {"param_groups": opt["param_groups"], "env": env_meta, "counters": counters}
    atomic_write_bytes(path, safetensors_bytes(tensors, metadata={"state": json.dumps(meta)}))


def load_training_state(path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """(tensors by key, JSON metadata) of a checkpoint written by ``save_training_state``."""
    with safe_open(str(path), framework="pt") as f:
        meta = json.loads(f.metadata()["state"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 (safe_open has no __iter__)
    return tensors, meta


def restore_optimizer(optimizer: torch.optim.Optimizer, tensors: dict, meta: dict) -> None:
    state: dict[int, dict] = {}
    for key, value in tensors.items():
        if key.startswith("optim."):
            _, idx, name = key.split(".", 2)
            state.setdefault(int(idx), {})[name] = value
    optimizer.load_state_dict({"state": state, "param_groups": meta["param_groups"]})


def sub_dict(tensors: dict[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
