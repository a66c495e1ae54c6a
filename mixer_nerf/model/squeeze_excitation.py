"""Squeeze-and-excitation over the samples of a ray, for dense and packed (ragged) layouts.

``s = sigmoid(W2 ReLU(W1 z))``, ``F' = s * F``, with ``W1`` reducing the ``C`` channels by
``reduction``. In an image network the squeeze ``z`` averages a feature map over its pixels; here
the spatial extent is the ray: ``z`` is the mean of the trunk features over the samples of each
ray, so every sample of a ray is gated by the same per-ray channel weights. ``per_point=True``
gates each sample by its own features instead (``z = F``).

Layouts:
  * dense ``(R, S, C)``: mean over ``S``;
  * packed ``(N, C)`` with CSR ``offsets (R+1,)`` (ray r owns rows ``offsets[r]:offsets[r+1]``,
    as ray marching packs them): the fused ops :func:`~mixer_nerf.ops.segment_mean` (squeeze)
    and :func:`~mixer_nerf.ops.ray_scale` (excitation), kernels with hand-written backwards that
    never materialise the (N, C) gather of the gate;
  * packed ``(N, C)`` with ``ray_indices (N,)``, rows in any order: segment mean (sum with
    ``index_add_`` over ``num_rays`` rays, divided by the samples per ray) and a gather of the
    gate; equal to the offsets path (and to the dense mean when every ray has the same samples);
  * ``(N, C)`` without ``offsets`` or ``ray_indices``: each point is its own ray (per-point gating).
"""

from __future__ import annotations

import torch
from torch import nn

from ..ops import ray_scale, segment_mean
from ..ops._checks import check_backend


def mean_over_ray_indices(values: torch.Tensor, ray_indices: torch.Tensor, num_rays: int) -> torch.Tensor:
    """Mean of ``values (N, C)`` over the rows of each ray -> ``(num_rays, C)``, accumulated in
    float32 or better; rays without samples get 0."""
    acc = torch.promote_types(values.dtype, torch.float32)
    ray_indices = ray_indices.long()
    sums = values.new_zeros(num_rays, values.shape[-1], dtype=acc).index_add_(0, ray_indices, values.to(acc))
    counts = torch.bincount(ray_indices, minlength=num_rays).clamp_min_(1)
    return sums / counts.unsqueeze(-1).to(acc)


class SqueezeExcitation(nn.Module):
    """Channel gating of per-sample features by a squeeze over each ray (see module docstring).

    Args:
        channels: ``C``.
        reduction: ``r``; the bottleneck has ``C // r`` channels.
        per_point: gate each sample by its own features instead of its ray's mean.
        backend: of the fused packed ops (``"auto"``, ``"kernel"`` or ``"torch"``, see
            :mod:`mixer_nerf.ops`); used only with ``offsets``.
    """

    def __init__(
        self, channels: int, reduction: int = 16, per_point: bool = False, backend: str = "auto"
    ) -> None:
        super().__init__()
        hidden = channels // reduction
        if hidden < 1:
            raise ValueError(f"reduction {reduction} leaves no channels of {channels}")
        check_backend(backend)
        self.per_point = per_point
        self.backend = backend
        self.reduce = nn.Linear(channels, hidden)
        self.expand = nn.Linear(hidden, channels)
        nn.init.kaiming_normal_(self.reduce.weight, nonlinearity="relu")
        nn.init.zeros_(self.reduce.bias)
        nn.init.xavier_uniform_(self.expand.weight)
        nn.init.zeros_(self.expand.bias)

    def forward(
        self,
        features: torch.Tensor,
        ray_indices: torch.Tensor | None = None,
        num_rays: int | None = None,
        offsets: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """features ``(R, S, C)``, or packed ``(N, C)`` with either CSR ``offsets (R+1,)`` int64
        (the fused path, taken when both are given) or ``ray_indices (N,)`` int64 and ``num_rays``
        (default ``ray_indices.max() + 1``, which synchronises on a GPU) -> same shape.

        ``offsets`` are trusted like ``ray_indices`` (their values are not checked: that would
        synchronise on a GPU); the kernels clamp them, so bad ones never reach outside the arrays.
        """
        if self.per_point:
            return self.gate(features) * features
        if offsets is not None:
            squeezed = segment_mean(features, offsets, backend=self.backend, check_values=False)
            scale = self.gate(squeezed).to(features.dtype)
            return ray_scale(features, scale, offsets, backend=self.backend, check_values=False)
        if ray_indices is not None:
            if num_rays is None:
                num_rays = int(ray_indices.max()) + 1 if ray_indices.numel() else 0
            squeezed = mean_over_ray_indices(features, ray_indices, num_rays).to(features.dtype)
            return self.gate(squeezed)[ray_indices] * features
        if features.dim() == 3:
            acc = torch.promote_types(features.dtype, torch.float32)
            # squeezed (R, C) rather than (R, 1, C): the gate's linears then dispatch no reshapes
            squeezed = features.mean(dim=1, dtype=acc).to(features.dtype)
            return self.gate(squeezed).unsqueeze(1) * features
        return self.gate(features) * features

    def gate(self, squeezed: torch.Tensor) -> torch.Tensor:
        """``sigmoid(W2 ReLU(W1 z))`` for squeezed features ``(..., C)``."""
        return torch.sigmoid(self.expand(torch.relu(self.reduce(squeezed))))
