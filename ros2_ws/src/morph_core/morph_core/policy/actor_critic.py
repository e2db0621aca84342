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
from safetensors.torch import load_file
from safetensors.torch import save as safetensors_bytes
from torch import nn

from morph_core.policy import graph_forward
from morph_core.policy.chain_conv import BACKENDS, TORCH_OPS, ChainConv, slot_coefficients
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
        return TORCH_OPS.tanh_mlp(linear_layers(self), x)


def linear_layers(module: nn.Sequential) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(weight, bias) of each linear layer of ``module``, in order: its layers as ``graph_forward.Net`` holds them."""
    return [(m.weight, m.bias) for m in module if isinstance(m, nn.Linear)]


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
        return self.embeddings(batch, self.net(), torch_graph(batch))

    def embeddings(self, batch: ChainBatch, net: graph_forward.Net, graph: graph_forward.Graph) -> torch.Tensor:
        """``forward`` with the network and the graph given (``GraphActorCritic`` reads both once)."""
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
        links = None
        if self.conv1.backend == "pyg":  # the reference: PyG's own NNConv on an edge list
            e, m, s = chains.edge_attr, chains.slot_mask, chains.sender
            links = e.new_ones(chains.num_links, 1)  # links carry no state of their own
            for conv in (self.conv1, self.conv2):
                links = torch.relu(conv(links, e, m, s))
        return graph_forward.joint_embeddings(TORCH_OPS, net, graph, batch.global_feats, links)

    def net(self, actor: nn.Sequential | None = None, critic: nn.Sequential | None = None) -> graph_forward.Net:
        """The extractor's weights (with the heads ``actor`` and ``critic``) as the forward pass reads them."""
        return graph_forward.Net(
            [self.conv1.weights(), self.conv2.weights()],
            linear_layers(self.global_mlp),
            [] if actor is None else linear_layers(actor),
            [] if critic is None else linear_layers(critic),
        )


def torch_graph(batch: ChainBatch) -> graph_forward.Graph:
    """The batch's packed chains as ``graph_forward.Graph``."""
    chains = batch.packed
    coef = slot_coefficients(chains.edge_attr, chains.slot_mask)
    return graph_forward.Graph(coef, chains.sender, chains.joint_link, chains.joint_chain, batch.num_joints)


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
        net, graph = self.net(), torch_graph(batch)
        z = self.features.embeddings(batch, net, graph)  # [V, C], real joints only
        joint_mean = graph_forward.mean_action(TORCH_OPS, net, z)
        mean = z.new_zeros(batch.mask.numel()).index_copy(0, batch.packed.joint_padded, joint_mean)
        return mean.view(batch.mask.shape), self.log_std, graph_forward.value(TORCH_OPS, net, z, graph)

    def net(self) -> graph_forward.Net:
        """The policy's weights as ``graph_forward`` reads them (views of the parameters: gradients flow)."""
        return self.features.net(self.actor_head, self.critic_head)

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
