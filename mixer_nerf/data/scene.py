"""A loaded scene split (images + cameras) and the rays it produces for training and rendering."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import torch

from .rays import camera_rays, ndc_rays, pixel_rays

NDC_NEAR = 1.0
"""Near plane that defines NDC space for forward-facing scenes, as in NeRF (LLFF poses are
rescaled so that the closest scene depth is ~1.33, beyond this plane)."""


@dataclass
class Scene:
    """One split of a scene.

    Attributes:
        images: (N, H, W, 3) float32 in [0, 1], already composited on ``background``.
        poses: (N, 4, 4) float32 camera-to-world, OpenGL convention (x right, y up, looks down -z).
        H, W, focal, cx, cy: image size, focal length and principal point in pixels.
        near, far: ray sampling range. For ``ndc`` scenes this is the NDC range (0, 1).
        bbox: (2, 3) axis-aligned box [min, max] holding the scene (in NDC when ``ndc``), or None.
        ndc: rays are warped to normalised device coordinates (forward-facing LLFF scenes).
        background: (3,) colour the images were composited on.
        name, split: scene name and split ("train", "val", "test", "all").
        image_paths: source file of each image.
    """

    images: torch.Tensor
    poses: torch.Tensor
    H: int
    W: int
    focal: float
    cx: float
    cy: float
    near: float
    far: float
    bbox: torch.Tensor | None = None
    ndc: bool = False
    background: torch.Tensor = field(default_factory=lambda: torch.ones(3))
    name: str = ""
    split: str = ""
    image_paths: list[Path] = field(default_factory=list)

    def __post_init__(self) -> None:
        n = self.images.shape[0]
        if self.images.shape != (n, self.H, self.W, 3):
            raise ValueError(f"images must be (N, {self.H}, {self.W}, 3), got {tuple(self.images.shape)}")
        if self.poses.shape != (n, 4, 4):
            raise ValueError(f"poses must be ({n}, 4, 4), got {tuple(self.poses.shape)}")
        if self.bbox is not None and self.bbox.shape != (2, 3):
            raise ValueError(f"bbox must be (2, 3), got {tuple(self.bbox.shape)}")

    def __len__(self) -> int:
        return self.images.shape[0]

    def to(self, device: torch.device | str) -> Scene:
        """A copy with every tensor on ``device``."""
        moved = {
            f.name: getattr(self, f.name).to(device)
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), torch.Tensor)
        }
        return dataclasses.replace(self, **moved)

    def rays_at(
        self, image_idx: torch.Tensor, pixel_idx: torch.Tensor, ndc: bool | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through arbitrary pixels, e.g. a random training batch.

        Args:
            image_idx: (M,) int64 image indices.
            pixel_idx: (M,) int64 flat pixel indices ``row * W + col``.
            ndc: warp to NDC; None follows ``self.ndc``. Pass False to get world-space rays (their
                normalised directions are the viewing directions, also for NDC scenes).

        Returns:
            origins, dirs: each (M, 3).
        """
        x = (pixel_idx % self.W).to(torch.float64) + 0.5
        y = torch.div(pixel_idx, self.W, rounding_mode="floor").to(torch.float64) + 0.5
        origins, dirs = pixel_rays(x, y, self.focal, self.poses[image_idx], self.cx, self.cy)
        return self._maybe_ndc(origins, dirs, ndc)

    def colors_at(self, image_idx: torch.Tensor, pixel_idx: torch.Tensor) -> torch.Tensor:
        """Target colours (M, 3) of the pixels addressed as in :meth:`rays_at`."""
        return self.images.reshape(len(self), self.H * self.W, 3)[image_idx, pixel_idx]

    def rays_for_image(self, i: int, ndc: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays of every pixel of image ``i``, row-major: origins, dirs each (H*W, 3)."""
        return self._flat_rays(self.poses[i], ndc)

    def all_rays(self, ndc: bool | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every ray of the split with its target colour, for training on shuffled rays.

        Returns:
            origins, dirs, rgb: each (N*H*W, 3), image-major then row-major (flat index
            ``(i * H + row) * W + col``), so ``rgb`` is ``images.reshape(-1, 3)``.
        """
        origins, dirs = self._flat_rays(self.poses, ndc)
        return origins, dirs, self.images.reshape(-1, 3)

    def _flat_rays(self, c2w: torch.Tensor, ndc: bool | None) -> tuple[torch.Tensor, torch.Tensor]:
        origins, dirs = camera_rays(self.H, self.W, self.focal, c2w, self.cx, self.cy)
        return self._maybe_ndc(origins.reshape(-1, 3), dirs.reshape(-1, 3), ndc)

    def _maybe_ndc(
        self, origins: torch.Tensor, dirs: torch.Tensor, ndc: bool | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if self.ndc if ndc is None else ndc:
            return ndc_rays(self.H, self.W, self.focal, NDC_NEAR, origins, dirs)
        return origins, dirs
