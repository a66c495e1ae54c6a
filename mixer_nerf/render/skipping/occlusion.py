"""Occlusion regularisation of the proposal sampler's main field (after FreeNeRF, Yang et al. 2023):
the weight each ray puts in its first stretch, in front of the camera, where a floater can explain
one training view without the others seeing it. Its weight in the loss pulls that density out.
"""

from __future__ import annotations

import torch

from .distortion import interval_midpoints


def occlusion_loss(weights: torch.Tensor, edges: torch.Tensor, fraction: float) -> torch.Tensor:
    """Mean over rays of the weight of the intervals whose midpoint lies in the first ``fraction``
    of the ray.

    Args:
        weights: ``(R, N)`` volume-rendering weights of each ray's intervals.
        edges: ``(R, N + 1)`` their edges in the proposal sampler's spacing coordinate ``s`` in [0, 1].
        fraction: in (0, 1): the stretch of ``s`` counted as in front of the camera.

    Returns:
        A scalar in [0, 1], differentiable in ``weights``.
    """
    near = interval_midpoints("occlusion_loss", weights, edges) < fraction
    return (weights * near).sum(dim=-1).mean()
