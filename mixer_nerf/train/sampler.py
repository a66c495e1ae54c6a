"""Random training-ray batches drawn across every pixel of every training image."""

from __future__ import annotations

import torch

from ..data import Scene


class RaySampler:
    """Draws ``batch_rays`` pixels uniformly (with replacement) from all training images.

    Rays are made on the fly from the drawn pixels (``Scene.rays_at``), so nothing of size
    N*H*W beyond the images is ever stored; the images stay on the host and only the drawn pixels'
    colours travel to the scene's device (``Scene.colors_at``). The sampler owns its generator (on
    the scene's device, where the renderer draws its samples with it too); its state goes into
    every checkpoint so a resumed run draws the same batches.
    """

    def __init__(self, scene: Scene, batch_rays: int, seed: int) -> None:
        self.scene = scene
        self.batch_rays = batch_rays
        self.generator = torch.Generator(device=scene.device)
        self.generator.manual_seed(seed)
        self._pixels = scene.H * scene.W
        self._total = len(scene) * self._pixels

    def sample(self, count: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One batch: origins, dirs, target colours, each (count, 3) float32 (default count:
        ``batch_rays``)."""
        count = self.batch_rays if count is None else count
        flat = torch.randint(self._total, (count,), generator=self.generator, device=self.generator.device)
        image_idx, pixel_idx = flat // self._pixels, flat % self._pixels
        origins, dirs = self.scene.rays_at(image_idx, pixel_idx)
        return origins.float(), dirs.float(), self.scene.colors_at(image_idx, pixel_idx)
