"""A module's parameters and their gradients as views into one flat vector each.

The optimizer and the gradient-norm clip then see one parameter vector
theta, as PPO is written, and cost a few operations per step instead of a few
per parameter tensor (30 of them here); for a network this small that
per-tensor overhead was about a tenth of a minibatch step. The update
differentiates its loss as a function of theta itself (``views``,
``algo.learner.minibatch_gradient``) and copies that gradient into the flat
buffer; autograd on the module (``backward()``) adds into an existing
``.grad`` in place, so its gradients land in the flat buffer too.

The trap: ``optimizer.zero_grad()`` and ``module.zero_grad()`` set gradients
to None by default. Backward would then write into fresh tensors outside the
buffer, and the optimizer would step on a stale or missing gradient without a
word. ``FlatParameters.zero_grad`` clears the buffer in place, and
``guard`` makes an optimizer's step fail loudly if the buffer was cut loose.
"""

from __future__ import annotations

import torch
from torch import nn


class FlatGradientError(RuntimeError):
    """The gradients no longer live in the flat buffer (e.g. set to None by a ``zero_grad()``)."""


class FlatParameters:
    """``module``'s parameters moved into one flat Parameter ``theta``; they become views of it."""

    def __init__(self, module: nn.Module):
        self.names = [name for name, _ in module.named_parameters()]
        self.params = list(module.parameters())
        self.theta = nn.Parameter(torch.cat([p.detach().flatten() for p in self.params]))
        self.grad = torch.zeros_like(self.theta)
        self.theta.grad = self.grad
        data, grads = self.views(self.theta.data).values(), self.views(self.grad).values()
        for p, view, grad in zip(self.params, data, grads, strict=True):
            p.data, p.grad = view, grad
        self._grad_views = [p.grad for p in self.params]

    def views(self, theta: torch.Tensor) -> dict[str, torch.Tensor]:
        """Parameter name -> its view into ``theta`` (a flat vector laid out as ``self.theta``), for
        ``torch.func.functional_call``: a function of the parameters as one vector has one gradient."""
        views, offset = {}, 0
        for name, p in zip(self.names, self.params, strict=True):
            views[name] = theta[offset : offset + p.numel()].view(p.shape)
            offset += p.numel()
        return views

    def zero_grad(self) -> None:
        """Clear every gradient in place (the only safe way to clear them)."""
        self.grad.zero_()

    def clip_grad_norm_(self, max_norm: float) -> torch.Tensor:
        """Scale the gradient to norm <= ``max_norm``; its norm before. The same numbers as
        ``torch.nn.utils.clip_grad_norm_(theta, max_norm)`` (the norm of the one tensor's norm, then
        the clamped factor), without that function's per-call grouping of tensors by device and dtype."""
        norm = torch.linalg.vector_norm(torch.linalg.vector_norm(self.grad).reshape(1))
        self.grad.mul_(torch.clamp(max_norm / (norm + 1e-6), max=1.0))
        return norm

    def optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """``optimizer.step()``; for a fused Adam on ``theta`` alone, its kernel called directly.

        ``torch.optim.Adam(fused=True)`` steps one tensor with two calls (``_foreach_add_`` on the step
        count, then ``_fused_adam_``); around them its ``step()`` spent ~70 µs per call of Python
        wrappers in a process that also runs compiled code, against ~55 µs for the kernel itself, in a
        minibatch step of ~2 ms (docs/benchmarks.md). Here the same two calls on the same state give the
        same numbers bit for bit (``test_param_buffer``). Any other optimizer or setting, and the first
        step (which creates the state), go through ``optimizer.step()``.
        """
        state = optimizer.state.get(self.theta)
        group = optimizer.param_groups[0]
        direct = (
            state is not None
            and type(optimizer) is torch.optim.Adam
            and len(optimizer.param_groups) == 1
            and len(group["params"]) == 1
            and group["params"][0] is self.theta
            and group["fused"]
            and not (group["amsgrad"] or group["maximize"] or group["differentiable"] or group["capturable"])
            and not group.get("decoupled_weight_decay", False)
            and not isinstance(group["lr"], torch.Tensor)
        )
        if not direct:
            optimizer.step()
            return
        self.check()  # what ``guard`` checks before each of the optimizer's steps
        beta1, beta2 = group["betas"]
        with torch.no_grad():
            torch._foreach_add_([state["step"]], 1)
            torch._fused_adam_(
                [self.theta], [self.grad], [state["exp_avg"]], [state["exp_avg_sq"]], [], [state["step"]],
                amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"],
                eps=group["eps"], maximize=False, grad_scale=None, found_inf=None,
            )  # fmt: skip

    def check(self) -> None:
        """Raise ``FlatGradientError`` unless every gradient is still its view into the buffer."""
        cut = self.theta.grad is not self.grad or any(
            p.grad is not view for p, view in zip(self.params, self._grad_views, strict=True)
        )
        if cut:
            raise FlatGradientError(
                "gradients were detached from the flat parameter buffer (a zero_grad() that sets them to "
                "None?): clear them with FlatParameters.zero_grad(), which zeroes the buffer in place"
            )

    def guard(self, optimizer: torch.optim.Optimizer) -> torch.optim.Optimizer:
        """Check the buffer before each of ``optimizer``'s steps; returns the optimizer."""
        optimizer.register_step_pre_hook(lambda _opt, _args, _kwargs: self.check())
        return optimizer
