"""What every kernel-backed op wrapper shares: calling a registered kernel with its hand-written
backward (:class:`KernelOp`), and the kernels' fake implementations (output shapes, for
torch.compile and opcheck).

The fakes are registered once the extension has defined the ops:
:func:`~mixer_nerf.ops._dispatch.use_kernel` calls :func:`register_declared` when it picks a kernel.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from torch.autograd.function import once_differentiable

_pending: list[Callable[[], None]] = []


def declare_fake(op: str, fake: Callable) -> None:
    """``fake(*inputs)`` returns empty outputs shaped like those of ``mixer_nerf::<op>``."""
    _pending.append(functools.partial(torch.library.register_fake, f"mixer_nerf::{op}", fake))


def register_declared() -> None:
    """Registers every fake declared and not registered yet; the ops must exist (extension loaded)."""
    while _pending:
        _pending.pop()()


def _no_flags(needs_input_grad: tuple[bool, ...]) -> tuple:
    return ()


class KernelOp:
    """The forward kernel ``mixer_nerf::<name>`` and, if it has one, its backward kernel.

    Calling it runs the forward on contiguous inputs; when an input requires grad, through an
    autograd node whose backward (differentiable once) calls the backward kernel as
    ``backward(*grads, *inputs, *flags(needs_input_grad))`` (``needs_input_grad``: one bool per
    input). That returns the gradients of the leading inputs; the others get none. Gradients of
    unused outputs arrive as None (a kernel reads no zeros), so a backward kernel of an op with
    several outputs takes them as ``Tensor?``. An op whose backward kernel takes other arguments
    overrides :meth:`save` and :meth:`backward`. The last ``aux_outputs`` outputs are not
    differentiable: a kernel's findings about its inputs (integer; see ``deferred_checks``) or
    random positions it drew. The backward kernel takes no gradient for them.
    """

    def __init__(
        self,
        name: str,
        fake: Callable,
        backward: str | None = None,
        backward_fake: Callable | None = None,
        flags: Callable[[tuple[bool, ...]], tuple] = _no_flags,
        aux_outputs: int = 0,
    ):
        self.name, self.backward_name, self.flags = name, backward, flags
        self.aux_outputs = aux_outputs
        declare_fake(name, fake)
        if backward_fake is not None:
            declare_fake(backward, backward_fake)

    def __call__(self, *inputs):
        inputs = tuple(x.contiguous() if isinstance(x, torch.Tensor) else x for x in inputs)
        if self.backward_name is not None and torch.is_grad_enabled() and _any_requires_grad(inputs):
            return _KernelFunction.apply(self, *inputs)
        return getattr(torch.ops.mixer_nerf, self.name)(*inputs)  # no autograd bookkeeping

    def save(self, ctx, inputs: tuple, outputs: tuple | torch.Tensor) -> None:
        """Keeps every input for :meth:`backward`: tensors saved for backward, the rest (numbers,
        absent optional tensors) on ``ctx``. The outputs are there for ops whose backward needs one."""
        ctx.tensor_slots = [i for i, x in enumerate(inputs) if isinstance(x, torch.Tensor)]
        ctx.inputs = [None if isinstance(x, torch.Tensor) else x for x in inputs]
        ctx.save_for_backward(*(inputs[i] for i in ctx.tensor_slots))
        ctx.set_materialize_grads(False)

    def backward(self, ctx, *grads) -> tuple:
        """One gradient (or None) per input."""
        grads = grads[: len(grads) - self.aux_outputs]
        if all(g is None for g in grads):
            return (None,) * len(ctx.inputs)
        inputs = list(ctx.inputs)
        for slot, tensor in zip(ctx.tensor_slots, ctx.saved_tensors):
            inputs[slot] = tensor
        upstream = (None if g is None else g.contiguous() for g in grads)
        kernel = getattr(torch.ops.mixer_nerf, self.backward_name)
        input_grads = kernel(*upstream, *inputs, *self.flags(ctx.needs_input_grad[1:]))
        if not isinstance(input_grads, tuple):
            input_grads = (input_grads,)
        return *input_grads, *[None] * (len(inputs) - len(input_grads))


def _any_requires_grad(inputs: tuple) -> bool:
    return any(isinstance(x, torch.Tensor) and x.requires_grad for x in inputs)


class _KernelFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, op: KernelOp, *inputs):
        ctx.op = op
        outputs = getattr(torch.ops.mixer_nerf, op.name)(*inputs)
        op.save(ctx, inputs, outputs)
        if op.aux_outputs:
            ctx.mark_non_differentiable(*outputs[-op.aux_outputs :])
        return outputs

    @staticmethod
    @once_differentiable
    def backward(ctx, *grads):
        return None, *ctx.op.backward(ctx, *grads)
