"""A built-in test scene: textured analytic shapes rendered exactly by ray intersection.

Three Lambertian shapes sit inside the Blender box [-1.5, 1.5]^3 (world z is up, as in
nerf_synthetic): a sphere with a latitude/longitude checkerboard, a box with diagonal stripes and
a capped cylinder with angular bands. Cameras lie on a sphere of radius 4 above the ground plane
looking at the origin, with nerf_synthetic's field of view. Pixels that miss every shape are
transparent, and the scene is written to disk in Blender format so it loads like any other.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from .blender import write_blender_split
from .images import downscale
from .rays import camera_rays

VERSION = 1  # part of the cache key: bump whenever the rendered images change
CAMERA_ANGLE_X = 0.6911112070083618  # nerf_synthetic's horizontal field of view
CAMERA_RADIUS = 4.0
ELEVATION_RANGE = (math.radians(10.0), math.radians(70.0))
SUPERSAMPLE = 2  # per axis: anti-aliased edges and partial alpha, as a real render has
LIGHT = np.array([0.4, -0.3, 1.0]) / np.linalg.norm([0.4, -0.3, 1.0])
AMBIENT = 0.35
SPLIT_SEEDS = {"train": 0, "val": 1, "test": 2}


def ensure_procedural_scene(
    resolution: int | tuple[int, int] = 100,
    n_train: int = 100,
    n_val: int = 8,
    n_test: int = 8,
    cache_dir: str | Path | None = None,
) -> Path:
    """Render the procedural scene once and return its folder (Blender format, cached).

    Args:
        resolution: image size, an int for square images or (H, W).
        n_train, n_val, n_test: number of views per split.
        cache_dir: root of the cache; default ``$MIXER_NERF_CACHE``, else
            ``$XDG_CACHE_HOME/mixer_nerf``, else ``~/.cache/mixer_nerf``. Scenes live in
            ``<cache_dir>/procedural/<hash of the parameters>/``.
    """
    H, W = (resolution, resolution) if isinstance(resolution, int) else tuple(resolution)
    views = {"train": n_train, "val": n_val, "test": n_test}
    if H < 1 or W < 1 or min(views.values()) < 1:
        raise ValueError(f"resolution and view counts must be positive, got {(H, W)} and {views}")
    params = {"version": VERSION, "H": H, "W": W, "views": views}
    key = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:16]
    final = _cache_root(cache_dir) / "procedural" / key
    if final.is_dir():
        return final
    final.parent.mkdir(parents=True, exist_ok=True)
    # Render into a private folder and rename it into place, so that a concurrent or interrupted
    # run never leaves a half-written scene at ``final``.
    tmp = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{key}-"))
    try:
        for split, n in views.items():
            poses = orbit_poses(n, seed=SPLIT_SEEDS[split])
            write_blender_split(tmp, split, [render(H, W, p) for p in poses], poses, CAMERA_ANGLE_X)
        (tmp / "params.json").write_text(json.dumps(params, indent=1))
        os.replace(tmp, final)
    except OSError:
        if not final.is_dir():  # a concurrent run winning the rename is fine; anything else is not
            raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


def orbit_poses(n: int, seed: int) -> np.ndarray:
    """(n, 4, 4) OpenGL camera-to-world matrices on the upper sphere of radius CAMERA_RADIUS,
    looking at the origin, at random azimuths and area-uniform elevations in ELEVATION_RANGE."""
    rng = np.random.default_rng(seed)
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n)
    lo, hi = np.sin(ELEVATION_RANGE)
    elevation = np.arcsin(rng.uniform(lo, hi, n))
    back = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], -1
    )
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    up = np.cross(back, right)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :] = np.stack([right, up, back, CAMERA_RADIUS * back], axis=-1)
    return poses


def render(H: int, W: int, c2w: np.ndarray) -> np.ndarray:
    """Render one view: (H, W, 4) float32 RGBA in [0, 1], straight (not premultiplied) alpha."""
    s = SUPERSAMPLE
    focal = 0.5 * W * s / math.tan(0.5 * CAMERA_ANGLE_X)
    origins, dirs = camera_rays(H * s, W * s, focal, torch.from_numpy(c2w))
    hit = _nearest([shape(origins.numpy(), dirs.numpy()) for shape in (_sphere, _box, _cylinder)])
    shade = AMBIENT + (1.0 - AMBIENT) * np.clip(hit.normal @ LIGHT, 0.0, None)
    alpha = np.isfinite(hit.t)[..., None].astype(np.float64)
    premult = np.concatenate([hit.albedo * shade[..., None] * alpha, alpha], axis=-1)
    rgba = downscale(premult, s)
    rgb = rgba[..., :3] / np.maximum(rgba[..., 3:], 1e-8)
    return np.concatenate([rgb, rgba[..., 3:]], axis=-1).astype(np.float32)


class _Hit(NamedTuple):
    """First intersection per ray: t (...,) with inf for a miss, unit normal and albedo (..., 3)."""

    t: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray


def _nearest(hits: list[_Hit]) -> _Hit:
    ts = np.stack([h.t for h in hits])
    k = ts.argmin(axis=0)[..., None]
    return _Hit(
        ts.min(axis=0), np.choose(k, [h.normal for h in hits]), np.choose(k, [h.albedo for h in hits])
    )


def _two_tone(mask: np.ndarray, a: tuple, b: tuple) -> np.ndarray:
    return np.where(mask[..., None], np.array(a), np.array(b))


def _first_positive(t_near: np.ndarray, t_far: np.ndarray, valid: np.ndarray | bool) -> np.ndarray:
    """Entry distance of a ray into a convex shape it hits, inf when it misses or starts inside."""
    return np.where(valid & (t_near > 0) & (t_near <= t_far), t_near, np.inf)


def _sphere(o: np.ndarray, d: np.ndarray, centre=(0.45, -0.35, 0.1), radius=0.5) -> _Hit:
    oc = o - np.array(centre)
    a = (d * d).sum(-1)
    b = (d * oc).sum(-1)
    disc = b * b - a * ((oc * oc).sum(-1) - radius**2)
    root = np.sqrt(np.maximum(disc, 0.0))
    t = _first_positive((-b - root) / a, (-b + root) / a, disc >= 0)
    n = (oc + np.where(np.isfinite(t), t, 0.0)[..., None] * d) / radius
    lon = np.floor((np.arctan2(n[..., 1], n[..., 0]) + np.pi) / (2 * np.pi) * 12)
    lat = np.floor(np.arccos(np.clip(n[..., 2], -1.0, 1.0)) / np.pi * 6)
    return _Hit(t, n, _two_tone((lon + lat) % 2 == 0, (0.85, 0.15, 0.1), (0.95, 0.95, 0.9)))


def _box(o: np.ndarray, d: np.ndarray, lo=(-0.85, -0.65, -0.8), hi=(-0.15, 0.05, 0.1)) -> _Hit:
    safe_d = np.where(np.abs(d) < 1e-12, 1e-12, d)  # rays parallel to a slab never cross it
    t1, t2 = (np.array(lo) - o) / safe_d, (np.array(hi) - o) / safe_d
    t_in, t_out = np.minimum(t1, t2), np.maximum(t1, t2)
    t = _first_positive(t_in.max(-1), t_out.min(-1), True)
    axis = t_in.argmax(-1)[..., None]
    n = -np.sign(np.take_along_axis(d, axis, -1)) * (np.arange(3) == axis)
    p = o + np.where(np.isfinite(t), t, 0.0)[..., None] * d
    stripes = np.floor(p.sum(-1) * 4.0) % 2 == 0
    return _Hit(t, n, _two_tone(stripes, (0.15, 0.3, 0.85), (0.95, 0.8, 0.2)))


def _cylinder(o: np.ndarray, d: np.ndarray, axis_xy=(0.05, 0.65), radius=0.3, z=(-0.8, 0.5)) -> _Hit:
    """Vertical capped cylinder: the entry point is on the side or on a cap."""
    oc = o[..., :2] - np.array(axis_xy)
    dxy = d[..., :2]
    a = np.maximum((dxy * dxy).sum(-1), 1e-12)
    b = (dxy * oc).sum(-1)
    disc = b * b - a * ((oc * oc).sum(-1) - radius**2)
    root = np.sqrt(np.maximum(disc, 0.0))
    safe_dz = np.where(np.abs(d[..., 2]) < 1e-12, 1e-12, d[..., 2])
    tz1, tz2 = (z[0] - o[..., 2]) / safe_dz, (z[1] - o[..., 2]) / safe_dz
    # Intersection of the infinite cylinder's interval with the slab between the caps.
    t_side, t_cap = (-b - root) / a, np.minimum(tz1, tz2)
    t = _first_positive(
        np.maximum(t_side, t_cap), np.minimum((-b + root) / a, np.maximum(tz1, tz2)), disc >= 0
    )
    on_cap = t_cap > t_side
    p = o + np.where(np.isfinite(t), t, 0.0)[..., None] * d
    rel = p[..., :2] - np.array(axis_xy)
    side_n = np.concatenate([rel / radius, np.zeros_like(rel[..., :1])], -1)
    cap_n = np.zeros_like(p)
    cap_n[..., 2] = -np.sign(safe_dz)
    n = np.where(on_cap[..., None], cap_n, side_n)
    bands = np.floor((np.arctan2(rel[..., 1], rel[..., 0]) + np.pi) / (2 * np.pi) * 8) % 2 == 0
    rings = np.floor(np.linalg.norm(rel, axis=-1) / radius * 3) % 2 == 0
    return _Hit(t, n, _two_tone(np.where(on_cap, rings, bands), (0.1, 0.65, 0.3), (0.9, 0.9, 0.95)))


def _cache_root(cache_dir: str | Path | None) -> Path:
    if cache_dir is not None:
        return Path(cache_dir)
    if os.environ.get("MIXER_NERF_CACHE"):
        return Path(os.environ["MIXER_NERF_CACHE"])
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "mixer_nerf"
