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

    Images stay in host memory whatever device the scene is on (:meth:`to`), so that a capture
    larger than the GPU's memory trains: only the pixels of a batch travel (:meth:`colors_at`),
    and whole views for validation one at a time (:meth:`image`). Everything else lives on
    :attr:`device`.

    Attributes:
        images: (N, H, W, 3), already composited on ``background``: uint8 (photos, a quarter of
            the memory of floats) or float32 in [0, 1] (values 8 bits would round, such as
            alpha-composited renders). Read them through :meth:`image` / :meth:`colors_at`, which
            give float32 in [0, 1] on :attr:`device`.
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
        if self.images.dtype not in (torch.uint8, torch.float32):
            raise ValueError(f"images must be uint8 or float32, got {self.images.dtype}")
        if self.poses.shape != (n, 4, 4):
            raise ValueError(f"poses must be ({n}, 4, 4), got {tuple(self.poses.shape)}")
        if self.bbox is not None and self.bbox.shape != (2, 3):
            raise ValueError(f"bbox must be (2, 3), got {tuple(self.bbox.shape)}")

    def __len__(self) -> int:
        return self.images.shape[0]

    @property
    def device(self) -> torch.device:
        """Where rays, colours and whole images are returned (the images may stay on the host)."""
        return self.poses.device

    def to(self, device: torch.device | str) -> Scene:
        """A copy on ``device``. The images go along when they take at most a quarter of a GPU's
        free memory (gathering a batch then needs no host round trip); larger captures stay on the
        host, pinned, and each batch's pixels are copied over."""
        device = torch.device(device)
        moved = {
            f.name: getattr(self, f.name).to(device)
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), torch.Tensor) and f.name != "images"
        }
        images = self.images.cpu()
        if device.type == "cuda":
            free, _ = torch.cuda.mem_get_info(device)
            if images.numel() * images.element_size() <= free // 4:
                images = images.to(device)
            elif not images.is_pinned():
                images = images.pin_memory()
        return dataclasses.replace(self, images=images, **moved)

    def image(self, i: int) -> torch.Tensor:
        """View ``i`` as (H, W, 3) float32 in [0, 1] on :attr:`device`."""
        return self._as_float(self.images[i])

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
        """Target colours (M, 3) float32 on :attr:`device` of the pixels addressed as in
        :meth:`rays_at` (indices on any device; those on a GPU are copied to the host)."""
        flat = (image_idx * (self.H * self.W) + pixel_idx).to(self.images.device)
        return self._as_float(self.images.reshape(-1, 3)[flat])

    def rays_for_image(self, i: int, ndc: bool | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays of every pixel of image ``i``, row-major: origins, dirs each (H*W, 3)."""
        return self._flat_rays(self.poses[i], ndc)

    def all_rays(self, ndc: bool | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every ray of the split with its target colour, for training on shuffled rays.

        Returns:
            origins, dirs, rgb: each (N*H*W, 3) on :attr:`device`, image-major then row-major
            (flat index ``(i * H + row) * W + col``); ``rgb`` is float32 in [0, 1].
        """
        origins, dirs = self._flat_rays(self.poses, ndc)
        return origins, dirs, self._as_float(self.images.reshape(-1, 3))

    def _as_float(self, pixels: torch.Tensor) -> torch.Tensor:
        """Host pixels (any shape) -> float32 in [0, 1] on :attr:`device`, converted after the copy
        (a quarter of the bytes to move for uint8)."""
        pixels = pixels.to(self.device, non_blocking=True)
        return pixels.float() / 255.0 if pixels.dtype == torch.uint8 else pixels

    def _flat_rays(self, c2w: torch.Tensor, ndc: bool | None) -> tuple[torch.Tensor, torch.Tensor]:
        origins, dirs = camera_rays(self.H, self.W, self.focal, c2w, self.cx, self.cy)
        return self._maybe_ndc(origins.reshape(-1, 3), dirs.reshape(-1, 3), ndc)

    def _maybe_ndc(
        self, origins: torch.Tensor, dirs: torch.Tensor, ndc: bool | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if self.ndc if ndc is None else ndc:
            return ndc_rays(self.H, self.W, self.focal, NDC_NEAR, origins, dirs)
        return origins, dirs
