"""Inverse-CDF sampling of piecewise-constant PDFs along rays (NeRF's hierarchical sampling).

The exact formulation, shared by the kernels and the reference path, is documented in
:mod:`mixer_nerf.ops.sample_pdf_reference`. In short: the PDF of a ray is exactly
``weights / weights.sum()`` (``weight_padding``, 0 by default, is added to every weight first;
the original NeRF code adds 1e-5); samples are its quantile function at sorted ``u`` in [0, 1],
so they come out sorted and within ``[bins[:, 0], bins[:, -1]]``; bins of zero weight are never
sampled, and padded weights below the smallest normal number of the accumulation dtype
(float32, or float64 for float64 inputs) count as zero; a ray whose weights are then all zero,
or whose total overflows, samples uniformly between its first and last edge. A ray with a NaN
weight samples NaN, and all its weights and edges get NaN gradients (other rays are
untouched). Gradients with respect to the weights scale like (bin width) / (bin weight): exact,
and large where a sample falls in a light bin.

Positions ``u``:
  * explicit ``u``: ``(R, N)`` or ``(N,)`` shared by every ray, sorted, in [0, 1];
  * ``deterministic=True``: ``u_i = (i + 1/2) / N``, the midpoints of N equal strata. The
    endpoints 0 and 1 are excluded on purpose: they would put samples exactly on the support's
    boundary edges (where the coarse pass already samples), and the midpoints are the mean of
    the stratified sampler below, so deterministic and random runs estimate the same thing;
  * otherwise stratified: ``u_i = (i + xi_i) / N``, ``xi_i ~ U[0, 1)`` from ``generator`` —
    sorted by construction, no sort needed. With the kernels (the default backend) the op draws
    them itself, in the one call that samples: on the CPU from the stream ``torch.rand`` draws
    (so the reference path with an equally seeded generator gives the same samples), on CUDA by
    Philox inside the one kernel launch, from the state of ``generator`` (or of torch's default
    CUDA generator): the same seed gives the same samples, and a CUDA graph capturing the call
    draws afresh at every replay. That stream is not ``torch.rand``'s, so on CUDA the kernels and
    the reference path agree in distribution, not sample for sample. When ``bins`` or ``weights``
    require grad, the op also writes the positions it drew, ``(R, N)`` in the accumulation dtype,
    which the backward reads (they are not redrawn there); otherwise it writes only the samples.

Value checks (``check_values=True``, the default): on the CPU, on the reference path and for
given or deterministic positions they run before the op (on a GPU each costs a host
synchronisation). The default call on a GPU costs none: its kernel checks the values it reads
(``weights >= 0``, ``bins`` sorted within each ray, the packed ``offsets``) and a bad one raises
ValueError at a later call or at :func:`~mixer_nerf.ops.check_pending`
(:mod:`~mixer_nerf.ops.deferred_checks`).
"""

from __future__ import annotations

import math

import torch

from ._checks import (
    check_alike,
    check_floating,
    check_in_range,
    check_int,
    check_ndim,
    check_nonnegative,
    check_offsets,
    check_same_device,
    check_same_dtype,
    check_shape,
    check_sorted,
    check_tensor,
    has_descent,
    nonnegative_message,
    sorted_message,
)
from . import deferred_checks
from ._dispatch import use_kernel
from ._kernel_op import KernelOp
from .sample_pdf_reference import accumulation_dtype, sample_pdf_packed_reference, sample_pdf_reference


