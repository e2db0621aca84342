"""A checkpoint's deterministic actor as an ONNX graph, for controllers that run no Python.

One chain per call, of any length N (a dynamic axis, ``num_joints``):

    inputs   joint_pos [N], joint_vel [N] (torso to tail), global [G], float32; G is the policy's
             ``global_features``: 4 for a swimmer's (yaw, yaw rate, vx, vy), 12 for a legged body's
             (``env.centipede.GLOBAL_FEATURES``)
    outputs  action [N]: the policy's mean action (unclipped; the policy node clips to [-1, 1])
             value [1]: the critic's estimate, only when exported ``with_value``

With ``tree=True`` the graph takes a kinematic tree (``index_plan``) instead, one more input:

    parents  [N] int64: joint j's parent joint (< j), or -1 when it hangs off the torso

and computes its index plan in the graph (each joint's sender, its parent link, is ``parents + 1``:
one tree has no cuts). The graph does not check ``parents``; a caller must (``index_plan.check_parents``).

A policy that reads joint descriptions (``PolicyConfig.joint_features`` D > 0) takes one more, last input:

    joint_desc  [N, D] float32: each joint's description (``policy.joint_description``)

The graph is torch's own exporter (``torch.onnx.export``, torch.export based) run on
``SingleChainPolicy``: the one forward pass (``graph_forward``) in torch on one chain laid out as
arrays, instead of the batched ``PackedChains`` whose index building (``nonzero``) does not trace with a
symbolic length. The same parameter tensors and the same operations as training; every export is
checked with ONNX Runtime against the torch policy before anything is written (``check_against_policy``),
so a graph that differs is never left on disk.

A training-side tool: torch is imported here, and ``onnx``/``onnxruntime``/``onnxscript`` (the
trainer's ``[onnx]`` extra) only when an export runs.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from morph_core.constants import NUM_GLOBAL_FEATURES
from morph_core.policy import graph_forward
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chain_conv import TORCH_OPS, slot_coefficients
from morph_core.policy.chains import ChainBatch, chain_batch
from morph_core.policy.weights import PolicyWeights, load_checkpoint
from morph_core.util.atomic import atomic_write_bytes

INPUT_NAMES = ("joint_pos", "joint_vel", "global")
DESC_INPUT = "joint_desc"
"""the last input of a policy that reads joint descriptions (``PolicyConfig.joint_features`` = D > 0): [N, D]
float32, each joint's ``policy.joint_description`` vector"""
TREE_INPUT_NAMES = (*INPUT_NAMES, "parents")
"""the tree graph's inputs (``export_model(tree=True)``): the chain's, then parents [N] int64"""
ACTION_OUTPUT = "action"
VALUE_OUTPUT = "value"
NUM_JOINTS_AXIS = "num_joints"
OPSET = 18
"""ONNX opset of the graph: the oldest torch's exporter writes; ONNX Runtime reads it from 1.14 on"""
FORMAT = "morph_policy_onnx/1"
"""``metadata_props['format']`` of an exported graph: what a controller checks before trusting the names above"""
TREE_FORMAT = "morph_policy_onnx_tree/1"
"""``metadata_props['format']`` of a tree graph (inputs ``TREE_INPUT_NAMES``)"""
CHECK_LENGTHS = (1, 2, 3, 7, 10, 20, 64)
"""chain lengths every export is checked at (1 and 64 are the simulator's extremes)"""
TOLERANCE = 1e-4
"""largest ``scaled_difference`` ONNX Runtime - torch accepted on the check's random states. A wiring
error is off by orders of magnitude more; float32 rounding alone reaches ~2e-5 on the random states'
extremes (a trained policy, 60 joints), and stays below 3e-6 on the states a swimmer visits (tested)."""


class ExportError(RuntimeError):
    """An export that cannot be done or whose graph does not compute the policy; ``str(err)`` says why."""


