"""Volume rendering: composite per-sample densities and colours along rays into pixels.

Definitions (transmittance as exp of an exclusive cumsum, weights via expm1) are in
:mod:`mixer_nerf.ops.composite_reference`; the kernels compute the same quantities in their
stable closed forms (``opacity = -expm1(-sum tau)``, ``1 - opacity = exp(-sum tau)``) and a
hand-written O(S)-per-ray backward that stays exact when transmittance underflows or the last
interval is 1e10 long (see ``csrc/composite.cpp``).

:func:`composite` takes S samples per ray, padded ``(R, S)``; :func:`composite_packed` takes
rays with different numbers of samples, packed ``(N,)`` with CSR offsets ``(R+1,)`` as
:func:`~mixer_nerf.ops.ray_marching` produces them. Both run the same per-ray scans.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ._checks import (
    check_alike,
    check_floating,
    check_ndim,
    check_nonnegative,
    check_offsets,
    check_same_device,
    check_shape,
    check_tensor,
    has_descent,
    nonnegative_message,
)
from . import deferred_checks
from ._dispatch import use_kernel
from ._kernel_op import KernelOp
from .composite_reference import composite_packed_reference, composite_reference


class CompositeResult(NamedTuple):
    color: torch.Tensor  # (R, C)
    depth: torch.Tensor  # (R,) unnormalised expected depth: sum_i w_i (t_start_i + t_end_i) / 2
    opacity: torch.Tensor  # (R,) sum_i w_i
    weights: torch.Tensor  # (R, S), or (N,) for packed samples


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
        check_values: check ``sigmas >= 0`` and ``t_ends >= t_starts``. On the CPU (and on the
            reference path) before the op runs; on a GPU the kernel checks the values it reads
            without a host synchronisation, and a bad one raises ValueError at a later call or at
            :func:`~mixer_nerf.ops.check_pending` (``deferred_checks``). False skips the checks.

    Returns:
        :class:`CompositeResult` (color (R, C), depth (R,), opacity (R,), weights (R, S)), all
        differentiable with respect to every input.
    """
    kernel = use_kernel(backend, check_tensor("sigmas", sigmas).device)
    deferred = check_values and deferred_checks.in_kernel(kernel, sigmas)
    _validate(sigmas, rgbs, t_starts, t_ends, background, check_values and not deferred)
    if not kernel:
        return CompositeResult(*composite_reference(sigmas, rgbs, t_starts, t_ends, background))
    *result, _chunk_transmittances, invalid = _COMPOSITE(sigmas, rgbs, t_starts, t_ends, background)
    if deferred:
        deferred_checks.watch(invalid, "composite", INVALID_INPUT)
    return CompositeResult(*result)


def composite_packed(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    offsets: torch.Tensor,
    background: torch.Tensor | None = None,
    backend: str = "auto",
    check_values: bool = True,
) -> CompositeResult:
    """Render rays from packed (ragged) samples: ray r owns rows ``offsets[r]:offsets[r+1]``.

    Args:
        sigmas: (N,) non-negative densities.
        rgbs: (N, C) per-sample colours (any C >= 1).
        t_starts, t_ends: (N,) interval bounds, ``t_ends >= t_starts``, in order along each ray.
        offsets: (R+1,) int64, non-decreasing from 0 to N; a ray with no sample (equal offsets)
            renders opacity 0, depth 0 and colour = background (0 without one).
        background: optional (C,) or (R, C) colour seen through the unoccupied fraction.
        backend: ``"auto"``, ``"kernel"`` or ``"torch"`` (see :mod:`mixer_nerf.ops`).
        check_values: also check ``sigmas >= 0``, ``t_ends >= t_starts`` and the values of
            ``offsets``, as :func:`composite` does (on a GPU in the kernel, reported later). The
            kernels clamp unchecked offsets into [0, N] and run the first ray from 0 and the last
            to N, so they never reach outside the arrays and write every output row.

    Returns:
        :class:`CompositeResult` (color (R, C), depth (R,), opacity (R,), weights (N,)),
        differentiable with respect to sigmas, rgbs, t_starts, t_ends and background.
    """
    kernel = use_kernel(backend, check_tensor("sigmas", sigmas).device)
    deferred = check_values and deferred_checks.in_kernel(kernel, sigmas)
    _validate_packed(sigmas, rgbs, t_starts, t_ends, offsets, background, check_values and not deferred)
    if not kernel:
        return CompositeResult(
            *composite_packed_reference(sigmas, rgbs, t_starts, t_ends, offsets, background)
        )
    *result, _chunk_transmittances, invalid = _COMPOSITE_PACKED(sigmas, rgbs, t_starts, t_ends, background, offsets)
    if deferred:
        deferred_checks.watch(invalid, "composite_packed", INVALID_INPUT)
    return CompositeResult(*result)


INTERVALS_MESSAGE = "t_ends must be >= t_starts everywhere (intervals of non-negative length)"

