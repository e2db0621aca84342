"""The graph actor-critic's forward pass, written once for every executor.

Given a batch's graph (``Graph``: the joints laid back to back, ``index_plan``) and the policy's weights in
message form (``Net``), the pass is

    x^0 = 1 on every link
    x^l = relu(x^{l-1} W_root + b + sum_{parent -> child} [e, 1] (x) x_parent A_fwd
                                  + sum_{child -> parent} [e, 1] (x) x_child A_bwd)      (l = 1, 2)
    z_j  = x^2[link behind joint j] + relu-MLP(global features)[sample of j]
    mu_j = tanh-MLP_actor(z_j),      V = tanh-MLP_critic(mean of z_j over the sample's joints)

(``chain_conv`` derives the message form of PyTorch Geometric's NNConv). This module writes the wiring
once; the arithmetic goes through ``ops``, a small set of array operations of one library
(``ArrayOps``):
- NumPy's (``numpy_actor.NUMPY_OPS``) for controllers, nodes and rollouts, without torch;
- torch's (``chain_conv.TORCH_OPS``) for training, where it is differentiated and compiled, and for the
  ONNX graph, which torch's exporter traces from it.

Each library's operations are the kernels that measured fastest there (e.g. the first layer, whose input is
1, takes its weights as its products in NumPy; torch keeps the product, whose gradient sums as it always
did), so the executors agree to float rounding (tested to 1e-5) and each is bit for bit what it was.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple, Protocol

Array = Any
"""an array of the executor's library: ``numpy.ndarray`` or ``torch.Tensor``"""


class ConvWeights(NamedTuple):
    """One edge-conditioned convolution in message form (``chain_conv``)."""

    root: Array
    """[C_in, C_out] W_root^T"""
    bias: Array
    """[C_out]"""
    fwd: Array
    """[(E+1) * C_in, C_out] torso-to-tail message blocks [A_0; ...; A_{E-1}; B] (``edge_blocks``)"""
    bwd: Array | None
    """the tail-to-torso blocks, or None (a one-directional policy, the paper's)"""


class Net(NamedTuple):
    """A policy's weights as the forward pass reads them; a linear layer in its library's form: (W^T, b) in
    NumPy, torch's (weight, bias)."""

    convs: Sequence[ConvWeights]
    global_mlp: Sequence[tuple[Array, Array]]
    """linear layers of the global MLP, ReLU after each (``ArrayOps.relu_mlp``)"""
    actor: Sequence[tuple[Array, Array]]
    """linear layers of the actor head, tanh between them"""
    critic: Sequence[tuple[Array, Array]]
    """linear layers of the critic head, tanh between them"""


class Graph(NamedTuple):
    """A batch's joint graph in one library's arrays (built from ``index_plan.IndexPlan``).

    ``joint_link``/``joint_sample`` None: one sample whose joint j is slot j (no cut), behind link j + 1, the
    form a traced graph takes for a symbolic number of joints (``onnx_export``).
    """

    coef: Array
    """[L-1, E+1] each slot's message coefficients [e, 1]: the joint's edge features, then 1; zero at a cut"""
    sender: Array | None
    """[L-1] the parent link of each slot's joint (trees); None: chains, slot k's parent is link k"""
    joint_link: Array | None
    """[V] the link behind each joint (its child), in the padded batch's row-major order"""
    joint_sample: Array | None
    """[V] the sample of each joint"""
    pool: Any = None
    """what ``ArrayOps.mean_per_sample`` needs beyond ``joint_sample`` (the library's own: counts, starts)"""