class SingleChainPolicy(nn.Module):
    """``policy``'s mean action (and value) of one chain: (joint_pos [N], joint_vel [N], global [G]) -> outputs.

    The forward pass of every executor (``graph_forward``, torch's operations on the policy's own
    parameters) on a batch of one chain: every slot holds a joint (no cuts), so the packed chain is just the
    joint states in order and the links are N + 1.
    """

    def __init__(self, policy: GraphActorCritic, with_value: bool):
        super().__init__()
        if policy.backend != "dense":
            raise ExportError(
                f"only the 'dense' chain convolution traces with a symbolic length, got {policy.backend!r}"
            )
        self.policy = policy
        self.with_value = with_value

    def forward(self, joint_pos: torch.Tensor, joint_vel: torch.Tensor, global_feats: torch.Tensor):
        return self._outputs(joint_pos, joint_vel, global_feats, None)

    def _outputs(self, joint_pos, joint_vel, global_feats, sender: torch.Tensor | None, joint_desc=None):
        edge_attr = torch.stack([joint_pos, joint_vel], dim=1)  # slot j holds joint j
        if joint_desc is not None:  # a policy with descriptions: [angle, velocity, description] per joint
            edge_attr = torch.cat([edge_attr, joint_desc], dim=1)
        coef = slot_coefficients(edge_attr, torch.ones_like(joint_pos, dtype=torch.bool))
        one = graph_forward.Graph(coef, sender, None, None)  # one sample: joint j behind link j + 1
        net = self.policy.net()
        z = graph_forward.joint_embeddings(TORCH_OPS, net, one, global_feats.unsqueeze(0))
        action = graph_forward.mean_action(TORCH_OPS, net, z)
        if not self.with_value:
            return action
        return action, graph_forward.value(TORCH_OPS, net, z, one).reshape(1)


class SingleTreePolicy(SingleChainPolicy):
    """``policy``'s mean action (and value) of one kinematic tree: (joint_pos [N], joint_vel [N], global [G],
    parents [N] int64) -> outputs. The index plan of one tree (``index_plan``): slot j holds joint j, whose
    child is link j + 1 and whose parent link (its sender) is link parents[j] + 1."""

    def forward(self, joint_pos, joint_vel, global_feats, parents):
        return self._outputs(joint_pos, joint_vel, global_feats, parents + 1)


class DescribedChainPolicy(SingleChainPolicy):
    """``SingleChainPolicy`` of a policy that reads joint descriptions: one more input, joint_desc [N, D]."""

    def forward(self, joint_pos, joint_vel, global_feats, joint_desc):
        return self._outputs(joint_pos, joint_vel, global_feats, None, joint_desc)


class DescribedTreePolicy(SingleChainPolicy):
    """``SingleTreePolicy`` of a policy that reads joint descriptions: parents, then joint_desc [N, D]."""

    def forward(self, joint_pos, joint_vel, global_feats, parents, joint_desc):
        return self._outputs(joint_pos, joint_vel, global_feats, parents + 1, joint_desc)


@dataclass(frozen=True)
class ExportResult:
    """What ``export_checkpoint`` wrote and how closely the graph matched the torch policy."""

    path: Path
    with_value: bool
    tree: bool
    """the graph takes ``parents`` (``TREE_INPUT_NAMES``)"""
    lengths_checked: tuple[int, ...]
    max_error: float
    """largest difference ONNX Runtime - torch over the checked lengths (``check_against_policy``)"""
    num_nodes: int
    global_features: int = 4
    """the width of the ``global`` input: the policy's (4 a swimmer's, 12 a legged body's)"""


def policy_from_checkpoint(path: str | Path) -> tuple[GraphActorCritic, PolicyWeights]:
    """The torch policy of a checkpoint, checked by ``weights.load_checkpoint`` (``CheckpointError`` if unusable)."""
    weights = load_checkpoint(path)
    policy = GraphActorCritic(weights.config)
    policy.load_state_dict({k: torch.from_numpy(v) for k, v in weights.arrays.items()})
    return policy.eval(), weights


def _require(module: str):
    try:
        return __import__(module)
    except ImportError:
        raise ExportError(
            f"the ONNX export needs the '{module}' package: install the trainer's [onnx] extra "
            "(pip install -c constraints.txt -e 'ros2_ws/src/trainer[onnx]')"
        ) from None