INVALID_INPUT = {
    1: nonnegative_message("sigmas"),
    2: INTERVALS_MESSAGE,
    4: "offsets must start at 0, end at N (the number of samples) and be non-decreasing",
}
"""The kernels' ``invalid`` bits (``InvalidInput`` in csrc/composite.h) and what each says."""



def _validate(sigmas, rgbs, t_starts, t_ends, background, check_values: bool) -> None:
    _check_dtypes(sigmas, rgbs, t_starts, t_ends, background)
    check_ndim("sigmas", sigmas, 2)
    check_ndim("rgbs", rgbs, 3)
    R, S, C = rgbs.shape
    if sigmas.shape != (R, S):
        raise ValueError(f"sigmas must have shape (R, S) = {(R, S)} to match rgbs, got {tuple(sigmas.shape)}")
    _check_samples(sigmas, rgbs, t_starts, t_ends, background, R, check_values)


def _validate_packed(sigmas, rgbs, t_starts, t_ends, offsets, background, check_values: bool) -> None:
    _check_dtypes(sigmas, rgbs, t_starts, t_ends, background)
    check_ndim("sigmas", sigmas, 1)
    check_ndim("rgbs", rgbs, 2)
    N = rgbs.shape[0]
    if sigmas.shape != (N,):
        raise ValueError(f"sigmas must have shape (N,) = {(N,)} to match rgbs, got {tuple(sigmas.shape)}")
    check_same_device(sigmas=sigmas, offsets=check_tensor("offsets", offsets))
    R = check_offsets("offsets", offsets, N, check_values)
    _check_samples(sigmas, rgbs, t_starts, t_ends, background, R, check_values)


def _check_dtypes(sigmas, rgbs, t_starts, t_ends, background) -> None:
    for name, t in (("sigmas", sigmas), ("rgbs", rgbs), ("t_starts", t_starts), ("t_ends", t_ends)):
        check_floating(name, t)
    if background is not None:
        check_floating("background", background)


def _check_samples(sigmas, rgbs, t_starts, t_ends, background, num_rays: int, check_values: bool) -> None:
    """Checks both layouts share once sigmas (samples) and rgbs (*samples, C) agree."""
    C = rgbs.shape[-1]
    if C < 1:
        raise ValueError(f"rgbs must have at least one channel, got shape {tuple(rgbs.shape)}")
    check_shape("t_starts", t_starts, tuple(sigmas.shape), " (like sigmas)")
    check_shape("t_ends", t_ends, tuple(sigmas.shape), " (like sigmas)")
    if background is not None:
        check_ndim("background", background, (1, 2))
        check_shape(
            "background", background, (C,) if background.dim() == 1 else (num_rays, C), " (C) or (R, C)"
        )
    check_alike(sigmas=sigmas, rgbs=rgbs, t_starts=t_starts, t_ends=t_ends, background=background)
    if check_values:
        check_nonnegative("sigmas", sigmas)
        if has_descent(t_starts, t_ends):
            raise ValueError(INTERVALS_MESSAGE)


_CUDA_CHUNK = 32
"""Samples per chunk of the CUDA backward (``kBackwardChunk`` in csrc/cuda/composite.cu)."""


def _chunk_transmittance_entries(sigmas: torch.Tensor, num_rays: int) -> int:
    """How many transmittances the forward keeps for the backward: one per chunk of each ray on a
    GPU (at most ``N // chunk + R``), none on the CPU, whose backward finds them itself."""
    return sigmas.numel() // _CUDA_CHUNK + num_rays if sigmas.device.type == "cuda" else 0


def _composite_fwd_fake(sigmas, rgbs, t_starts, t_ends, background, *layout):
    num_rays = layout[0].shape[0] - 1 if layout else sigmas.shape[0]
    return (
        sigmas.new_empty(num_rays, rgbs.shape[-1]),
        sigmas.new_empty(num_rays),
        sigmas.new_empty(num_rays),
        torch.empty_like(sigmas),
        sigmas.new_empty(_chunk_transmittance_entries(sigmas, num_rays), dtype=torch.float64),
        sigmas.new_empty(1, dtype=torch.int32),
    )


def _composite_bwd_fake(
    grad_color,
    grad_depth,
    grad_opacity,
    grad_weights,
    sigmas,
    rgbs,
    t_starts,
    t_ends,
    background,
    *layout_transmittances_and_flags,
):
    interval_grads, background_grad = layout_transmittances_and_flags[-2:]
    grad_t_starts = torch.empty_like(t_starts) if interval_grads else None
    grad_t_ends = torch.empty_like(t_ends) if interval_grads else None
    grad_background = torch.empty_like(background) if background is not None and background_grad else None
    return torch.empty_like(sigmas), torch.empty_like(rgbs), grad_t_starts, grad_t_ends, grad_background


_COMPOSITE = KernelOp("composite_fwd", _composite_fwd_fake, "composite_bwd", _composite_bwd_fake)
_COMPOSITE_PACKED = KernelOp("composite_packed_fwd", _composite_fwd_fake, "composite_packed_bwd", _composite_bwd_fake)
