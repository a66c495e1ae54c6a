"""Volume rendering: composite per-sample densities and colours along rays into pixels.

Definitions (transmittance as exp of an exclusive cumsum, weights via expm1) are in
:mod:`mixer_nerf.ops.composite_reference`; the kernels compute the same quantities in their
stable closed forms (``opacity = -expm1(-sum tau)``, ``1 - opacity = exp(-sum tau)``) and a
hand-written O(S)-per-ray backward that stays exact when transmittance underflows or the last
interval is 1e10 long (see ``csrc/composite.cpp``).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import torch
from torch.autograd.function import once_differentiable

from ._checks import (
    check_floating,
    check_ndim,
    check_nonnegative,
    check_same_device,
    check_same_dtype,
    check_shape,
)
from ._dispatch import use_kernel
from .composite_reference import composite_reference


class CompositeResult(NamedTuple):
    color: torch.Tensor  # (R, C)
    depth: torch.Tensor  # (R,) unnormalised expected depth: sum_i w_i (t_start_i + t_end_i) / 2
    opacity: torch.Tensor  # (R,) sum_i w_i
    weights: torch.Tensor  # (R, S)


def composite(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    check_values: bool = True,
) -> CompositeResult:
    """Render rays from S samples each.

    Args:
        sigmas: (R, S) non-negative densities.
        rgbs: (R, S, C) per-sample colours (any C >= 1).
        t_starts, t_ends: (R, S) interval bounds along each ray, ``t_ends >= t_starts``.
        background: optional (C,) or (R, C) colour seen through the unoccupied fraction.
        backend: ``"auto"``, ``"kernel"`` or ``"torch"`` (see :mod:`mixer_nerf.ops`).
        check_values: check ``sigmas >= 0`` and ``t_ends >= t_starts``. Each check reads its
            tensors once more and, on a GPU, synchronises with the host; pass False on hot paths
            whose inputs are valid by construction (e.g. softplus densities, sorted samples).

    Returns:
        :class:`CompositeResult` (color (R, C), depth (R,), opacity (R,), weights (R, S)), all
        differentiable with respect to every input.
    """
    _validate(sigmas, rgbs, t_starts, t_ends, background, check_values)
    if not use_kernel(backend, sigmas.device):
        return CompositeResult(*composite_reference(sigmas, rgbs, t_starts, t_ends, background))
    _register_fakes()
    tensors = [None if x is None else x.contiguous() for x in (sigmas, rgbs, t_starts, t_ends, background)]
    if torch.is_grad_enabled() and any(x is not None and x.requires_grad for x in tensors):
        return CompositeResult(*_CompositeFunction.apply(*tensors))
    return CompositeResult(*torch.ops.mixer_nerf.composite_fwd(*tensors))  # inference: no autograd bookkeeping


def _validate(sigmas, rgbs, t_starts, t_ends, background, check_values: bool) -> None:
    for name, t in (("sigmas", sigmas), ("rgbs", rgbs), ("t_starts", t_starts), ("t_ends", t_ends)):
        check_floating(name, t)
    if background is not None:
        check_floating("background", background)
    check_ndim("sigmas", sigmas, 2)
    check_ndim("rgbs", rgbs, 3)
    R, S, C = rgbs.shape
    if sigmas.shape != (R, S):
        raise ValueError(f"sigmas must have shape (R, S) = {(R, S)} to match rgbs, got {tuple(sigmas.shape)}")
    if C < 1:
        raise ValueError(f"rgbs must have at least one channel, got shape {tuple(rgbs.shape)}")
    check_shape("t_starts", t_starts, (R, S), " (like sigmas)")
    check_shape("t_ends", t_ends, (R, S), " (like sigmas)")
    if background is not None:
        check_ndim("background", background, (1, 2))
        check_shape("background", background, (C,) if background.dim() == 1 else (R, C), " (C) or (R, C)")
    check_same_device(sigmas=sigmas, rgbs=rgbs, t_starts=t_starts, t_ends=t_ends, background=background)
    check_same_dtype(sigmas=sigmas, rgbs=rgbs, t_starts=t_starts, t_ends=t_ends, background=background)
    if check_values:
        check_nonnegative("sigmas", sigmas)
        if t_ends.numel() and bool((t_ends < t_starts).any()):
            raise ValueError("t_ends must be >= t_starts everywhere (intervals of non-negative length)")


class _CompositeFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sigmas, rgbs, t_starts, t_ends, background):
        outputs = torch.ops.mixer_nerf.composite_fwd(sigmas, rgbs, t_starts, t_ends, background)
        ctx.save_for_backward(sigmas, rgbs, t_starts, t_ends, background)
        ctx.set_materialize_grads(False)  # unused outputs arrive as None: the kernel reads no zeros
        return outputs

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_color, grad_depth, grad_opacity, grad_weights):
        sigmas, rgbs, t_starts, t_ends, background = ctx.saved_tensors
        upstream = [None if g is None else g.contiguous() for g in (grad_color, grad_depth, grad_opacity, grad_weights)]
        interval_grads = ctx.needs_input_grad[2] or ctx.needs_input_grad[3]
        grad_sigmas, grad_rgbs, grad_t_starts, grad_t_ends, grad_background = torch.ops.mixer_nerf.composite_bwd(
            *upstream, sigmas, rgbs, t_starts, t_ends, background, interval_grads
        )
        return grad_sigmas, grad_rgbs, grad_t_starts, grad_t_ends, grad_background


@functools.cache
def _register_fakes() -> None:
    """Shape functions for torch.compile and opcheck; the ops exist only once the extension loaded."""
    torch.library.register_fake("mixer_nerf::composite_fwd", _composite_fwd_fake)
    torch.library.register_fake("mixer_nerf::composite_bwd", _composite_bwd_fake)


def _composite_fwd_fake(sigmas, rgbs, t_starts, t_ends, background):
    R, S, C = rgbs.shape
    return sigmas.new_empty(R, C), sigmas.new_empty(R), sigmas.new_empty(R), sigmas.new_empty(R, S)


def _composite_bwd_fake(
    grad_color, grad_depth, grad_opacity, grad_weights, sigmas, rgbs, t_starts, t_ends, background, interval_grads
):
    grad_t_starts = torch.empty_like(t_starts) if interval_grads else None
    grad_t_ends = torch.empty_like(t_ends) if interval_grads else None
    grad_background = None if background is None else torch.empty_like(background)
    return torch.empty_like(sigmas), torch.empty_like(rgbs), grad_t_starts, grad_t_ends, grad_background
