"""nerfstudio / instant-ngp ``transforms.json`` captures, and the PLY point reader they use."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from capture_files import forward_rig, orbit_rig, write_photos

from mixer_nerf.data import DatasetError, MissingFileError, detect_format, load_nerfstudio, load_scene
from mixer_nerf.data.llff import BD_FACTOR
from mixer_nerf.data.ply import read_ply_points
from mixer_nerf.data.pose_alignment import pose_errors

W, H = 40, 30


def _write(root: Path, poses: np.ndarray, top: dict, per_frame: dict | None = None) -> dict:
    """transforms.json with ``top`` level keys and random photos in images/."""
    names = [f"images/frame_{k:05d}.png" for k in range(len(poses))]
    photos = write_photos(root, names, W, H)
    frames = [{"file_path": n, "transform_matrix": p.tolist(), **(per_frame or {}).get(k, {})}
              for k, (n, p) in enumerate(zip(names, poses, strict=True))]  # fmt: skip
    (root / "transforms.json").write_text(json.dumps({**top, "frames": frames}))
    return photos


def test_shared_intrinsics_round_trip(tmp_path):
    poses = orbit_rig(9, seed=5)
    camera = {"w": W, "h": H, "fl_x": 33.0, "fl_y": 33.0, "cx": 19.5, "cy": 15.5, "camera_model": "OPENCV"}
    photos = _write(tmp_path, poses, {**camera, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
    assert detect_format(tmp_path) == "nerfstudio"
    scene = load_scene(tmp_path, split="all")
    assert (scene.W, scene.H, scene.focal, scene.cx, scene.cy) == (W, H, 33.0, 19.5, 15.5)
    assert scene.images.dtype == torch.uint8
    np.testing.assert_array_equal(scene.images[4].numpy(), photos["images/frame_00004.png"])
    errors = pose_errors(poses, scene.poses.double().numpy())
    assert errors.rotation_degrees.max() < 1e-3 and errors.centre_error.max() < 1e-5
    assert not scene.ndc and scene.bbox.tolist() == [[-1.0] * 3, [1.0] * 3]
    assert len(load_nerfstudio(tmp_path)) == 7 and len(load_nerfstudio(tmp_path, split="val")) == 2


def test_field_of_view_and_size_from_the_image(tmp_path):
    _write(tmp_path, orbit_rig(3), {"camera_angle_x": 1.0})
    scene = load_nerfstudio(tmp_path, split="all")
    assert (scene.W, scene.H, scene.cx, scene.cy) == (W, H, W / 2, H / 2)
    assert scene.focal == pytest.approx(0.5 * W / math.tan(0.5))


def test_per_frame_cameras_share_one_pinhole(tmp_path):
    # Frame 1 has a longer lens: the shared camera narrows until every pixel sees into it.
    _write(tmp_path, orbit_rig(3), {"w": W, "h": H, "fl_x": 30.0}, per_frame={1: {"fl_x": 36.0}})
    scene = load_nerfstudio(tmp_path, split="all")
    assert scene.focal == pytest.approx(36.0 * (W / 2 - 0.5) / (W / 2), rel=1e-5)


@pytest.mark.parametrize("encoding", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_forward_facing_capture_takes_depths_from_the_point_cloud(tmp_path, encoding):
    poses, points = forward_rig(8)
    _write(tmp_path, poses, {"w": W, "h": H, "fl_x": 30.0, "ply_file_path": "sparse_pc.ply"})
    _write_ply(tmp_path / "sparse_pc.ply", points, encoding)
    np.testing.assert_allclose(read_ply_points(tmp_path / "sparse_pc.ply"), points, rtol=1e-6)
    scene = load_nerfstudio(tmp_path)
    assert scene.ndc and (scene.near, scene.far) == (0.0, 1.0)
    assert load_nerfstudio(tmp_path, ndc=False).near == pytest.approx(0.9 / BD_FACTOR)


def _write_ply(path: Path, points: np.ndarray, encoding: str) -> None:
    """Vertices with float32 x, y, z and uint8 colours, then an unused face element."""
    header = (f"ply\nformat {encoding} 1.0\ncomment made by a test\nelement vertex {len(points)}\n"
              "property float x\nproperty float y\nproperty float z\nproperty uchar red\n"
              "property uchar green\nproperty uchar blue\nelement face 0\n"
              "property list uchar int vertex_indices\nend_header\n")  # fmt: skip
    if encoding == "ascii":
        body = "".join(f"{x} {y} {z} 1 2 3\n" for x, y, z in points.astype(np.float32).tolist()).encode()
    else:
        order = "<" if encoding == "binary_little_endian" else ">"
        rows = np.zeros(len(points), dtype=[(c, order + "f4") for c in "xyz"] + [(c, "u1") for c in "rgb"])
        for k, c in enumerate("xyz"):
            rows[c] = points[:, k]
        body = rows.tobytes()
    path.write_bytes(header.encode() + body)


def test_ply_errors(tmp_path):
    path = tmp_path / "p.ply"
    path.write_bytes(b"not a ply")
    with pytest.raises(DatasetError, match=r"p\.ply: not a PLY file"):
        read_ply_points(path)
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nend_header\n"
    )
    with pytest.raises(DatasetError, match="no x, y, z"):
        read_ply_points(path)
    path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\n"
                     b"property float y\nproperty float z\nend_header\n" + bytes(12))  # fmt: skip
    with pytest.raises(DatasetError, match="truncated or malformed vertex data"):
        read_ply_points(path)
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                     b"property float z\nend_header\n1 2 3\n4 5 6\n")  # fmt: skip
    with pytest.raises(DatasetError, match="truncated or malformed vertex data"):
        read_ply_points(path)
    path.write_bytes(b"ply\nformat ascii 1.0\nelement face 1\nelement vertex 3\nend_header\n")
    with pytest.raises(DatasetError, match="the vertex element must come first"):
        read_ply_points(path)
    with pytest.raises(MissingFileError, match="point cloud file not found"):
        read_ply_points(tmp_path / "nothing.ply")


def _top(**extra) -> dict:
    return {"w": W, "h": H, "fl_x": 30.0, **extra}


NERFSTUDIO_BREAKAGES = {
    "fisheye": (_top(camera_model="OPENCV_FISHEYE"), None, r"camera_model 'OPENCV_FISHEYE' is not supported"),
    "k3": (_top(k3=0.01), None, r"frames\[0\]: distortion term k3 is not supported"),
    "no focal": ({"w": W, "h": H}, None, r"frames\[0\]: needs fl_x or camera_angle_x"),
    "text focal": (_top(), {2: {"fl_x": "thirty"}}, r"frames\[2\]: fl_x must be a number, got 'thirty'"),
    "negative focal": (
        _top(),
        {1: {"fl_x": -3.0}},
        r"frames\[1\]: camera size and focal lengths must be positive",
    ),
    "size": (_top(w=W + 1), None, r"frame_00000\.png: image is 40x30 but its camera is 41x30"),
    "forward-facing without points": (
        _top(),
        "forward",
        r"a forward-facing capture needs sparse points .* ply_file_path",
    ),
    "missing point cloud": (_top(ply_file_path="pc.ply"), None, r"pc\.ply: point cloud file not found"),
}


@pytest.mark.parametrize("breakage", NERFSTUDIO_BREAKAGES)
def test_nerfstudio_errors_name_file_and_problem(tmp_path, breakage):
    top, frames, message = NERFSTUDIO_BREAKAGES[breakage]
    poses = forward_rig(4)[0] if frames == "forward" else orbit_rig(4)
    _write(tmp_path, poses, top, None if frames == "forward" else frames)
    with pytest.raises(DatasetError, match=message) as info:
        load_nerfstudio(tmp_path, split="all")
    assert str(tmp_path) in str(info.value) and "\n" not in str(info.value)


def test_nerfstudio_missing_files(tmp_path):
    with pytest.raises(MissingFileError, match=r"transforms\.json: transforms file not found"):
        load_nerfstudio(tmp_path)
    _write(tmp_path, orbit_rig(3), {"camera_angle_x": 1.0})
    (tmp_path / "images/frame_00002.png").unlink()
    with pytest.raises(MissingFileError, match=r"frame_00002\.png: image file not found"):
        load_nerfstudio(tmp_path)
