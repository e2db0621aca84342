"""torch.compile for the update step, falling back to eager mode where it cannot run.

The network is small enough that eager PyTorch spends most of a minibatch
step on per-operation overhead; compiled (forward and backward one graph,
fused by Inductor) the step is ~1.9x faster (bench/bench_policy.py). Compiling
costs ~30 s once per process (28 s measured with an empty cache, 2026-12-03;
less with Inductor's on-disk cache) and needs a C++
compiler: without one, the first call fails, and training goes on eagerly
after a warning.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable


def compiled(fn: Callable, enabled: bool = True, eager: Callable | None = None) -> Callable:
    """``fn`` compiled with dynamic shapes (chain mixes vary per minibatch); when not ``enabled`` or when
    compiling fails, ``eager`` (the same computation in a form that runs faster uncompiled) or ``fn``."""
    eager = fn if eager is None else eager
    if not enabled:
        return eager
    import torch

    # Inductor's C++ wrapper calls the kernels without its generated Python (buffer allocations, tensor
    # reinterpretations): a minibatch step ~7% faster, the same kernels and so the same numbers.
    fast = torch.compile(fn, dynamic=True, options={"cpp_wrapper": True})
    first_call = True

    def call(*args, **kwargs):
        nonlocal fast, first_call
        if not first_call:
            return fast(*args, **kwargs)
        first_call = False
        try:
            return fast(*args, **kwargs)
        except Exception as err:  # e.g. no C++ compiler: Inductor fails on the first call only
            warnings.warn(f"torch.compile failed, training goes on in eager mode: {err}", stacklevel=2)
            fast = eager
            call.fell_back = True
            return eager(*args, **kwargs)

    call.fell_back = False
    return call
