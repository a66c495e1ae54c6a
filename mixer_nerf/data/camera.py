"""Camera intrinsics with lens distortion, and resampling photos into one shared pinhole camera.

Pixel coordinates put the centre of the top-left pixel at (0.5, 0.5), as COLMAP, nerfstudio and
:mod:`.rays` do. Distortion is OpenCV's radial-tangential model on normalised coordinates
(x, y) = ((u - cx) / fx, (v - cy) / fy) of the undistorted ray, r^2 = x^2 + y^2:

    x_d = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y

which also covers COLMAP's SIMPLE_RADIAL (k1) and RADIAL (k1, k2) models. A Scene has a single
pinhole camera (one focal length, no distortion), so photos whose camera differs from it are
resampled into it (undistorting the images, not the rays): the rays of training and rendering stay
plain pinhole rays.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from .errors import DatasetError
from .images import downscaled_size

MAX_ZOOM = 4.0  # the shared camera may narrow the field of view this much to keep every pixel seen
MONOTONIC_SAMPLES = 256  # radii at which the distortion is checked to be invertible over an image


@dataclass(frozen=True)
class Camera:
    """Intrinsics in pixels of a ``width`` x ``height`` image, plus radial (k1, k2) and tangential
    (p1, p2) distortion coefficients (all zero: a pinhole camera)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    def __post_init__(self) -> None:
        values = dataclasses.astuple(self)
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"camera values must be finite, got {self}")
        if self.width < 1 or self.height < 1 or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera size and focal lengths must be positive, got {self}")

    @property
    def distorted(self) -> bool:
        return any((self.k1, self.k2, self.p1, self.p2))

    def downscaled(self, factor: float) -> Camera:
        """The camera of the image shrunk by :func:`.images.downscale` with ``factor``."""
        return dataclasses.replace(
            self,
            width=downscaled_size(self.width, factor),
            height=downscaled_size(self.height, factor),
            fx=self.fx / factor,
            fy=self.fy / factor,
            cx=self.cx / factor,
            cy=self.cy / factor,
        )

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised undistorted coordinates -> normalised distorted coordinates (any shape)."""
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + self.k2 * r2)
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return xd, yd

    def source_pixels(self, target: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Where each pixel centre of pinhole ``target`` lies in this camera's image: u, v each
        (target.height, target.width), in this camera's pixel coordinates."""
        u = (np.arange(target.width) + 0.5 - target.cx) / target.fx
        v = (np.arange(target.height) + 0.5 - target.cy) / target.fy
        x, y = np.meshgrid(u, v)
        xd, yd = self.distort(x, y)
        return self.fx * xd + self.cx, self.fy * yd + self.cy

    def same_as(self, other: Camera) -> bool:
        """Equal up to float noise (relative 1e-6), so a resampling would change nothing."""
        return all(
            math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-9)
            for a, b in zip(dataclasses.astuple(self), dataclasses.astuple(other), strict=True)
        )


def shared_pinhole(cameras: list[Camera], where: str) -> Camera:
    """The pinhole camera every photo of a capture is resampled into.

    It has the first camera's size, principal point and horizontal focal length (square pixels),
    narrowed by the smallest zoom (>= 1) at which every one of its pixels sees into every photo:
    barrel distortion needs none, pincushion distortion or a narrower second camera does.
    Raises DatasetError (naming ``where``) when a distortion is not invertible over the image.
    """
    first = cameras[0]
    base = Camera(first.width, first.height, first.fx, first.fx, first.cx, first.cy)
    distinct = [c for k, c in enumerate(cameras) if not any(c.same_as(d) for d in cameras[:k])]
    for camera in distinct:
        _check_invertible(camera, base, where)
    if all(camera.same_as(base) for camera in distinct):
        return base

    def sees_everything(zoom: float) -> bool:
        target = dataclasses.replace(base, fx=base.fx * zoom, fy=base.fy * zoom)
        return all(_border_inside(camera, target) for camera in distinct)

    if sees_everything(1.0):
        return base
    if not sees_everything(MAX_ZOOM):
        raise DatasetError(f"{where}: the cameras' fields of view differ too much to share one camera")
    lo, hi = 1.0, MAX_ZOOM
    while hi - lo > 1e-6:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if sees_everything(mid) else (mid, hi)
    return dataclasses.replace(base, fx=base.fx * hi, fy=base.fy * hi)


def resample(img: np.ndarray, source: Camera, target: Camera) -> np.ndarray:
    """Photo ``img`` (H, W, C) float taken with ``source`` as seen by pinhole ``target``:
    (target.height, target.width, C) float32, bilinear (edge pixels extend half a pixel out)."""
    if source.same_as(target):
        return img
    u, v = source.source_pixels(target)
    # grid_sample's align_corners=False puts -1 and 1 on the image's outer pixel edges.
    grid = np.stack([2.0 * u / source.width - 1.0, 2.0 * v / source.height - 1.0], axis=-1)
    out = F.grid_sample(
        torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32))[None],
        torch.from_numpy(grid.astype(np.float32))[None],
        mode="bilinear",
        padding_mode="border",
        align_corners=False,
    )
    return out[0].permute(1, 2, 0).numpy()


def _border_inside(camera: Camera, target: Camera) -> bool:
    """Every border pixel centre of ``target`` maps into ``camera``'s image."""
    u, v = camera.source_pixels(target)
    border = (
        np.concatenate([u[0], u[-1], u[:, 0], u[:, -1]]),
        np.concatenate([v[0], v[-1], v[:, 0], v[:, -1]]),
    )
    return bool(
        (border[0] >= 0).all() and (border[0] <= camera.width).all()
        and (border[1] >= 0).all() and (border[1] <= camera.height).all()
    )  # fmt: skip


def _check_invertible(camera: Camera, target: Camera, where: str) -> None:
    """The radial distortion must grow with the radius out to the farthest corner of ``target``
    (a zoom only shrinks that radius); past a fold, two rays would share one pixel."""
    if not (camera.k1 or camera.k2):
        return
    corner = (
        max(abs(target.cx), abs(target.width - target.cx)),
        max(abs(target.cy), abs(target.height - target.cy)),
    )
    r = np.linspace(0.0, math.hypot(corner[0] / target.fx, corner[1] / target.fy), MONOTONIC_SAMPLES)
    distorted = r * (1.0 + r * r * (camera.k1 + camera.k2 * r * r))
    if (np.diff(distorted) <= 0).any():
        raise DatasetError(
            f"{where}: distortion k1={camera.k1:g}, k2={camera.k2:g} folds over within the image "
            "(not invertible); undistort the photos first"
        )