def sample_pdf(
    bins: torch.Tensor,
    weights: torch.Tensor,
    num_samples: int,
    deterministic: bool = False,
    u: torch.Tensor | None = None,
    weight_padding: float = 0.0,
    generator: torch.Generator | None = None,
    backend: str = "auto",
    check_values: bool = True,
) -> torch.Tensor:
    """Draw ``num_samples`` sorted samples per ray from the PDF given by bin edges and weights.

    Args:
        bins: (R, B+1) sorted bin edges, B >= 1.
        weights: (R, B) non-negative bin weights (any scale; need not sum to 1).
        num_samples: N >= 0 samples per ray.
        deterministic: use ``u_i = (i + 1/2) / N`` (see the module docstring).
        u: optional explicit positions, (R, N) or (N,), sorted, in [0, 1].
        weight_padding: non-negative constant added to every weight (0: the PDF is exactly
            ``weights / weights.sum()``).
        generator: random generator for the stratified positions (None: torch's default
            generator of the inputs' device).
        backend: ``"auto"``, ``"kernel"`` or ``"torch"`` (see :mod:`mixer_nerf.ops`).
        check_values: check that ``bins`` and ``u`` are sorted, ``weights >= 0`` and ``u`` in
            [0, 1]. The default call (stratified positions) on a GPU checks in its kernel, with
            no host synchronisation; otherwise each check reads its tensor once more before the
            op and, on a GPU, synchronises with the host (see the module docstring). False skips
            the checks.

    Returns:
        (R, N) samples in the dtype of ``bins``, sorted along each ray, differentiable with
        respect to ``bins`` and ``weights``.
    """
    kernel = use_kernel(backend, check_tensor("bins", bins).device)
    drawn = kernel and u is None and not deterministic  # the kernel draws the stratified positions
    deferred = drawn and check_values and deferred_checks.in_kernel(kernel, bins)
    _validate_pdf(bins, weights, check_values and not deferred)
    check_int("num_samples", num_samples)
    pad = check_weight_padding(weight_padding)
    if drawn:
        check_generator(generator, bins)
        keep = _needs_grad(bins, weights)
        samples, _, invalid = _SAMPLE_PDF_STRATIFIED(bins, weights, num_samples, generator, pad, keep)
        if deferred:
            deferred_checks.watch(invalid, "sample_pdf", INVALID_INPUT)
        return samples
    positions = sample_positions("bins", bins, num_samples, deterministic, u, generator, check_values)
    if not kernel:
        return sample_pdf_reference(bins, weights, positions, pad)
    return _SAMPLE_PDF(bins, weights, positions, pad)


def sample_pdf_packed(
    bins: torch.Tensor,
    weights: torch.Tensor,
    offsets: torch.Tensor,
    num_samples: int,
    deterministic: bool = False,
    u: torch.Tensor | None = None,
    weight_padding: float = 0.0,
    generator: torch.Generator | None = None,
    backend: str = "auto",
    check_values: bool = True,
) -> torch.Tensor:
    """:func:`sample_pdf` for rays with different numbers of bins, packed (CSR).

    Ray r has ``B_r = offsets[r+1] - offsets[r]`` bins: weights ``weights[offsets[r]:offsets[r+1]]``
    and the ``B_r + 1`` edges ``bins[offsets[r] + r : offsets[r+1] + r + 1]`` (each ray's edges
    follow the previous ray's, one more edge than bins per ray, so ``bins`` has ``N + R``
    entries). The samples are the same as :func:`sample_pdf` on each ray alone. A ray with no bin
    has one edge: all its samples are that edge (as for a ray whose weights are all zero, which
    samples its edges' range uniformly). From packed samples with contiguous intervals (the
    ``t_starts``/``t_ends`` of each ray abutting), a ray's edges are its ``t_starts`` and its last
    ``t_end``; samples that skipped empty space leave gaps, which are bins of weight 0.

    Args:
        bins: (N + R,) edges, sorted within each ray.
        weights: (N,) non-negative bin weights.
        offsets: (R+1,) int64, non-decreasing from 0 to N.
        num_samples, deterministic, u, weight_padding, generator, backend: as in
            :func:`sample_pdf` (``u`` is (R, S) or (S,)).
        check_values: also check the offsets' values and that each ray's edges are sorted (as
            :func:`sample_pdf` checks: in the kernel for the default call on a GPU, else before
            the op). The kernels clamp unchecked offsets into [0, N] (the first ray from 0, the
            last to N), so they never reach outside the arrays. On CUDA the kernels size shared
            memory by the longest ray (of those clamped offsets), which costs one host sync per
            call whatever ``check_values``: unlike :func:`sample_pdf`, a packed call cannot be
            captured in a CUDA graph.

    Returns:
        (R, num_samples) samples in the dtype of ``bins``, sorted along each ray, differentiable
        with respect to ``bins`` and ``weights``.
    """
    kernel = use_kernel(backend, check_tensor("bins", bins).device)
    drawn = kernel and u is None and not deterministic
    deferred = drawn and check_values and deferred_checks.in_kernel(kernel, bins)
    num_rays = _validate_packed(bins, weights, offsets, check_values and not deferred)
    check_int("num_samples", num_samples)
    pad = check_weight_padding(weight_padding)
    if drawn:
        check_generator(generator, bins)
        keep = _needs_grad(bins, weights)
        samples, _, invalid = _SAMPLE_PDF_PACKED_STRATIFIED(
            bins, weights, offsets, num_samples, generator, pad, keep
        )
        if deferred:
            deferred_checks.watch(invalid, "sample_pdf_packed", PACKED_INVALID_INPUT)
        return samples
    positions = sample_positions(
        "bins", bins, num_samples, deterministic, u, generator, check_values, num_rays
    )
    if not kernel:
        return sample_pdf_packed_reference(bins, weights, offsets, positions, pad)
    return _SAMPLE_PDF_PACKED(bins, weights, offsets, positions, pad)


