"""NeRF's fine-pass depths: ``hierarchical_samples`` draws fine depths from the PDF of the coarse
pass (:func:`~mixer_nerf.ops.sample_pdf`'s formulation) and merges them with the coarse depths.
The reference path is :mod:`mixer_nerf.ops.hierarchical_samples_reference`."""

from __future__ import annotations

import torch

from ._checks import (
    check_alike,
    check_floating,
    check_int,
    check_ndim,
    check_nonnegative,
    check_shape,
    check_sorted,
    check_tensor,
    in_range_message,
    nonnegative_message,
    sorted_message,
)
from . import deferred_checks
from ._dispatch import use_kernel
from ._kernel_op import KernelOp
from .hierarchical_samples_reference import hierarchical_samples_reference
from .sample_pdf import check_generator, check_weight_padding, sample_positions


def hierarchical_samples(
    z_coarse: torch.Tensor,
    weights_coarse: torch.Tensor,
    num_fine: int,
    deterministic: bool = False,
    u: torch.Tensor | None = None,
    weight_padding: float = 0.0,
    generator: torch.Generator | None = None,
    backend: str = "auto",
    check_values: bool = True,
) -> torch.Tensor:
    """NeRF's fine-pass depths: the coarse depths and ``num_fine`` new ones, merged and sorted.

    As in NeRF, the fine samples are drawn from the PDF whose bins are the midpoints of
    ``z_coarse`` (S-1 edges) and whose weights are ``weights_coarse[:, 1:-1]`` (S-2 bins), then
    merged with ``z_coarse`` in one pass (the kernels do not sort). No gradient flows: NeRF
    detaches the fine depths, so the result never requires grad. A ray with a NaN weight gets its
    NaN fine depths after its coarse ones, as ``torch.sort`` puts NaN last.

    Stratified positions (the default) are drawn by the kernel itself: on the CPU from the stream
    ``torch.rand`` draws (so the reference path with the same generator gives the same samples),
    on CUDA by Philox inside the one launch (graph-safe; a stream of its own, so the two paths
    then agree in distribution, not sample for sample).

    Args:
        z_coarse: (R, S) sorted coarse depths, S >= 3.
        weights_coarse: (R, S) non-negative compositing weights of the coarse samples.
        num_fine: N >= 0 fine samples per ray.
        deterministic, u, weight_padding, generator, backend: as in
            :func:`~mixer_nerf.ops.sample_pdf` (``u`` is (R, N) or (N,)).
        check_values: check that ``z_coarse`` and ``u`` are sorted, ``weights_coarse >= 0`` and
            ``u`` in [0, 1]: on the CPU before the kernel, on a GPU in the kernel without a host
            synchronisation (a bad value raises at a later call or at
            :func:`~mixer_nerf.ops.check_pending`, as for :func:`~mixer_nerf.ops.composite`).

    Returns:
        (R, S + N) sorted depths in the dtype of ``z_coarse``.
    """
    kernel = use_kernel(backend, check_tensor("z_coarse", z_coarse).device)
    deferred = check_values and deferred_checks.in_kernel(kernel, z_coarse)
    _validate(z_coarse, weights_coarse, check_values and not deferred)
    check_int("num_fine", num_fine)
    pad = check_weight_padding(weight_padding)
    z_coarse, weights_coarse = z_coarse.detach(), weights_coarse.detach()
    if kernel and u is None and not deterministic:  # the kernel draws the stratified positions itself
        check_generator(generator, z_coarse)
        merged, invalid = _HIERARCHICAL_STRATIFIED(z_coarse, weights_coarse, num_fine, generator, pad)
    else:
        positions = sample_positions("z_coarse", z_coarse, num_fine, deterministic, u, generator,
                                     check_values and not deferred)
        if not kernel:
            return hierarchical_samples_reference(z_coarse, weights_coarse, positions, pad)
        merged, invalid = _HIERARCHICAL_SAMPLES(z_coarse, weights_coarse, positions, pad)
    if deferred:
        deferred_checks.watch(invalid, "hierarchical_samples", INVALID_INPUT)
    return merged


INVALID_INPUT = {
    1: nonnegative_message("weights_coarse"),
    2: sorted_message("z_coarse"),
    4: in_range_message("u", 0.0, 1.0),
    8: sorted_message("u"),
}
"""The kernels' ``invalid`` bits (``InvalidInput`` in csrc/sample_pdf.h) and what each says."""


def _validate(z_coarse: torch.Tensor, weights_coarse: torch.Tensor, check_values: bool) -> None:
    check_floating("z_coarse", z_coarse)
    check_floating("weights_coarse", weights_coarse)
    check_ndim("z_coarse", z_coarse, 2)
    if z_coarse.shape[1] < 3:
        raise ValueError(f"z_coarse must have at least 3 samples per ray, got shape {tuple(z_coarse.shape)}")
    check_shape("weights_coarse", weights_coarse, tuple(z_coarse.shape), " (like z_coarse)")
    check_alike(z_coarse=z_coarse, weights_coarse=weights_coarse)
    if check_values:
        check_sorted("z_coarse", z_coarse)
        check_nonnegative("weights_coarse", weights_coarse)


def _hierarchical_samples_fwd_fake(z_coarse, weights, u, weight_padding):
    return (z_coarse.new_empty(z_coarse.shape[0], z_coarse.shape[1] + u.shape[-1]),
            z_coarse.new_empty(1, dtype=torch.int32))


def _hierarchical_stratified_fwd_fake(z_coarse, weights, num_samples, generator, weight_padding):
    return _hierarchical_samples_fwd_fake(z_coarse, weights, z_coarse.new_empty(num_samples), weight_padding)


_HIERARCHICAL_SAMPLES = KernelOp("hierarchical_samples_fwd", _hierarchical_samples_fwd_fake)
_HIERARCHICAL_STRATIFIED = KernelOp("hierarchical_samples_stratified_fwd", _hierarchical_stratified_fwd_fake)
