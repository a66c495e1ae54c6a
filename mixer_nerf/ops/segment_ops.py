"""Per-ray segment mean and per-ray channel scale of packed rows: the squeeze and the excitation of
squeeze-and-excitation (:class:`~mixer_nerf.model.SqueezeExcitation`) on ragged rays.

Rows are packed ``(N, C)`` with CSR offsets ``(R+1,)`` as :func:`~mixer_nerf.ops.ray_marching`
produces them: ray r owns rows ``offsets[r]:offsets[r+1]``. Definitions are in
:mod:`mixer_nerf.ops.segment_ops_reference`; the kernels (``csrc/segment_ops.cpp``,
``csrc/cuda/segment_ops.cu``) compute them with hand-written backwards that walk each ray's rows
(deterministic, no atomics):

    segment_mean:  d values_i = grad_{ray(i)} / n_{ray(i)}
    ray_scale:     d features_i = grad_i * scale_{ray(i)},  d scale_r = sum_{i in r} grad_i * features_i
"""

from __future__ import annotations

import torch

from ._checks import (
    check_alike,
    check_floating,
    check_ndim,
    check_offsets,
    check_same_device,
    check_shape,
    check_tensor,
)
from . import deferred_checks
from ._dispatch import use_kernel
from ._kernel_op import KernelOp
from .segment_ops_reference import ray_scale_reference, segment_mean_reference


def segment_mean(
    values: torch.Tensor, offsets: torch.Tensor, backend: str = "auto", check_values: bool = True
) -> torch.Tensor:
    """Mean of each ray's rows.

    Args:
        values: (N, C) floating rows (half/bfloat16 are summed in float32).
        offsets: (R+1,) int64, non-decreasing from 0 to N.
        backend: ``"auto"``, ``"kernel"`` or ``"torch"`` (see :mod:`mixer_nerf.ops`).
        check_values: also check the values of ``offsets``: on the CPU (and on the reference
            path) before the op runs; on a GPU the kernel checks the offsets it reads without a host
            synchronisation, and bad ones raise ValueError at a later call or at
            :func:`~mixer_nerf.ops.check_pending` (``deferred_checks``). False skips the checks
            (where they hold by construction). The kernels clamp unchecked offsets into [0, N] and
            run the first ray from 0 and the last to N, so they never reach outside the arrays and
            write every row.

    Returns:
        (R, C) in values' dtype, 0 for a ray with no row; differentiable with respect to values.
    """
    _check_rows("values", values)
    _, kernel, deferred = _check_offsets(offsets, "values", values, backend, check_values)
    if not kernel:
        return segment_mean_reference(values, offsets)
    mean, invalid = _SEGMENT_MEAN(values, offsets)
    if deferred:
        deferred_checks.watch(invalid, "segment_mean", INVALID_INPUT)
    return mean


def ray_scale(
    features: torch.Tensor,
    scale: torch.Tensor,
    offsets: torch.Tensor,
    backend: str = "auto",
    check_values: bool = True,
) -> torch.Tensor:
    """Every row times its ray's scale: ``out[i] = features[i] * scale[ray(i)]``.

    Args:
        features: (N, C) floating rows.
        scale: (R, C) in features' dtype, else a TypeError (the (N, C) output keeps features'
            dtype: cast a float32 gate to bfloat16 features' dtype first, as SE does).
        offsets: (R+1,) int64, non-decreasing from 0 to N.
        backend, check_values: as for :func:`segment_mean`.

    Returns:
        (N, C) in features' dtype, differentiable with respect to features and scale.
    """
    _check_rows("features", features)
    num_rays, kernel, deferred = _check_offsets(offsets, "features", features, backend, check_values)
    check_floating("scale", scale)
    check_alike(features=features, scale=scale)
    check_shape("scale", scale, (num_rays, features.shape[1]), " (R, C)")
    if not kernel:
        return ray_scale_reference(features, scale, offsets)
    out, invalid = _RAY_SCALE(features, scale, offsets)
    if deferred:
        deferred_checks.watch(invalid, "ray_scale", INVALID_INPUT)
    return out


def _check_rows(name: str, rows: torch.Tensor) -> None:
    check_floating(name, rows)
    check_ndim(name, rows, 2)
    if rows.shape[1] < 1:
        raise ValueError(f"{name} must have at least one channel, got shape {tuple(rows.shape)}")


def _check_offsets(
    offsets: torch.Tensor, name: str, rows: torch.Tensor, backend: str, check_values: bool
) -> tuple[int, bool, bool]:
    """Returns R, whether the kernel runs, and whether it checks the offsets' values (on a GPU,
    without a sync) in place of this check."""
    check_same_device(**{name: rows, "offsets": check_tensor("offsets", offsets)})
    kernel = use_kernel(backend, rows.device)
    deferred = check_values and deferred_checks.in_kernel(kernel, rows)
    return check_offsets("offsets", offsets, rows.shape[0], check_values and not deferred), kernel, deferred


INVALID_INPUT = {4: "offsets must start at 0, end at N (the number of rows) and be non-decreasing"}
"""The forward kernels' ``invalid`` bit (``InvalidInput`` in csrc/segment_ops.h) and what it says."""


def _invalid_fake(like):
    return like.new_empty(1, dtype=torch.int32)


def _segment_mean_fwd_fake(values, offsets):
    return values.new_empty(offsets.shape[0] - 1, values.shape[1]), _invalid_fake(values)


def _segment_mean_bwd_fake(grad, offsets, num_rows):
    return grad.new_empty(num_rows, grad.shape[1])


def _ray_scale_fwd_fake(features, scale, offsets):
    return torch.empty_like(features), _invalid_fake(features)


def _ray_scale_bwd_fake(grad_out, features, scale, offsets):
    return torch.empty_like(features), torch.empty_like(scale)


_SEGMENT_MEAN = KernelOp("segment_mean_fwd", _segment_mean_fwd_fake, "segment_mean_bwd", _segment_mean_bwd_fake)
_RAY_SCALE = KernelOp("ray_scale_fwd", _ray_scale_fwd_fake, "ray_scale_bwd", _ray_scale_bwd_fake)