@contextlib.contextmanager
def _quiet_exporter():
    """The exporter logs about optional packages it skips (torchvision) and warns about its own internals:
    nothing a user of this command can act on. Real failures still raise."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*LeafSpec.*", category=FutureWarning)
            warnings.filterwarnings("ignore", message=r".*axis name.*will not be used.*")
            yield
    finally:
        logger.setLevel(level)


def global_input_text(width: int) -> str:
    """The ``global`` input of a graph whose policy reads ``width`` global features, as its doc string says it."""
    if width == NUM_GLOBAL_FEATURES:
        return f"global [{width}] (yaw, yaw rate, vx, vy)"
    return f"global [{width}] (a body in 3-D: env.centipede.GLOBAL_FEATURES when 12)"


def random_global(rng: np.random.Generator, width: int) -> np.ndarray:
    """[width] float32 global features of a body's scale: a turned torso's yaw first, then unit-scale values
    (a swimmer's yaw rate and velocities; a legged body's rates, velocities, height and up vector)."""
    return np.array([rng.uniform(-6, 6), *rng.normal(0.0, 1.0, width - 1)], dtype=np.float32)


def export_model(
    policy: GraphActorCritic, with_value: bool = False, metadata: dict[str, str] | None = None, tree: bool = False
):
    """The ONNX ``ModelProto`` of ``policy``'s single-chain actor (and critic), with ``metadata`` in its props;
    with ``tree``, of one kinematic tree (inputs ``TREE_INPUT_NAMES``)."""
    onnx = _require("onnx")
    _require("onnxscript")  # torch's exporter imports it itself; fail here with the install hint
    described = policy.config.joint_features
    kinds = {(False, False): SingleChainPolicy, (True, False): SingleTreePolicy,
             (False, True): DescribedChainPolicy, (True, True): DescribedTreePolicy}  # fmt: skip
    module = kinds[tree, bool(described)](policy, with_value).eval()
    example = (torch.zeros(3), torch.zeros(3), torch.zeros(policy.config.global_features))
    n = torch.export.Dim(NUM_JOINTS_AXIS, min=1)
    dynamic: tuple = ({0: n}, {0: n}, None)
    if tree:
        example, dynamic = (*example, torch.tensor([-1, 0, 0])), (*dynamic, {0: n})
    if described:
        example, dynamic = (*example, torch.zeros(3, described)), (*dynamic, {0: n})
    names = input_names(tree, described)
    outputs = [ACTION_OUTPUT, VALUE_OUTPUT] if with_value else [ACTION_OUTPUT]
    try:
        with _quiet_exporter(), torch.no_grad():
            program = torch.onnx.export(
                module,
                example,
                input_names=list(names),
                output_names=outputs,
                dynamic_shapes=dynamic,
                opset_version=OPSET,
                dynamo=True,
                external_data=False,
                verbose=False,
            )
    except Exception as err:  # the exporter raises many types; one message naming the step
        raise ExportError(f"torch's ONNX exporter failed: {type(err).__name__}: {err}") from err
    model = program.model_proto
    glob = global_input_text(policy.config.global_features)
    if tree:
        inputs = f"one kinematic tree: joint_pos [N], joint_vel [N] (topological order), {glob}, "
        inputs += "parents [N] int64 (parent joint, -1: the torso)"
    else:
        inputs = f"one chain: joint_pos [N], joint_vel [N] (torso to tail), {glob}"
    if described:
        inputs += f", joint_desc [N, {described}] (each joint's description, policy.joint_description)"
    model.doc_string = f"Graph policy, deterministic actor of {inputs} -> action [N] (mean, unclipped)" + (
        ", value [1]" if with_value else ""
    )
    onnx.helper.set_model_props(model, {"format": TREE_FORMAT if tree else FORMAT, **(metadata or {})})
    onnx.checker.check_model(model, full_check=True)
    return model


def input_names(tree: bool, joint_features: int) -> tuple[str, ...]:
    """The graph's inputs, in order: the chain's or the tree's, then ``joint_desc`` when the policy reads it."""
    return (*(TREE_INPUT_NAMES if tree else INPUT_NAMES), *((DESC_INPUT,) if joint_features else ()))


