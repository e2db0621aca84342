"""Inference of the graph actor-critic in NumPy, for controllers and for rollouts.

A node answers one chain at a time and a rollout steps six swimmers at a
time; for a network this small torch spends most of such a forward pass on
per-operation overhead (about 0.45 ms against 0.1 ms here). This is the
torch policy's forward pass (``graph_forward``, written once) on NumPy's
operations (``NUMPY_OPS``) and NumPy copies of its weights, over the same
index plan (``index_plan``: the chains laid end to end, a tree's parent
links), tested equal to torch to 1e-5. Gradients and updates stay in torch.

No torch here: the weights come from a torch policy handed in by the
trainer (its state dict, copied) or from ``weights.load_checkpoint`` (a
controller, which then never imports torch).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from morph_core.policy import graph_forward
from morph_core.policy.gaussian import log_density_from_norm
from morph_core.policy.graph_forward import ConvWeights, Graph, Net
from morph_core.policy.index_plan import IndexPlan, check_parents, is_chain
from morph_core.policy.weights import PolicyWeights


def _state_arrays(source) -> Mapping[str, np.ndarray]:
    """Name -> array of a torch policy's state dict (copied now), a ``PolicyWeights`` or a mapping."""
    if isinstance(source, PolicyWeights):
        return source.arrays
    if hasattr(source, "state_dict"):  # a torch module: its parameters as they are now
        return {k: v.detach().cpu().numpy().copy() for k, v in source.state_dict().items()}
    return source


def _linear(state: Mapping[str, np.ndarray], prefix: str) -> tuple[np.ndarray, np.ndarray]:
    """(W^T, b) of a linear layer, C-ordered copies."""
    return np.array(state[f"{prefix}.weight"].T, order="C"), np.array(state[f"{prefix}.bias"], order="C")


def _conv(state: Mapping[str, np.ndarray], prefix: str) -> ConvWeights:
    """One ``ChainConv`` of a state dict in message form: C-ordered copies, as torch's copy had them (a
    matmul's rounding can depend on the operand's layout)."""
    root = state[f"{prefix}.fwd.lin.weight"]  # [C_out, C_in]
    c_out, c_in = root.shape

    def blocks(net: str) -> np.ndarray | None:
        if f"{net}.weight" not in state:  # a one-directional policy has no tail-to-torso network
            return None
        return graph_forward.edge_blocks(NUMPY_OPS, state[f"{net}.weight"], state[f"{net}.bias"], c_in, c_out)

    bias = np.array(state[f"{prefix}.fwd.bias"], order="C")
    return ConvWeights(np.array(root.T, order="C"), bias, blocks(f"{prefix}.fwd.nn"), blocks(f"{prefix}.bwd.nn"))


class NumpyOps:
    """``graph_forward.ArrayOps`` in NumPy (no torch): what nodes, controllers and rollouts run."""

    @classmethod
    def first_layer(cls, conv: ConvWeights, coef: np.ndarray, sender: np.ndarray | None) -> np.ndarray:
        # The links' input is 1, so the layer's products are its weights themselves (exactly: 1 * w), and
        # its messages are the coefficients times the edge blocks, whatever the parent.
        out = np.repeat(conv.root + conv.bias, coef.shape[0] + 1, axis=0)
        out[1:] += coef @ conv.fwd
        if conv.bwd is not None:
            out = cls.add_to_parents(out, sender, coef @ conv.bwd)
        return out

    @staticmethod
    def outer(coef: np.ndarray, x: np.ndarray) -> np.ndarray:
        return (coef[:, :, None] * x[:, None, :]).reshape(coef.shape[0], -1)

    @staticmethod
    def affine(x: np.ndarray, root: np.ndarray, bias: np.ndarray) -> np.ndarray:
        return x @ root + bias

    @staticmethod
    def add_to_parents(out: np.ndarray, sender: np.ndarray | None, messages: np.ndarray) -> np.ndarray:
        if sender is None:
            out[:-1] += messages
        else:
            np.add.at(out, sender, messages)  # several children's messages meet at a parent
        return out

    @staticmethod
    def relu(x: np.ndarray) -> np.ndarray:
        return np.maximum(x, 0.0)

    @staticmethod
    def relu_mlp(layers, x: np.ndarray) -> np.ndarray:
        for w, b in layers:  # (W^T, b)
            x = np.maximum(x @ w + b, 0.0)
        return x

    @staticmethod
    def tanh_mlp(layers, x: np.ndarray) -> np.ndarray:
        for w, b in layers[:-1]:
            x = np.tanh(x @ w + b)
        w, b = layers[-1]
        return x @ w + b

    @staticmethod
    def mean_per_sample(z: np.ndarray, graph: Graph) -> np.ndarray:
        if graph.joint_sample is None:  # one sample
            return z.mean(axis=0, keepdims=True)
        first, count = graph.pool  # [B] each sample's first joint, [B, 1] its joints
        return np.add.reduceat(z, first, axis=0) / count

    concat = staticmethod(np.concatenate)
    permute_dims = staticmethod(np.transpose)


NUMPY_OPS = NumpyOps()