class ArrayOps(Protocol):
    """The operations of one array library that the forward pass is written in."""

    def first_layer(self, conv: ConvWeights, coef: Array, sender: Array | None) -> Array:
        """[L, C_out] the pre-activation of the first convolution, whose input is 1 on every link."""

    def outer(self, coef: Array, x: Array) -> Array:
        """[S, (E+1) * C] each sender's features scaled by each coefficient, [e_0 x, ..., 1 x]."""

    def affine(self, x: Array, root: Array, bias: Array) -> Array:
        """x @ root + bias."""

    def add_to_parents(self, out: Array, sender: Array | None, messages: Array) -> Array:
        """``out`` with each slot's message added to its parent link: link k (chains), else sender[k]."""

    def relu(self, x: Array) -> Array: ...

    def relu_mlp(self, layers: Sequence[tuple[Array, Array]], x: Array) -> Array:
        """Linear, ReLU, ..., Linear, ReLU."""

    def tanh_mlp(self, layers: Sequence[tuple[Array, Array]], x: Array) -> Array:
        """Linear, tanh, ..., Linear."""

    def mean_per_sample(self, z: Array, graph: Graph) -> Array:
        """[B, C] the mean of ``z`` [V, C] over each sample's joints."""

    def concat(self, arrays: Sequence[Array]) -> Array:
        """Along the first axis."""

    def permute_dims(self, x: Array, axes: tuple[int, ...]) -> Array: ...


def edge_blocks(ops: ArrayOps, weight: Array, bias: Array, c_in: int, c_out: int) -> Array:
    """[(E+1) * C_in, C_out] the message blocks [A_0; ...; A_{E-1}; B] of a linear edge network (``weight``
    [C_in * C_out, E], ``bias`` [C_in * C_out]): Theta(e) = sum_k e_k A_k + B (``chain_conv``)."""
    # W_e viewed [C_in, C_out, E]: the (in, out) order of PyG's view(-1, C_in, C_out).
    a = ops.permute_dims(weight.reshape(c_in, c_out, -1), (2, 0, 1))
    return ops.concat([a, bias.reshape(1, c_in, c_out)]).reshape(-1, c_out)


def conv(ops: ArrayOps, w: ConvWeights, x: Array | None, coef: Array, sender: Array | None) -> Array:
    """The pre-activation of one convolution on link features ``x`` [L, C_in] (None: 1 on every link)."""
    if x is None:
        return ops.first_layer(w, coef, sender)
    root, bias, fwd, bwd = w
    out = ops.affine(x, root, bias)
    parent = x[:-1] if sender is None else x[sender]
    out[1:] += ops.outer(coef, parent) @ fwd  # parent link -> child link k + 1 across slot k
    if bwd is not None:
        out = ops.add_to_parents(out, sender, ops.outer(coef, x[1:]) @ bwd)  # child -> parent
    return out


def link_embeddings(ops: ArrayOps, convs: Sequence[ConvWeights], coef: Array, sender: Array | None) -> Array:
    """[L, C] every link after the convolutions (ReLU after each); the links start from 1."""
    x = None
    for w in convs:
        x = ops.relu(conv(ops, w, x, coef, sender))
    return x


def joint_embeddings(ops: ArrayOps, net: Net, graph: Graph, global_feats: Array, links: Array | None = None) -> Array:
    """[V, C] each joint's embedding: the link behind it plus its sample's global embedding (``links``: the
    link embeddings when computed otherwise, e.g. by PyTorch Geometric's own layers, the reference)."""
    if links is None:
        links = link_embeddings(ops, net.convs, graph.coef, graph.sender)
    glob = ops.relu_mlp(net.global_mlp, global_feats)
    if graph.joint_link is None:  # one sample, joint j behind link j + 1
        return links[1:] + glob
    return links[graph.joint_link] + glob[graph.joint_sample]


def mean_action(ops: ArrayOps, net: Net, z: Array) -> Array:
    """[V] each joint's mean action from its embedding."""
    return ops.tanh_mlp(net.actor, z)[:, 0]


def value(ops: ArrayOps, net: Net, z: Array, graph: Graph) -> Array:
    """[B] the critic on the mean of each sample's joint embeddings."""
    return ops.tanh_mlp(net.critic, ops.mean_per_sample(z, graph))[:, 0]