def scaled_difference(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """|got - want| / max(1, |want|): absolute within the motors' range [-1, 1], relative beyond it.

    Float32 allows no uniform absolute bound: a trained policy's unclipped means reach ~5 and its
    values tens, and on extreme states the torch policy differs from its own float64 evaluation by
    ~1.3e-5 (the shipped model, 60 joints), as much as ONNX Runtime differs from torch.
    """
    return np.abs(got - want) / np.maximum(np.abs(want), 1.0)


TREE_SHAPES = ("random", "star", "chain")
"""the trees a tree graph is checked on at each length: parents drawn from -1..j-1, all on the torso, a chain"""


def random_parents(rng: np.random.Generator, n: int, shape: str) -> np.ndarray:
    """[N] int64 parents of a tree of ``shape`` (one of ``TREE_SHAPES``)."""
    if shape == "star":
        return np.full(n, -1, np.int64)
    if shape == "chain":
        return np.arange(n, dtype=np.int64) - 1
    return np.array([rng.integers(-1, j) for j in range(n)], np.int64)


def check_against_policy(
    model_bytes: bytes,
    policy: GraphActorCritic,
    lengths: Sequence[int] = CHECK_LENGTHS,
    seed: int = 0,
    tree: bool = False,
) -> float:
    """Largest ``scaled_difference`` ONNX Runtime - torch over random states of each chain length in ``lengths``;
    with ``tree``, of trees of each of ``TREE_SHAPES`` at each length, torch given the same parents."""
    ort = _require("onnxruntime")

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(model_bytes, options, providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    rng = np.random.default_rng(seed)
    worst = 0.0
    cases = [(n, shape) for n in lengths for shape in (TREE_SHAPES if tree else (None,))]
    for n, shape in cases:
        # States of a swimming chain's scale: angles within the joint range, fast joints, a turned torso.
        pos = rng.uniform(-1.7, 1.7, n).astype(np.float32)
        vel = rng.normal(0.0, 3.0, n).astype(np.float32)
        glob = random_global(rng, policy.config.global_features)  # the policy's width: 4, or 12 for legs
        inputs = (pos, vel, glob) if shape is None else (pos, vel, glob, random_parents(rng, n, shape))
        described = policy.config.joint_features
        desc = rng.uniform(-1, 1, (n, described)).astype(np.float32) if described else None
        if desc is not None:
            inputs = (*inputs, desc)
        names_in = input_names(tree, described)
        got = dict(zip(names, session.run(None, dict(zip(names_in, inputs, strict=True))), strict=True))
        with torch.no_grad():
            if shape is None and desc is None:
                batch = chain_batch(pos, vel, glob)
            else:
                parents = None if shape is None else inputs[3][None]
                batch = ChainBatch.from_padded(
                    pos[None], vel[None], glob[None], [n], parents=parents,
                    joint_desc=None if desc is None else desc[None],
                )  # fmt: skip
            mean, _, value = policy(batch)
        want = {ACTION_OUTPUT: mean[0].numpy(), VALUE_OUTPUT: value.numpy()}
        for name, out in got.items():
            if out.shape != want[name].shape:
                raise ExportError(f"output {name} has shape {list(out.shape)} for {n} joints, "
                                  f"expected {list(want[name].shape)}")  # fmt: skip
            err = float(np.max(scaled_difference(out, want[name]))) if out.size else 0.0
            worst = max(worst, err if math.isfinite(err) else math.inf)
    return worst


def export_checkpoint(
    checkpoint: str | Path,
    out: str | Path,
    with_value: bool = False,
    lengths: Sequence[int] = CHECK_LENGTHS,
    tolerance: float = TOLERANCE,
    tree: bool = False,
) -> ExportResult:
    """Export ``checkpoint`` to ``out`` (.onnx), written atomically only once ONNX Runtime reproduced the
    policy to ``tolerance`` at every length in ``lengths`` (with ``tree``: the tree graph, checked on trees
    of every shape in ``TREE_SHAPES`` at those lengths).

    Raises ``CheckpointError`` (a ``ValueError``) for an unusable checkpoint and ``ExportError`` otherwise.
    """
    out = Path(out)
    if out.suffix != ".onnx":
        raise ExportError(f"the output must be a .onnx file, got {out}")
    if not lengths or min(lengths) < 1:
        raise ExportError(f"chain lengths to check must be >= 1, got {list(lengths)}")
    policy, weights = policy_from_checkpoint(checkpoint)
    metadata = {
        "checkpoint": str(checkpoint),
        "policy_config": json.dumps(asdict(weights.config)),
        "checkpoint_metadata": json.dumps(weights.metadata),
        "log_std": repr(float(weights.arrays["log_std"])),
        "joint_order": "topological, parents before children (parents input)" if tree
        else "torso to tail (JointState message order)",
    }  # fmt: skip
    if weights.signed is not None:  # provenance: who signed the weights this graph was made from (docs/robustness.md)
        metadata["checkpoint_sha256"] = weights.data_sha256
        metadata["signed_weights"] = json.dumps(
            {"header": weights.signed.header, "signature": weights.signed.signature}
        )
    model = export_model(policy, with_value, metadata, tree)
    data = model.SerializeToString()
    error = check_against_policy(data, policy, lengths, tree=tree)
    if not error <= tolerance:
        raise ExportError(f"the exported graph differs from the policy by {error:.3g} (> {tolerance:g}); not written")
    atomic_write_bytes(out, data)
    width = policy.config.global_features
    return ExportResult(out, with_value, tree, tuple(lengths), error, len(model.graph.node), width)
