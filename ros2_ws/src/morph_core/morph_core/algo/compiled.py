"""The update step as one Inductor graph, called directly; eager mode where it cannot be compiled.

The network is small enough that eager PyTorch spends most of a minibatch
step on per-operation overhead; compiled (forward and backward one graph,
fused by Inductor) the step is ~1.9x faster (bench/bench_policy.py).
``torch.compile`` adds ~270 µs of its own to every call (dynamo's frame entry
and guards, AOTAutograd's wrappers: ~22% of a 128-sample part gradient), so
the function is traced here instead, once per layout of its arguments, into
one graph of ATen operations with symbolic sizes (``make_fx``), compiled by
Inductor and called with the arguments' tensors. The same graph and kernels
as ``torch.compile`` makes of it, so the same numbers bit for bit.

What dynamo's guards check, ``_Graph.fits`` checks: the layout (nesting,
constants, each tensor's dtype, rank and contiguity) by a key, and the
relations between sizes the trace assumed (e.g. that no size is 0 or 1, that
the batch sizes agree) by the shape guards the trace recorded. A call that
fits no graph so far is traced anew, up to ``MAX_GRAPHS`` layouts. Compiling
costs ~15-30 s once per layout per process (less with Inductor's on-disk
cache) and needs a C++ compiler: without one, the first call fails, and
training goes on eagerly after a warning.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from typing import Any

import torch

MAX_GRAPHS = 8
"""layouts compiled per function; calls that fit none of them run eagerly"""


def compiled(fn: Callable, enabled: bool = True, eager: Callable | None = None) -> Callable:
    """``fn`` traced and compiled once per argument layout (sizes symbolic: chain mixes vary per minibatch);
    when not ``enabled`` or when compiling fails, ``eager`` (the same computation in a form that runs faster
    uncompiled) or ``fn``. Arguments are tensors, constants (None, bool, int, float, str) and tuples, lists,
    dicts and dataclasses of them; the result is tensors in such containers. Tensors ``fn`` reads other than
    through its arguments enter the graph as constants (the update passes all parameters as ``theta``; the
    policy has no buffers)."""
    eager = fn if eager is None else eager
    if not enabled:
        return eager
    graphs: list[_Graph] = []
    warned = False

    def call(*args, **kwargs):
        nonlocal warned
        if call.fell_back:
            return eager(*args, **kwargs)
        leaves: list = []
        key = _flatten((args, kwargs), leaves)
        for graph in graphs:
            if graph.fits(key, leaves):
                return graph(leaves)
        if len(graphs) >= MAX_GRAPHS:
            if not warned:
                warnings.warn(f"{MAX_GRAPHS} argument layouts compiled; calls that fit none of them run eagerly",
                              stacklevel=2)  # fmt: skip
                warned = True
            return eager(*args, **kwargs)
        try:
            graph = _Graph.trace(fn, key, leaves)
            result = graph(leaves)
        except Exception as err:  # e.g. no C++ compiler: Inductor fails on compiling
            warnings.warn(f"compiling failed, training goes on in eager mode: {err}", stacklevel=2)
            call.fell_back = True
            return eager(*args, **kwargs)
        graphs.append(graph)
        return result

    call.fell_back = False
    call.graphs = graphs
    call.__wrapped__ = fn  # what is compiled, e.g. for benchmarking it through torch.compile instead
    return call


@dataclasses.dataclass
class _Graph:
    """One compiled graph: the layout it was traced for, the size relations it assumes, its kernels."""

    key: Any
    shape_guards: Any
    """the trace's size assumptions as compiled Python over ``L['t<i>']`` (the i-th tensor), or None"""
    run: Callable
    out_key: Any
    names: tuple[str, ...]
    """``t<i>`` for each tensor: its name in ``shape_guards``"""
    interp: dict
    """the functions ``shape_guards`` calls (imported with the tracer, not at start-up)"""

    @classmethod
    def trace(cls, fn: Callable, key, leaves: list) -> _Graph:
        import torch._inductor  # Inductor and the tracer load when a graph is traced, not at start-up
        from torch._guards import detect_fake_mode
        from torch.fx.experimental.proxy_tensor import make_fx
        from torch.fx.experimental.symbolic_shapes import SYMPY_INTERP

        out_keys = []

        def flat_fn(*tensors):
            args, kwargs = _unflatten(key, iter(tensors))
            out: list = []
            out_keys.append(_flatten(fn(*args, **kwargs), out))
            return tuple(out)

        gm = make_fx(flat_fn, tracing_mode="symbolic")(*leaves)
        fakes = [node.meta["val"] for node in gm.graph.nodes if node.op == "placeholder"]
        shape_env = detect_fake_mode(fakes).shape_env
        # ignore_static=False: also the sizes the trace fixed (a dimension of 1, a feature width)
        code = shape_env.produce_guards_expression(fakes, ignore_static=False)
        shape_guards = compile(code, "<shape guards>", "eval") if code else None
        run = torch._inductor.compile(gm, list(leaves), options={"cpp_wrapper": True})
        names = tuple(f"t{i}" for i in range(len(leaves)))
        return cls(key, shape_guards, run, out_keys[-1], names, SYMPY_INTERP)

    def fits(self, key, leaves: list) -> bool:
        if key != self.key:
            return False
        if self.shape_guards is None:
            return True
        return bool(eval(self.shape_guards, self.interp, {"L": dict(zip(self.names, leaves, strict=True))}))

    def __call__(self, leaves: list):
        return _unflatten(self.out_key, iter(self.run(*leaves)))


_CONSTANTS = (type(None), bool, int, float, str)
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}
"""each dataclass's field names, looked up once per class (``dataclasses.fields`` on every call cost ~0.5 us a
dataclass, and the minibatch is two of them)"""


def _flatten(obj, leaves: list):
    """``obj``'s layout as a hashable key; appends its tensors to ``leaves`` in order."""
    if isinstance(obj, torch.Tensor):
        leaves.append(obj)
        return (torch.Tensor, obj.dtype, obj.dim(), obj.is_contiguous(), obj.requires_grad)
    if isinstance(obj, _CONSTANTS):
        return (type(obj), obj)  # the type too: True and 1 are equal keys otherwise
    if isinstance(obj, (tuple, list)):
        return (type(obj), tuple(_flatten(item, leaves) for item in obj))
    if isinstance(obj, dict):
        return (dict, tuple((k, _flatten(v, leaves)) for k, v in obj.items()))
    names = _FIELD_NAMES.get(type(obj))
    if names is None:
        if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
            raise TypeError(f"cannot compile over a {type(obj).__name__} argument")
        names = _FIELD_NAMES[type(obj)] = tuple(f.name for f in dataclasses.fields(obj))
    return (type(obj), tuple((name, _flatten(getattr(obj, name), leaves)) for name in names))


def _unflatten(key, tensors):
    """The object ``_flatten`` made ``key`` of, with the next of ``tensors`` in place of each tensor."""
    kind, *rest = key
    if kind is torch.Tensor:
        return next(tensors)
    if kind in (tuple, list):
        return kind(_unflatten(item, tensors) for item in rest[0])
    if kind is dict:
        return {k: _unflatten(v, tensors) for k, v in rest[0]}
    if kind in _CONSTANTS:
        return rest[0]
    obj = object.__new__(kind)  # a dataclass: its fields set as they were, __post_init__ not run again
    for name, item in rest[0]:
        object.__setattr__(obj, name, _unflatten(item, tensors))
    return obj
