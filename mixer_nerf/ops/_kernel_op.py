"""What every kernel-backed op wrapper shares: calling a registered kernel (:class:`KernelOp`), and
the kernels' fake implementations (output shapes, for torch.compile and opcheck).

The fakes are registered once the extension has defined the ops:
:func:`~mixer_nerf.ops._dispatch.use_kernel` calls :func:`register_declared` when it picks a kernel.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch

_pending: list[Callable[[], None]] = []


def declare_fake(op: str, fake: Callable) -> None:
    """``fake(*inputs)`` returns empty outputs shaped like those of ``mixer_nerf::<op>``."""
    _pending.append(functools.partial(torch.library.register_fake, f"mixer_nerf::{op}", fake))


def register_declared() -> None:
    """Registers every fake declared and not registered yet; the ops must exist (extension loaded)."""
    while _pending:
        _pending.pop()()


class KernelOp:
    """The forward kernel ``mixer_nerf::<name>`` and the fake kernels of it and, if it has one, of its
    backward kernel ``backward``.

    Calling it runs the forward. An op with a backward kernel is differentiable as registered: its
    autograd is C++ (``csrc/autograd.cpp``), which makes the inputs contiguous, records the backward
    and calls the backward kernel, so no Python runs between the two. The inputs of the others, and
    of every op under inference mode (which skips autograd kernels), are made contiguous here.
    """

    def __init__(self, name: str, fake: Callable, backward: str | None = None, backward_fake: Callable | None = None):
        self.name, self.differentiable = name, backward is not None
        declare_fake(name, fake)
        if backward_fake is not None:
            declare_fake(backward, backward_fake)

    def __call__(self, *inputs):
        if not self.differentiable or torch.is_inference_mode_enabled():
            inputs = tuple(x.contiguous() if isinstance(x, torch.Tensor) else x for x in inputs)
        return getattr(torch.ops.mixer_nerf, self.name)(*inputs)