class _Layout(NamedTuple):
    """Where the joints of padded chains go when the chains are laid end to end (``PackedChains``'s layout)."""

    mask: np.ndarray
    """[B, J] True where a joint exists"""
    joint_padded: np.ndarray
    """[V] each joint's flat index in the padded [B * J] layout"""
    chain: np.ndarray
    """[V] the chain of each joint"""
    slot: np.ndarray
    """[V] each joint's slot, the chains back to back with one cut between neighbours"""
    link: np.ndarray
    """[V] the link behind each joint (``slot + 1``)"""
    coef: np.ndarray
    """[L - 1, 3 + D] the messages' coefficients before the joint states (and D description features) are
    written: 1 in the last column at joints, 0 at cuts"""
    first: np.ndarray
    """[B] each chain's first joint"""
    count: np.ndarray
    """[B, 1] float32 joints per chain"""
    sender: np.ndarray | None
    """[L - 1] the parent link of each slot's joint (trees, ``index_plan.IndexPlan.slot_sender``); None: chains"""

    @classmethod
    def of(cls, num_joints: np.ndarray, width: int, parents: np.ndarray | None = None, described: int = 0) -> _Layout:
        mask = np.arange(width) < num_joints[:, None]
        plan = IndexPlan.of(mask, parents)  # the chains back to back, one cut between neighbours
        slot = plan.joint_slot
        coef = np.zeros((plan.joint_padded.size + num_joints.shape[0] - 1, 3 + described), dtype=np.float32)
        coef[slot, 2 + described] = 1.0
        first = np.cumsum(num_joints) - num_joints  # joints of a chain are contiguous
        count = num_joints[:, None].astype(np.float32)
        return cls(mask, plan.joint_padded, plan.joint_sample, slot, slot + 1, coef, first, count, plan.slot_sender)


