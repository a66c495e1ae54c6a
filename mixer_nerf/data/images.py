"""Image files <-> float arrays, alpha compositing, area downscaling and 8-bit rounding (numpy,
HxWxC layout)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .errors import DatasetError, MissingFileError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def read_image(path: str | Path) -> np.ndarray:
    """Read an 8- or 16-bit image as float32 in [0, 1], shape (H, W, 3) or (H, W, 4) with alpha.

    Grey images are expanded to RGB. Raises MissingFileError / DatasetError naming ``path``.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(f"{path}: image file not found")
    try:
        # Pillow alone: it reads every format scenes use, and a corrupt file then fails with one
        # clear error instead of imageio probing (and warning about) every other backend.
        img = iio.imread(path, plugin="pillow")
    except Exception as exc:  # pillow/imageio raise several types for undecodable data
        raise DatasetError(f"{path}: cannot decode image ({type(exc).__name__}: {exc})") from exc
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        img = img.astype(np.float32) / 65535.0
    else:
        raise DatasetError(f"{path}: unsupported pixel type {img.dtype} (expected 8- or 16-bit)")
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[2] not in (1, 2, 3, 4):
        raise DatasetError(f"{path}: unsupported image shape {img.shape}")
    if img.shape[2] <= 2:  # grey or grey+alpha
        img = np.concatenate([np.repeat(img[..., :1], 3, axis=2), img[..., 1:]], axis=2)
    return img


def write_png(path: str | Path, img: np.ndarray) -> None:
    """Write a float (H, W, 3|4) image in [0, 1] as an 8-bit PNG (alpha kept, not premultiplied)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, to_uint8(img))


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float values in [0, 1] (clipped) rounded to 8 bits."""
    return np.round(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)


def composite(img: np.ndarray, background: np.ndarray) -> np.ndarray:
    """(H, W, 3|4) straight-alpha image over a (3,) background colour -> (H, W, 3)."""
    if img.shape[2] == 3:
        return img
    alpha = img[..., 3:]
    return img[..., :3] * alpha + background * (1.0 - alpha)


def check_downscale(factor: object) -> float:
    """``factor`` as a float, or ValueError unless it is a finite number >= 1."""
    if isinstance(factor, bool) or not isinstance(factor, (int, float)) or not 1 <= factor < math.inf:
        raise ValueError(f"downscale must be a number >= 1, got {factor!r}")
    return float(factor)


def downscaled_size(size: int, factor: float) -> int:
    """Pixels along an axis of ``size`` pixels after :func:`downscale` by ``factor``."""
    return max(1, math.floor(size / factor + 1e-9))


def downscale(img: np.ndarray, factor: float, path: str | Path = "<image>") -> np.ndarray:
    """Shrink (H, W, C) by ``factor`` >= 1 with an area filter; pixel coordinates scale by exactly
    1 / factor, so intrinsics (focal length, principal point) divide by it too.

    An integer factor averages factor x factor blocks and must divide the size. Any other factor
    averages each output pixel's exact footprint; the output is :func:`downscaled_size` pixels,
    dropping the partial footprint at the right and bottom edges (less than ``factor`` pixels).
    Applied after compositing, so averaging colours is averaging premultiplied colours, as a
    camera at the lower resolution would see it.
    """
    if factor == 1:
        return img
    h, w, c = img.shape
    if float(factor).is_integer():
        factor = int(factor)
        if h % factor or w % factor:
            raise DatasetError(
                f"{path}: size {w}x{h} is not divisible by downscale factor {factor} "
                "(a non-integer factor resamples instead)"
            )
        return img.reshape(h // factor, factor, w // factor, factor, c).mean(axis=(1, 3))
    out = _area_resample(img, factor, axis=0)
    return _area_resample(out, factor, axis=1).astype(img.dtype, copy=False)


def _area_resample(img: np.ndarray, factor: float, axis: int) -> np.ndarray:
    """Mean of ``img`` over the intervals [k, k + 1) * factor along ``axis``, exact for a
    piecewise-constant image (each pixel a unit-wide box): differences of its running integral."""
    n = img.shape[axis]
    edges = np.arange(downscaled_size(n, factor) + 1) * factor
    pixels = np.moveaxis(img, axis, 0).astype(np.float64)
    running = np.concatenate([np.zeros_like(pixels[:1]), np.cumsum(pixels, axis=0)])
    whole = np.minimum(np.floor(edges).astype(np.int64), n)
    part = (edges - whole)[(...,) + (None,) * (pixels.ndim - 1)]
    integral = running[whole] + part * pixels[np.minimum(whole, n - 1)]
    return np.moveaxis((integral[1:] - integral[:-1]) / factor, 0, axis)


def stack_same_size(images: Sequence[np.ndarray], paths: Sequence[str | Path]) -> np.ndarray:
    """Stack (H, W, C) images (dtype kept) into (N, H, W, C), failing on the first whose size differs."""
    if not images:
        raise DatasetError("no images to stack")
    h, w = images[0].shape[:2]
    for img, p in zip(images, paths, strict=True):
        if img.shape[:2] != (h, w):
            raise DatasetError(
                f"{p}: image is {img.shape[1]}x{img.shape[0]} but {paths[0]} is {w}x{h}; "
                "all images of a scene must have one size"
            )
    return np.stack(images)


def list_images(folder: Path) -> list[Path]:
    """Image files (png/jpg) directly in ``folder``, sorted by name."""
    if not folder.is_dir():
        raise MissingFileError(f"{folder}: image folder not found")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