def _validate_pdf(bins: torch.Tensor, weights: torch.Tensor, check_values: bool) -> None:
    check_floating("bins", bins)
    check_floating("weights", weights)
    check_ndim("bins", bins, 2)
    check_ndim("weights", weights, 2)
    num_rays, num_edges = bins.shape
    if num_edges < 2:
        raise ValueError(f"bins must have at least 2 edges per ray (one bin), got shape {tuple(bins.shape)}")
    check_shape("weights", weights, (num_rays, num_edges - 1), " (one weight per bin of bins)")
    check_alike(bins=bins, weights=weights)
    if check_values:
        check_sorted("bins", bins)
        check_nonnegative("weights", weights)


def _validate_packed(
    bins: torch.Tensor, weights: torch.Tensor, offsets: torch.Tensor, check_values: bool
) -> int:
    """Checks of sample_pdf_packed's inputs; returns the number of rays."""
    check_floating("bins", bins)
    check_floating("weights", weights)
    check_ndim("bins", bins, 1)
    check_ndim("weights", weights, 1)
    check_same_device(bins=bins, weights=weights, offsets=check_tensor("offsets", offsets))
    check_same_dtype(bins=bins, weights=weights)
    num_bins = weights.shape[0]
    num_rays = check_offsets("offsets", offsets, num_bins, check_values)
    check_shape("bins", bins, (num_bins + num_rays,), " (N + R: one more edge than bins per ray)")
    if check_values:
        check_nonnegative("weights", weights)
        # Sorted within rays: the steps from one ray's last edge to the next ray's first are free
        # (that last edge compared as -inf).
        previous = bins[:-1].clone()
        first_edges = offsets[1:-1] + torch.arange(1, max(num_rays, 1), device=offsets.device)
        previous[first_edges - 1] = -math.inf
        if has_descent(previous, bins[1:]):
            raise ValueError(PACKED_SORTED_MESSAGE)
    return num_rays


PACKED_SORTED_MESSAGE = "bins must be sorted (non-decreasing) within each ray"

INVALID_INPUT = {1: nonnegative_message("weights"), 2: sorted_message("bins")}
"""The stratified kernels' ``invalid`` bits (``InvalidInput`` in csrc/sample_pdf.h) and what each says."""

PACKED_INVALID_INPUT = {
    1: nonnegative_message("weights"),
    2: PACKED_SORTED_MESSAGE,
    16: "offsets must start at 0, end at N (the number of bins) and be non-decreasing",
}


def _needs_grad(bins: torch.Tensor, weights: torch.Tensor) -> bool:
    """Whether the call records a backward, which reads the positions drawn."""
    return torch.is_grad_enabled() and (bins.requires_grad or weights.requires_grad)


