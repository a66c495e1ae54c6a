"""Pure-PyTorch volume rendering (``composite(..., backend="torch")``); autograd gives its gradients.

The definitions the kernels must match (per ray, samples i = 0..S-1):

    delta_i = t_end_i - t_start_i,   tau_i = sigma_i * delta_i
    T_i     = exp(-sum_{j<i} tau_j)           transmittance: exp of an exclusive cumsum
    alpha_i = -expm1(-tau_i)                   = 1 - exp(-tau_i), accurate for tiny tau
    w_i     = T_i * alpha_i                    weights
    opacity = sum_i w_i
    color   = sum_i w_i rgb_i + (1 - opacity) * background,  1 - opacity = exp(-sum_i tau_i)
    depth   = sum_i w_i (t_start_i + t_end_i) / 2

``depth`` is the unnormalised expected depth (divide by ``opacity`` for the depth of the surface
given a hit). ``w_i = T_i * alpha_i`` rather than ``T_i - T_{i+1}``: the difference cancels
catastrophically when tau_i is small, the product keeps full relative accuracy for any tau_i
(tiny, or 1e18 from the 1e10-long last interval). Half/bfloat16 inputs are computed in float32.

Packed (ragged) rays, ``composite_packed(..., backend="torch")``, are padded to (R, max samples)
with empty intervals (tau = 0: weight 0, transmittance unchanged) and go through the same
definitions; a ray with no sample has opacity 0, depth 0 and the background as its colour.
"""

from __future__ import annotations

import torch

from .segment_ops_reference import ray_of_rows


def composite_reference(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    background: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """sigmas, t_starts, t_ends (R, S); rgbs (R, S, C); background (C) or (R, C) or None
    -> color (R, C), depth (R), opacity (R), weights (R, S), in the inputs' dtype."""
    dtype = sigmas.dtype
    compute = torch.promote_types(dtype, torch.float32)
    sigmas, rgbs, t_starts, t_ends = (x.to(compute) for x in (sigmas, rgbs, t_starts, t_ends))

    tau = sigmas * (t_ends - t_starts)
    optical_depth = torch.cumsum(tau, dim=1)  # after each sample
    # Exclusive by shifting (not optical_depth - tau, which cancels after a huge tau).
    before = torch.cat([torch.zeros_like(tau[:, :1]), optical_depth[:, :-1]], dim=1)
    weights = torch.exp(-before) * -torch.expm1(-tau)

    opacity = weights.sum(dim=1)
    color = (weights.unsqueeze(-1) * rgbs).sum(dim=1)
    if background is not None:
        # 1 - opacity, as the transmittance past the last sample: the same number, but accurate
        # when opacity rounds to 1 (1 - sum w would keep no digit of a 1e-15 transmittance).
        transmittance_end = (
            torch.exp(-optical_depth[:, -1:]) if tau.shape[1] else torch.ones_like(color[:, :1])
        )
        color = color + transmittance_end * background.to(compute)
    depth = (weights * 0.5 * (t_starts + t_ends)).sum(dim=1)
    return tuple(x.to(dtype) for x in (color, depth, opacity, weights))


def composite_packed_reference(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    t_starts: torch.Tensor,
    t_ends: torch.Tensor,
    offsets: torch.Tensor,
    background: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """sigmas, t_starts, t_ends (N); rgbs (N, C); offsets (R+1) int64 (ray r owns rows
    offsets[r]:offsets[r+1]); background (C) or (R, C) or None
    -> color (R, C), depth (R), opacity (R), weights (N).

    A segmented cumsum over the flat samples would need each ray's start subtracted, which
    cancels catastrophically after a huge tau in an earlier ray; padding keeps every ray's sums
    its own. Costs a host sync (the longest ray) and R x max-samples memory: a reference, not a
    fast path.
    """
    counts = offsets[1:] - offsets[:-1]
    num_rays, num_samples = counts.numel(), sigmas.shape[0]
    width = int(counts.max()) if num_rays and num_samples else 0
    ray = ray_of_rows(offsets, num_samples)
    slot = torch.arange(num_samples, device=offsets.device) - offsets[ray]

    def padded(x: torch.Tensor) -> torch.Tensor:
        return x.new_zeros(num_rays, width, *x.shape[1:]).index_put((ray, slot), x)

    color, depth, opacity, weights = composite_reference(
        padded(sigmas), padded(rgbs), padded(t_starts), padded(t_ends), background
    )
    return color, depth, opacity, weights[ray, slot]
