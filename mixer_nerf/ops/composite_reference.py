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
"""

from __future__ import annotations

import torch


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
        transmittance_end = torch.exp(-optical_depth[:, -1:]) if tau.shape[1] else torch.ones_like(color[:, :1])
        color = color + transmittance_end * background.to(compute)
    depth = (weights * 0.5 * (t_starts + t_ends)).sum(dim=1)
    return tuple(x.to(dtype) for x in (color, depth, opacity, weights))
