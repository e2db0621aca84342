"""Graph actor-critic for chains of any length and kinematic trees (the paper's architecture).

Feature extractor (the paper's, 4,376 parameters, with ``bidirectional=False``): two NNConv layers
(24 and 16 channels) over the joint graph, whose link nodes start from a
constant 1 and whose edges carry the joint states; a global MLP 4 -> 128 -> 16
on (yaw, yaw rate, vx, vy) (its input ``PolicyConfig.global_features`` wide: 4, the swimmer's, by
default); the global embedding is added to every joint's embedding (the embedding of the link behind
that joint). ReLU throughout.
By default messages also flow tail-to-torso, through a second edge network
per layer (5,600 parameters; see chain_conv for why direction matters).

Heads (64-64 tanh MLPs, as in the reference): a per-joint Gaussian mean, one
state-independent log-std shared by all joints, and a value from the mean of
the joint embeddings. The log-probability of an action is the sum over the
chain's joints, so it is a density over that sample's own action dimension.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import load_file
from safetensors.torch import save as safetensors_bytes
from torch import nn

from morph_core.policy.chain_conv import BACKENDS, ChainConv
from morph_core.policy.chains import ChainBatch
from morph_core.policy.config import PolicyConfig
from morph_core.policy.gaussian import entropy_per_joint, log_density_per_joint
from morph_core.policy.weights import write_checkpoint


def _mlp(sizes: list[int], act: type[nn.Module], last_act: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2 or last_act:
            layers.append(act())
    return nn.Sequential(*layers)


class TanhMLP(nn.Sequential):
    """Linear, Tanh, ..., Linear (the reference's heads), evaluated through tanh(u) = 2 sigmoid(2u) - 1.

    Same function and gradients (to float rounding). Torch's eager CPU tanh kernel was ~5x slower than
    sigmoid when this was written and dominated the update; in today's compiled update step the sigmoid
    form is still ~12% faster than plain tanh (docs/benchmarks.md). The factors 2 and the -1 are moved
    into the small weight matrices, W (2s - 1) + b = (2W) s + (b - W 1), so the large activation
    tensors see one sigmoid per layer and nothing else.
    """

    def __init__(self, sizes: list[int]):
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            layers += [nn.Linear(a, b), nn.Tanh()] if i < len(sizes) - 2 else [nn.Linear(a, b)]
        super().__init__(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        linears = [m for m in self if isinstance(m, nn.Linear)]
        for i, lin in enumerate(linears):
            w, b = lin.weight, lin.bias
            if i > 0:  # the input is s = sigmoid(2u), the layer wants tanh(u) = 2s - 1
                w, b = 2.0 * w, b - w.sum(1)
            if i < len(linears) - 1:  # a tanh follows: compute sigmoid(2u)
                x = torch.sigmoid(F.linear(x, 2.0 * w, 2.0 * b))
            else:
                x = F.linear(x, w, b)
        return x


class GraphFeatureExtractor(nn.Module):
    """Joint graph + global state -> one embedding per joint."""

    def __init__(self, config: PolicyConfig, backend: str = "dense"):
        super().__init__()
        self.config = config
        bi, e = config.bidirectional, config.edge_features
        self.conv1 = ChainConv(1, config.conv1_channels, bi, backend, e)
        self.conv2 = ChainConv(config.conv1_channels, config.embed_channels, bi, backend, e)
        self.global_mlp = _mlp([config.global_features, config.global_hidden, config.embed_channels], nn.ReLU, True)

    def forward(self, batch: ChainBatch) -> torch.Tensor:
        """[V, embed_channels]: one row per joint of the batch, in the padded batch's row-major order."""
        if batch.global_feats.shape[1] != self.config.global_features:  # else a matmul's shape error
            raise ValueError(
                f"this policy reads {self.config.global_features} global features, the batch has "
                f"{batch.global_feats.shape[1]}"
            )
        chains = batch.packed
        if chains.edge_attr.shape[1] != self.config.edge_features:  # else a matmul's shape error
            raise ValueError(
                f"this policy reads {self.config.joint_features} joint description features per joint, the batch "
                f"has {chains.edge_attr.shape[1] - 2} (ChainBatch joint_desc)"
            )
        e, m, s = chains.edge_attr, chains.slot_mask, chains.sender
        x = e.new_ones(chains.num_links, 1)  # links carry no state of their own
        x = torch.relu(self.conv1(x, e, m, s))
        x = torch.relu(self.conv2(x, e, m, s))
        joint_embed = x[chains.joint_link]  # joint j reads the link behind it (link j+1 of its chain)
        return joint_embed + self.global_mlp(batch.global_feats)[chains.joint_chain]


class GraphActorCritic(nn.Module):
    """pi(a | s) = prod_j N(a_j; mu_j(s), sigma^2) over the chain's joints, and V(s).

    ``backend`` is how the chain convolutions execute, not part of the network: 'dense' (batched
    chain NNConv) or 'pyg' (PyTorch Geometric's NNConv, the reference), same parameters either way.
    """

    def __init__(self, config: PolicyConfig | None = None, backend: str = "dense"):
        super().__init__()
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.config = config or PolicyConfig()
        self.backend = backend
        h = self.config.head_hidden
        self.features = GraphFeatureExtractor(self.config, backend)
        self.actor_head = TanhMLP([self.config.embed_channels, h, h, 1])
        self.critic_head = TanhMLP([self.config.embed_channels, h, h, 1])
        self.log_std = nn.Parameter(torch.tensor(float(self.config.log_std_init)))
        if self.config.ortho_init:
            self._orthogonal_init()

    def _orthogonal_init(self) -> None:
        # Only torch Linear layers, as SB3 does: PyG's root-weight layers keep PyG's own init.
        def init(module: nn.Module, gain: float) -> None:
            for m in module.modules():
                if type(m) is nn.Linear:
                    nn.init.orthogonal_(m.weight, gain=gain)
                    nn.init.zeros_(m.bias)

        init(self.features, math.sqrt(2))
        init(self.actor_head, math.sqrt(2))
        init(self.critic_head, math.sqrt(2))
        init(self.actor_head[-1], 0.01)
        init(self.critic_head[-1], 1.0)

    def forward(self, batch: ChainBatch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Returns mean [B, J] (zero at padding), log_std (scalar), value [B]."""
        z = self.features(batch)  # [V, C], real joints only
        chains = batch.packed
        mean = z.new_zeros(batch.mask.numel()).index_copy(0, chains.joint_padded, self.actor_head(z).squeeze(1))
        pooled = z.new_zeros(batch.batch_size, z.shape[1]).index_add(0, chains.joint_chain, z)
        value = self.critic_head(pooled / batch.num_joints.unsqueeze(1)).squeeze(1)
        return mean.view(batch.mask.shape), self.log_std, value

    def log_prob(self, batch: ChainBatch, actions: torch.Tensor, mean: torch.Tensor | None = None) -> torch.Tensor:
        """[B] log-density of padded actions [B, J] over each sample's own joints."""
        if mean is None:
            mean = self.forward(batch)[0]
        return gaussian_log_prob(actions, mean, self.log_std, batch.mask)

    def entropy(self, batch: ChainBatch) -> torch.Tensor:
        """[B] entropy of each sample's joint action distribution (grows with its dimension)."""
        per_joint = entropy_per_joint(self.log_std)
        return per_joint * batch.num_joints.to(per_joint.dtype)

    @torch.no_grad()
    def act(self, batch: ChainBatch, deterministic: bool = False, generator: torch.Generator | None = None):
        """Sample (or take the mean): returns action [B, J], log_prob [B], value [B], mean [B, J]."""
        mean, log_std, value = self.forward(batch)
        if deterministic:
            action = mean
        else:
            noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype)
            action = (mean + log_std.exp() * noise) * batch.mask
        return action, gaussian_log_prob(action, mean, log_std, batch.mask), value, mean

    def actor_parameters(self) -> list[nn.Parameter]:
        """Parameters the action distribution depends on (extractor, actor head, log-std)."""
        return [*self.features.parameters(), *self.actor_head.parameters(), self.log_std]

    # -- persistence: safetensors + JSON, nothing is ever unpickled ----------
    def save(self, path: str | Path, metadata: dict | None = None) -> None:
        """Write ``path`` (.safetensors) and ``path`` with .json (config + metadata), atomically."""
        write_checkpoint(path, self.to_bytes(), asdict(self.config), metadata)

    def to_bytes(self) -> bytes:
        """The parameters as a safetensors file (what a checkpoint and a weights message hold)."""
        return safetensors_bytes({k: v.detach().contiguous() for k, v in self.state_dict().items()})

    @classmethod
    def load(cls, path: str | Path, backend: str = "dense") -> GraphActorCritic:
        path = Path(path)
        if path.suffix != ".safetensors":
            raise ValueError(f"expected a .safetensors file, got {path}")
        meta_path = path.with_suffix(".json")
        try:
            meta = json.loads(meta_path.read_text())
        except FileNotFoundError:
            raise FileNotFoundError(f"policy config {meta_path} missing beside {path}") from None
        model = cls(PolicyConfig.from_dict(meta["policy"]), backend)
        model.load_state_dict(load_file(str(path)))
        return model


def gaussian_log_prob(
    actions: torch.Tensor, mean: torch.Tensor, log_std: torch.Tensor, mask: torch.Tensor
) -> torch.Tensor:
    """sum_j log N(a_j; mu_j, sigma^2) over valid joints; [B]."""
    z = (actions - mean) * torch.exp(-log_std)
    return (log_density_per_joint(z, log_std) * mask).sum(dim=1)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
