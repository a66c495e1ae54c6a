"""Pure-PyTorch reference of inverse-CDF sampling (what ``backend="torch"`` runs).

The formulation is exactly the one the C++/CUDA kernels evaluate and differentiate by hand, so
autograd through this file gives the kernels' gradients:

  w_i  = weights_i + weight_padding, 0 if below the smallest normal number of the accumulation
         dtype (subnormal weights are flushed: 1 / w_k stays finite; NaN stays NaN)   (R, B)
  C_k  = w_0 + ... + w_{k-1},  W = C_B                    (unnormalised CDF, C_0 = 0)
  v    = u * W                                            (u in [0, 1], sorted)
  k    = #{j in 1..B-1 : C_j < v}                         (the bin with C_k < v <= C_{k+1})
  t    = clamp((v - C_k) / w_k, 0, 1)    if w_k > 0, else 0
  s    = min(b_k + t * (b_{k+1} - b_k), b_{k+1})

This is the quantile function Q(u) = inf{x : F(x) >= u} of the piecewise-constant PDF w / W:
bins of zero weight are never sampled (u = 0 with leading zero-weight bins gives b_0, u = 1 gives
the right edge of the last bin with weight), and a zero-width bin gives its edge. Working with the
unnormalised CDF divides by the bin's own weight, never by a difference of CDF values, so no
epsilon is needed. ``t`` only leaves [0, 1] and ``s`` only passes b_{k+1}
by rounding; the clamps keep every sample inside its bin, hence sorted and within
[b_0, b_B], and since they only undo rounding they are transparent to gradients (straight
through): a sample whose t rounds to 1 gets the same gradient as its neighbours.
The kernels carry C, v and t in float64 (see csrc/sample_pdf_math.h), so they are at least as
accurate as this float32 path; the formulas are the same.

A ray whose weights are all 0 (after flushing), or whose total overflows, has no PDF: it samples
uniformly, s = min(b_0 + u (b_B - b_0), b_B), and its weights get zero gradient. A ray with a
NaN weight (so W is NaN) samples NaN, and every weight and edge of it gets a NaN gradient; other
rays are untouched.

Half and bfloat16 inputs are computed in float32 and the result cast back, like the kernels.
"""

from __future__ import annotations

import torch


def accumulation_dtype(dtype: torch.dtype) -> torch.dtype:
    """float64 stays float64; every other floating dtype accumulates in float32."""
    return torch.float64 if dtype == torch.float64 else torch.float32


def sample_pdf_reference(
    bins: torch.Tensor, weights: torch.Tensor, u: torch.Tensor, weight_padding: float = 0.0
) -> torch.Tensor:
    """bins (R, B+1) sorted, weights (R, B) >= 0, u (R, N) or (N,) sorted in [0, 1] -> (R, N)."""
    acc = accumulation_dtype(bins.dtype)
    finfo = torch.finfo(acc)
    edges = bins.to(acc)
    raw = weights.to(acc)
    w = raw + weight_padding
    w = torch.where(w < finfo.tiny, torch.zeros_like(w), w)  # NaN stays NaN
    num_rays, num_bins = w.shape
    u = u.to(acc).expand(num_rays, u.shape[-1])

    cdf = torch.cat([w.new_zeros(num_rays, 1), torch.cumsum(w, dim=-1)], dim=-1)  # (R, B+1)
    total = cdf[:, -1:]
    nan_ray = torch.isnan(total)  # (R, 1): a NaN weight, NaN samples and gradients
    empty = (total < finfo.tiny) | (total > finfo.max)  # (R, 1): no PDF, sample [b_0, b_B] uniformly
    # Empty rays take the other branch of the where()s below, NaN rays the last one; keep this
    # one finite for both (a NaN or inf there would turn the empty rays' zero gradients into NaN).
    v = u * torch.where(empty | nan_ray, torch.ones_like(total), total)
    # side="left" counts the interior CDF values strictly below v.
    k = torch.searchsorted(cdf[:, 1:-1].contiguous(), v.detach(), side="left")  # (R, N) in [0, B-1]

    w_k = torch.gather(w, 1, k)
    has_weight = (w_k > 0) & ~empty
    t = (v - torch.gather(cdf, 1, k)) / torch.where(has_weight, w_k, torch.ones_like(w_k))
    t = torch.where(has_weight, _straight_through(t.clamp(0.0, 1.0), t), torch.zeros_like(t))
    lo = torch.gather(edges, 1, k)
    hi = torch.gather(edges, 1, k + 1)

    t = torch.where(empty, u, t)
    lo = torch.where(empty, edges[:, :1], lo)
    hi = torch.where(empty, edges[:, -1:], hi)
    samples = lo + t * (hi - lo)
    samples = _straight_through(torch.minimum(samples, hi), samples)
    # NaN rays: NaN, with a NaN gradient for every weight and edge of the ray (the factor is
    # their NaN total). Other rays get a zero gradient through it, times a finite factor 1.
    factor = torch.where(nan_ray, total, torch.ones_like(total)).detach()
    carrier = (raw.sum(-1, keepdim=True) + edges.sum(-1, keepdim=True)) * factor
    samples = torch.where(nan_ray, carrier, samples)
    return samples.to(bins.dtype)


def sample_pdf_packed_reference(
    bins: torch.Tensor,
    weights: torch.Tensor,
    offsets: torch.Tensor,
    u: torch.Tensor,
    weight_padding: float = 0.0,
) -> torch.Tensor:
    """Packed bins (``sample_pdf_packed``): ray r has B_r = offsets[r+1] - offsets[r] bins with
    weights (N,) from offsets[r] and B_r + 1 edges (N + R,) from offsets[r] + r; u (R, S) or (S,)
    -> (R, S).

    Pads every ray to the longest one (at least one bin) and runs :func:`sample_pdf_reference`:
    the padding bins repeat the ray's last edge and weigh exactly 0 (``weight_padding`` is added
    to the real bins only, here), so they are never sampled and do not change the CDF; a ray
    without bins gets weights all 0 and samples its single edge. Costs a host sync (the longest
    ray): a reference, not a fast path.
    """
    acc = accumulation_dtype(bins.dtype)
    counts = offsets[1:] - offsets[:-1]
    num_rays = counts.numel()
    width = max(int(counts.max()) if num_rays else 0, 1)
    slots = torch.arange(width + 1, device=bins.device)
    first_edge = offsets[:-1] + torch.arange(num_rays, device=bins.device)
    edges = bins[first_edge[:, None] + torch.minimum(slots, counts[:, None])]  # (R, width + 1)
    real = slots[:width] < counts[:, None]
    slot_weight = torch.cat([weights.to(acc) + weight_padding, weights.new_zeros(1, dtype=acc)])
    w_index = torch.where(real, offsets[:-1, None] + slots[:width], weights.shape[0])  # the 0 past the end
    padded_weights = torch.where(real, slot_weight[w_index], torch.zeros((), dtype=acc, device=bins.device))
    return sample_pdf_reference(edges, padded_weights, u, 0.0)


def _straight_through(value: torch.Tensor, carrier: torch.Tensor) -> torch.Tensor:
    """Exactly ``value``, with the gradient of ``carrier`` (adding carrier - carrier is exactly 0)."""
    return value.detach() + (carrier - carrier.detach())