class NumpyPolicy:
    """Mean action, value and Gaussian samples of a policy's weights (copied at construction).

    ``source``: a torch ``GraphActorCritic`` (the trainer's; its parameters as they are now), a
    ``weights.PolicyWeights`` (a checkpoint or an untrained policy), or its state dict as arrays.
    """

    def __init__(self, source):
        state = _state_arrays(source)
        convs = [_conv(state, conv) for conv in ("features.conv1", "features.conv2")]
        self.net = Net(
            convs,
            [_linear(state, "features.global_mlp.0"), _linear(state, "features.global_mlp.2")],
            [_linear(state, f"actor_head.{i}") for i in (0, 2, 4)],
            [_linear(state, f"critic_head.{i}") for i in (0, 2, 4)],
        )
        """the weights as ``graph_forward`` reads them"""
        self.log_std = float(state["log_std"])
        self.global_features = self.net.global_mlp[0][0].shape[0]
        """how many global features the policy reads (``PolicyConfig.global_features``: 4 planar, 12 legged)"""
        self.joint_features = int(state["features.conv1.fwd.nn.weight"].shape[1]) - 2
        """description features per joint the policy reads (``PolicyConfig.joint_features``)"""
        self._layouts: dict[tuple[int, str, bytes], _Layout] = {}

    def _check_desc(self, joint_desc, joints: tuple[int, ...]) -> np.ndarray | None:
        """``joint_desc`` as float32 [*joints, D], checked against the policy's D (None when D is 0)."""
        if self.joint_features == 0:
            if joint_desc is not None:
                raise ValueError("this policy reads no joint descriptions (joint_features 0), but some were given")
            return None
        if joint_desc is None:
            raise ValueError(f"this policy reads {self.joint_features} joint description features per joint: pass "
                             "joint_desc")  # fmt: skip
        d = np.asarray(joint_desc, dtype=np.float32)
        if d.shape != (*joints, self.joint_features):
            raise ValueError(f"joint_desc must be {[*joints, self.joint_features]}, got {list(d.shape)}")
        return d

    def mean(
        self,
        joint_pos: np.ndarray,
        joint_vel: np.ndarray,
        global_feats: np.ndarray,
        parents: np.ndarray | None = None,
        joint_desc: np.ndarray | None = None,
    ) -> np.ndarray:
        """[N] mean action of one chain of N joints (torso to tail), or of a tree with ``parents`` [N]
        (joint j's parent joint, -1 for the torso; ValueError if not in -1..j-1); ``joint_desc`` [N, D] the
        joints' descriptions, for a policy that reads them."""
        n = joint_pos.shape[0]
        desc = self._check_desc(joint_desc, (n,))
        coef = np.ones((n, 3 + self.joint_features), dtype=np.float32)
        coef[:, 0], coef[:, 1] = joint_pos, joint_vel
        if desc is not None:
            coef[:, 2:-1] = desc
        sender = None
        if parents is not None:
            p = check_parents(parents, np.ones(n, dtype=bool))
            sender = None if is_chain(p, np.ones(n, dtype=bool)) else p + 1  # one tree: no cuts, slot j = joint j
        one = Graph(coef, sender, None, None)  # one sample: joint j is slot j, behind link j + 1
        z = graph_forward.joint_embeddings(NUMPY_OPS, self.net, one, self._global_feats(global_feats[None]))
        return graph_forward.mean_action(NUMPY_OPS, self.net, z)

    def sample(
        self,
        joint_pos: np.ndarray,
        joint_vel: np.ndarray,
        global_feats: np.ndarray,
        rng: np.random.Generator,
        parents: np.ndarray | None = None,
        joint_desc: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One chain's (or tree's) Gaussian sample: (action [N], mean [N]) as float64, a = mean + sigma * z,
        z ~ N(0, I)."""
        mean = self.mean(joint_pos, joint_vel, global_feats, parents, joint_desc).astype(np.float64)
        return mean + math.exp(self.log_std) * rng.standard_normal(mean.shape[0]), mean

    def forward(
        self, joint_pos, joint_vel, global_feats, num_joints, parents=None, joint_desc=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Padded batch [B, J] (zero padding beyond each chain; trees with ``parents`` [B, J]; descriptions
        ``joint_desc`` [B, J, D] for a policy that reads them) -> mean [B, J] (zero at padding), value [B]."""
        chains, graph, z = self._joint_embeddings(joint_pos, joint_vel, global_feats, num_joints, parents, joint_desc)
        return self._padded_mean(chains, z, joint_pos.shape), graph_forward.value(NUMPY_OPS, self.net, z, graph)

    def mean_actions(self, joint_pos, joint_vel, global_feats, num_joints, parents=None, joint_desc=None) -> np.ndarray:
        """``forward``'s mean [B, J] alone, without the critic: what a deterministic evaluation acts on."""
        chains, _, z = self._joint_embeddings(joint_pos, joint_vel, global_feats, num_joints, parents, joint_desc)
        return self._padded_mean(chains, z, joint_pos.shape)

    def _joint_embeddings(
        self, joint_pos, joint_vel, global_feats, num_joints, parents=None, joint_desc=None
    ) -> tuple[_Layout, Graph, np.ndarray]:
        """The chains' layout, their graph and the [V, C] embedding of every joint (its link's plus its chain's
        global one)."""
        desc = self._check_desc(joint_desc, joint_pos.shape)
        chains = self._layout(num_joints, joint_pos.shape[1], parents)
        coef = chains.coef.copy()
        coef[chains.slot, 0] = joint_pos.reshape(-1)[chains.joint_padded]
        coef[chains.slot, 1] = joint_vel.reshape(-1)[chains.joint_padded]
        if desc is not None:
            coef[chains.slot, 2:-1] = desc.reshape(-1, self.joint_features)[chains.joint_padded]
        graph = Graph(coef, chains.sender, chains.link, chains.chain, (chains.first, chains.count))
        z = graph_forward.joint_embeddings(NUMPY_OPS, self.net, graph, self._global_feats(global_feats))
        return chains, graph, z

    def _padded_mean(self, chains: _Layout, z: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        mean = np.zeros(shape[0] * shape[1], dtype=np.float32)
        mean[chains.joint_padded] = graph_forward.mean_action(NUMPY_OPS, self.net, z)
        return mean.reshape(shape)

    def act(self, joint_pos, joint_vel, global_feats, num_joints, noise: np.ndarray, parents=None, joint_desc=None):
        """Sample a = mean + sigma * noise on each chain's joints: (action [B, J], log_prob [B], value [B], mean)."""
        chains, graph, z = self._joint_embeddings(joint_pos, joint_vel, global_feats, num_joints, parents, joint_desc)
        mean, mask = self._padded_mean(chains, z, joint_pos.shape), chains.mask
        value = graph_forward.value(NUMPY_OPS, self.net, z, graph)
        action = (mean + math.exp(self.log_std) * noise) * mask
        log_prob = log_density_from_norm(np.square(noise * mask).sum(1), num_joints, self.log_std)
        return action.astype(np.float32), log_prob.astype(np.float32), value, mean

    def _layout(self, num_joints: np.ndarray, width: int, parents: np.ndarray | None = None) -> _Layout:
        """The index arrays of chains of ``num_joints`` padded to ``width`` (trees: with ``parents``, checked),
        kept per chain mix: a rollout's mix changes only when a swimmer resets, and computing them took ~8 of
        a step's ~65 µs."""
        # Keyed by the raw bytes: the check below runs once per new mix, not at every step.
        key = (width, num_joints.dtype.str, num_joints.tobytes())
        if parents is not None:
            parents = np.asarray(parents)
            key += (parents.dtype.str, parents.shape, parents.tobytes())
        layout = self._layouts.get(key)
        if layout is None:
            if parents is not None:
                mask = np.arange(width) < num_joints[:, None]
                parents = check_parents(parents, mask)
                if is_chain(parents, mask):
                    parents = None
            if len(self._layouts) >= 256:
                self._layouts.clear()
            layout = self._layouts[key] = _Layout.of(num_joints, width, parents, self.joint_features)
        return layout

    def _global_feats(self, global_feats: np.ndarray) -> np.ndarray:
        """``global_feats`` as float32, checked against the policy's width (else a matmul's shape error)."""
        if global_feats.shape[-1] != self.global_features:
            raise ValueError(f"this policy reads {self.global_features} global features, got {global_feats.shape[-1]}")
        return global_feats.astype(np.float32)