def check_weight_padding(weight_padding: float) -> float:
    """``weight_padding`` as a float, else an error naming it."""
    if isinstance(weight_padding, bool) or not isinstance(weight_padding, (int, float)):
        raise TypeError(f"weight_padding must be a float, got {type(weight_padding).__name__}")
    if not (math.isfinite(weight_padding) and weight_padding >= 0):
        raise ValueError(f"weight_padding must be finite and >= 0, got {weight_padding}")
    return float(weight_padding)


def sample_positions(
    like_name: str,
    like: torch.Tensor,
    num_samples: int,
    deterministic: bool,
    u: torch.Tensor | None,
    generator: torch.Generator | None,
    check_values: bool,
    num_rays: int | None = None,
) -> torch.Tensor:
    """The sorted positions in [0, 1] as the kernels take them: (N,) or (R, N), contiguous, in
    the accumulation dtype of ``like`` ((R, ...) unless ``num_rays`` says otherwise)."""
    num_rays = like.shape[0] if num_rays is None else num_rays
    acc = accumulation_dtype(like.dtype)
    if u is not None:
        if deterministic:
            raise ValueError("pass either u or deterministic=True, not both")
        check_floating("u", u)
        check_ndim("u", u, (1, 2))
        check_shape("u", u, (num_samples,) if u.dim() == 1 else (num_rays, num_samples), " (N,) or (R, N)")
        check_same_device(u=u, **{like_name: like})
        if check_values:
            check_in_range("u", u, 0.0, 1.0)
            check_sorted("u", u)
        return u.detach().to(acc).contiguous()
    strata = torch.arange(num_samples, device=like.device, dtype=acc)
    if deterministic:
        return (strata + 0.5) / num_samples
    check_generator(generator, like)
    jitter = torch.rand(num_rays, num_samples, generator=generator, device=like.device, dtype=acc)
    return (strata + jitter) / num_samples


def check_generator(generator: torch.Generator | None, like: torch.Tensor) -> None:
    """A generator (or None: the default one) of the device the inputs are on."""
    if generator is not None and generator.device.type != like.device.type:
        raise ValueError(f"generator is on {generator.device} but the inputs are on {like.device}")


def _sample_pdf_fwd_fake(bins, weights, u, weight_padding):
    return bins.new_empty(bins.shape[0], u.shape[-1])


def _sample_pdf_packed_fwd_fake(bins, weights, offsets, u, weight_padding):
    return bins.new_empty(offsets.shape[0] - 1, u.shape[-1])


def _sample_pdf_bwd_fake(grad_samples, bins, weights, *offsets_u_and_padding):
    return torch.empty_like(bins), torch.empty_like(weights)


def _stratified_fwd_fake(bins, weights, *offsets_and_draw):
    *offsets, num_samples, _generator, _weight_padding, keep_positions = offsets_and_draw
    num_rays = offsets[0].shape[0] - 1 if offsets else bins.shape[0]
    acc = accumulation_dtype(bins.dtype)
    return (bins.new_empty(num_rays, num_samples),
            bins.new_empty(num_rays, num_samples if keep_positions else 0, dtype=acc),
            bins.new_empty(1, dtype=torch.int32))


_SAMPLE_PDF = KernelOp("sample_pdf_fwd", _sample_pdf_fwd_fake, "sample_pdf_bwd", _sample_pdf_bwd_fake)
_SAMPLE_PDF_PACKED = KernelOp(
    "sample_pdf_packed_fwd", _sample_pdf_packed_fwd_fake, "sample_pdf_packed_bwd", _sample_pdf_bwd_fake
)
# Backward: the given-positions op's, on the positions drawn (kept where a backward is recorded).
_SAMPLE_PDF_STRATIFIED = KernelOp("sample_pdf_stratified_fwd", _stratified_fwd_fake, "sample_pdf_bwd")
_SAMPLE_PDF_PACKED_STRATIFIED = KernelOp("sample_pdf_packed_stratified_fwd", _stratified_fwd_fake, "sample_pdf_packed_bwd")
