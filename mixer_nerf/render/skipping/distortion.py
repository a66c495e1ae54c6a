"""mip-NeRF 360's distortion loss (Barron et al. 2022, eq. 15), a regulariser of the proposal
sampler's main field against floaters: it is smallest when each ray's weight sits in one short
interval, so it pulls weight together and away from scattered, semi-transparent blobs.

For one ray with intervals ``[s_i, s_{i+1}]`` (midpoints ``m_i``) and weights ``w_i``::

    L = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_{i+1} - s_i)

The double sum is evaluated in O(N) with prefix sums: with sorted edges ``m_i >= m_j`` for
``j < i``, so it equals ``2 sum_i w_i (m_i W_{<i} - (wm)_{<i})`` where ``W_{<i}`` and
``(wm)_{<i}`` are exclusive cumulative sums of ``w`` and ``w m``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def interval_midpoints(loss: str, weights: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """``(R, N)`` midpoints of the intervals of ``edges (R, N + 1)``, after checking that they match
    ``weights (R, N)`` (shapes only: no device synchronisation); ``loss`` names the caller."""
    if weights.dim() != 2 or edges.shape != (weights.shape[0], weights.shape[1] + 1):
        raise ValueError(f"{loss} needs weights (R, N) and edges (R, N + 1), got "
                         f"{tuple(weights.shape)} and {tuple(edges.shape)}")
    return 0.5 * (edges[:, 1:] + edges[:, :-1])


def distortion_loss(weights: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Distortion loss of rays, averaged over them.

    Args:
        weights: ``(R, N)`` volume-rendering weights of each ray's intervals.
        edges: ``(R, N + 1)`` the intervals' edges in a normalised coordinate ``s`` in [0, 1] (the
            proposal sampler's spacing coordinate, not t), sorted along each ray.

    Returns:
        A scalar: the loss of each ray, mean over rays; differentiable in both inputs.

    Raises:
        ValueError: the shapes do not match (checked on shapes only: no device synchronisation).
    """
    mids = interval_midpoints("distortion_loss", weights, edges)
    widths = edges[:, 1:] - edges[:, :-1]
    weighted_mids = weights * mids
    # shifted inclusive sums rather than cumsum - self: exact zeros for the first interval
    w_before = F.pad(torch.cumsum(weights[:, :-1], dim=-1), (1, 0))
    wm_before = F.pad(torch.cumsum(weighted_mids[:, :-1], dim=-1), (1, 0))
    between = 2 * (weights * (mids * w_before - wm_before)).sum(dim=-1)
    within = (weights.square() * widths).sum(dim=-1) / 3
    return (between + within).mean()
