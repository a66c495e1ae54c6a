"""Rendering many rays (whole images) in chunks, without gradients, in bounded memory: one
chunking loop for every sampler."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import NamedTuple

import torch
from torch import nn

from ..ops.deferred_checks import check_pending


class ImageResult(NamedTuple):
    color: torch.Tensor  # (..., 3)
    depth: torch.Tensor  # (...)
    opacity: torch.Tensor  # (...)


class ChunkResult(NamedTuple):
    """What rendering one chunk of rays gives: colour (R, 3), depth (R,), opacity (R,), and how
    many samples the field shaded and how many marching emitted (what a pre-pass evaluated)."""

    color: torch.Tensor
    depth: torch.Tensor
    opacity: torch.Tensor
    num_shaded: int
    num_marched: int


RENDER_SAMPLES = {"cpu": 1 << 18, "cuda": 1 << 22}
"""Default most samples one chunk shades, per device type (docs/training.md#memory)."""


def rays_per_chunk(max_samples: int, samples_per_ray: int, max_rays: int) -> int:
    """Rays per chunk such that a chunk shades at most ``max_samples`` samples whatever its rays
    hit, given the most samples one ray can take; at least 1, at most ``max_rays``. Chunks hold
    whole rays: a field may pool over a ray's samples (SE), so splitting one would change it."""
    for name, value in (("max_samples", max_samples), ("samples_per_ray", samples_per_ray), ("max_rays", max_rays)):
        if value < 1:
            raise ValueError(f"{name} must be positive, got {value}")
    return max(1, min(max_rays, max_samples // samples_per_ray))


RenderChunk = Callable[..., ChunkResult]
"""``render_chunk(rays_o (R, 3), rays_d (R, 3), **per_ray) -> ChunkResult``."""


@torch.no_grad()
def render_in_chunks(
    render_chunk: RenderChunk,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    chunk: int,
    per_ray: Mapping[str, torch.Tensor] | None = None,
) -> tuple[ImageResult, int, int]:
    """Render rays ``(N, 3)`` ``chunk`` at a time; ``per_ray`` tensors ``(N, ...)`` are sliced
    alongside. Only one chunk's samples are alive at a time; the results go into preallocated
    outputs. Returns the :class:`ImageResult` ``(N, ...)`` and the samples shaded and marched."""
    num_rays = rays_o.shape[0]
    color = rays_o.new_empty(num_rays, 3)
    depth, opacity = rays_o.new_empty(num_rays), rays_o.new_empty(num_rays)
    shaded = marched = 0
    for start in range(0, num_rays, chunk):
        part = slice(start, start + chunk)
        extra = {name: value[part] for name, value in (per_ray or {}).items()}
        out = render_chunk(rays_o[part], rays_d[part], **extra)
        color[part], depth[part], opacity[part] = out.color, out.depth, out.opacity
        shaded, marched = shaded + out.num_shaded, marched + out.num_marched
    check_pending()  # what the kernels found in the values on a GPU: raised once an image is done
    return ImageResult(color, depth, opacity), shaded, marched


class ImageRenderer:
    """Renders rays of trained fields in chunks with deterministic samples (no grad), whichever
    sampler ``render_chunk`` uses. ``module`` (the fields) is put in eval mode while rendering;
    rays are moved to ``device`` as float32."""

    def __init__(self, render_chunk: RenderChunk, module: nn.Module, device: torch.device, chunk: int) -> None:
        if chunk < 1:
            raise ValueError(f"chunk must be positive, got {chunk}")
        self.render_chunk, self.module, self.device, self.chunk = render_chunk, module, device, chunk

    def __call__(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> ImageResult:
        """color (R, 3), depth (R,), opacity (R,) of rays (R, 3)."""
        return self.render_counted(rays_o, rays_d)[0]

    def render_counted(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> tuple[ImageResult, int, int]:
        """As :meth:`__call__`, with the number of samples shaded and marched."""
        was_training = self.module.training
        self.module.eval()
        try:
            o = rays_o.to(self.device, torch.float32)
            d = rays_d.to(self.device, torch.float32)
            return render_in_chunks(self.render_chunk, o, d, self.chunk)
        finally:
            self.module.train(was_training)
