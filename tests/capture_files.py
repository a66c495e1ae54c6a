"""Test helpers: camera rigs with known poses, and COLMAP model files written from the documented
format independently of the package's reader (so that a round trip checks both)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from mixer_nerf.data.blender import write_blender_split
from mixer_nerf.data.images import write_png
from mixer_nerf.data.procedural import orbit_poses

COLMAP_MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
                    "OPENCV_FISHEYE": 5}  # fmt: skip
CV_FROM_GL = np.diag([1.0, -1.0, -1.0])


def write_blender_scene(root: Path, size: int = 8, seed: int = 0, **views: int) -> Path:
    """A Blender scene in ``root`` with ``views`` (split name -> count) of random size x size RGBA
    images and orbit cameras, e.g. ``write_blender_scene(root, train=9, val=2)``."""
    rng = np.random.default_rng(seed)
    for k, (split, n) in enumerate(views.items()):
        write_blender_split(root, split, rng.uniform(size=(n, size, size, 4)), orbit_poses(n, k), 0.69)
    return root


def orbit_rig(n: int, seed: int = 0) -> np.ndarray:
    """(n, 4, 4) OpenGL cameras on a sphere of radius 4 around the origin, looking at it (360)."""
    return orbit_poses(n, seed)


def forward_rig(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(n, 4, 4) OpenGL cameras near the plane z = 1 looking roughly down -z, and (200, 3) scene
    points in front of them at depths 3 to 12 (a forward-facing capture)."""
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        yaw, pitch = rng.uniform(-0.1, 0.1, 2)
        ry = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        rx = np.array([[1, 0, 0], [0, np.cos(pitch), -np.sin(pitch)], [0, np.sin(pitch), np.cos(pitch)]])
        poses[k, :3, :3] = ry @ rx
        poses[k, :3, 3] = [rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), 1.0 + rng.uniform(-0.1, 0.1)]
    depth = rng.uniform(3.0, 12.0, 200)
    points = np.stack(
        [rng.uniform(-0.3, 0.3, 200) * depth, rng.uniform(-0.2, 0.2, 200) * depth, 1.0 - depth], -1
    )
    return poses, points


def world_to_colmap(c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenGL camera-to-world (4, 4) -> COLMAP's world-to-camera quaternion (w, x, y, z) and t."""
    rotation = (c2w[:3, :3] @ CV_FROM_GL).T
    return rotation_to_quaternion(rotation), -rotation @ c2w[:3, 3]


def rotation_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix, via the largest of the four components."""
    w = np.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2
    k = int(np.argmax([w, x, y, z]))
    if k == 0:
        q = [w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)]
    elif k == 1:
        q = [(r[2, 1] - r[1, 2]) / (4 * x), x, (r[0, 1] + r[1, 0]) / (4 * x), (r[0, 2] + r[2, 0]) / (4 * x)]
    elif k == 2:
        q = [(r[0, 2] - r[2, 0]) / (4 * y), (r[0, 1] + r[1, 0]) / (4 * y), y, (r[1, 2] + r[2, 1]) / (4 * y)]
    else:
        q = [(r[1, 0] - r[0, 1]) / (4 * z), (r[0, 2] + r[2, 0]) / (4 * z), (r[1, 2] + r[2, 1]) / (4 * z), z]
    return np.array(q)


def write_colmap(
    folder: Path,
    cameras: dict[int, tuple[str, int, int, tuple[float, ...]]],
    images: list[tuple[int, np.ndarray, int, str]],
    points: np.ndarray,
    binary: bool = True,
) -> Path:
    """Write cameras/images/points3D in ``folder``.

    Args:
        cameras: id -> (model name, width, height, params).
        images: (image id, OpenGL camera-to-world (4, 4), camera id, name); each gets three 2D
            points, one of them without a 3D point.
        points: (P, 3) positions; each gets a two-element track.
    """
    folder.mkdir(parents=True, exist_ok=True)
    rows = [(image_id, *world_to_colmap(c2w), camera_id, name) for image_id, c2w, camera_id, name in images]
    if binary:
        data = struct.pack("<Q", len(cameras))
        for cid, (model, w, h, params) in cameras.items():
            data += struct.pack(f"<iiQQ{len(params)}d", cid, COLMAP_MODEL_IDS[model], w, h, *params)
        (folder / "cameras.bin").write_bytes(data)
        data = struct.pack("<Q", len(rows))
        for image_id, q, t, cid, name in rows:
            data += struct.pack("<i7di", image_id, *q, *t, cid) + name.encode() + b"\0"
            data += struct.pack("<Q", 3) + struct.pack("<ddqddqddq", 1.5, 2.5, 0, 3.0, 4.0, -1, 5.5, 6.5, 1)
        (folder / "images.bin").write_bytes(data)
        data = struct.pack("<Q", len(points))
        for k, p in enumerate(points):
            data += struct.pack("<Q3d3BdQ", k, *p, 10, 20, 30, 0.5, 2) + struct.pack("<iiii", 1, 0, 2, 1)
        (folder / "points3D.bin").write_bytes(data)
    else:
        lines = ["# Camera list with one line of data per camera:"]
        lines += [
            f"{cid} {model} {w} {h} " + " ".join(repr(float(x)) for x in params)
            for cid, (model, w, h, params) in cameras.items()
        ]
        (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
        lines = [
            "# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        ]
        for k, (image_id, q, t, cid, name) in enumerate(rows):
            lines.append(" ".join(map(repr, [image_id, *q.tolist(), *t.tolist(), cid])) + " " + name)
            lines.append("" if k % 2 else "1.5 2.5 0 3.0 4.0 -1")  # an image without 2D points too
        (folder / "images.txt").write_text("\n".join(lines) + "\n")
        lines = ["# 3D point list with one line of data per point:"]
        lines += [
            f"{k} " + " ".join(map(repr, p.tolist())) + " 10 20 30 0.5 1 0 2 1" for k, p in enumerate(points)
        ]
        (folder / "points3D.txt").write_text("\n".join(lines) + "\n")
    return folder


def write_photos(
    folder: Path, names: list[str], width: int, height: int, seed: int = 0
) -> dict[str, np.ndarray]:
    """Random 8-bit RGB photos; returns name -> (height, width, 3) uint8 as written."""
    rng = np.random.default_rng(seed)
    photos = {}
    for name in names:
        img = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        write_png(folder / name, img / 255.0)
        photos[name] = img
    return photos
