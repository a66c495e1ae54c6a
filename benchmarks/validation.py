"""Mean PSNR over every view of a validation split, for any renderer (ours, nerfacc's): shared by
``time_to_quality`` (its curves) and ``skip_report`` (its all-view means)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch

from mixer_nerf.metrics import psnr


@torch.no_grad()
def validate(render: Callable, val, chunk: int = 1 << 15, views: Sequence[int] | None = None) -> float:
    """Mean PSNR over ``views`` of a split (default: every view);
    ``render(rays_o (R, 3), rays_d (R, 3)) -> rgb (R, 3)``."""
    scores = []
    for i in range(len(val)) if views is None else views:
        rays_o, rays_d = val.rays_for_image(i)
        chunks = range(0, len(rays_o), chunk)
        rgb = torch.cat([render(rays_o[j:j + chunk], rays_d[j:j + chunk]) for j in chunks])
        scores.append(psnr(rgb.reshape(val.H, val.W, 3).clamp(0, 1), val.image(i)).item())
    return sum(scores) / len(scores)
