"""COLMAP captures: the model reader (.bin and .txt), camera models, undistortion, framing of
forward-facing and 360 captures, non-integer downscale, and errors that name the problem."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from capture_files import forward_rig, orbit_rig, write_colmap, write_photos

from mixer_nerf.data import DatasetError, MissingFileError, detect_format, load_colmap, load_scene
from mixer_nerf.data.camera import Camera
from mixer_nerf.data.captures import is_forward_facing
from mixer_nerf.data.colmap import colmap_camera
from mixer_nerf.data.colmap_model import ColmapCamera, read_model
from mixer_nerf.data.images import downscale
from mixer_nerf.data.llff import BD_FACTOR, average_pose
from mixer_nerf.data.pose_alignment import pose_errors

W, H, F = 40, 30, 36.0


def _capture(root: Path, poses: np.ndarray, points: np.ndarray, binary: bool = True, model=None) -> dict:
    """COLMAP capture of ``poses`` with one camera (default PINHOLE W x H, focal F) and random
    photos; image ids run backwards so that the loader's name order differs from the file's."""
    names = [f"img_{k:03d}.png" for k in range(len(poses))]
    photos = write_photos(root / "images", names, W, H)
    camera = model or ("PINHOLE", W, H, (F, F, W / 2 + 0.5, H / 2 - 0.25))
    images = [(len(poses) - k, poses[k], 7, names[k]) for k in range(len(poses))]
    write_colmap(root / "sparse" / "0", {7: camera}, images, points, binary)
    return photos


@pytest.mark.parametrize("binary", [True, False])
def test_360_capture_round_trips_poses_intrinsics_and_pixels(tmp_path, binary):
    poses = orbit_rig(10, seed=3)
    photos = _capture(tmp_path, poses, np.zeros((5, 3)), binary)
    assert detect_format(tmp_path) == "colmap"
    scene = load_scene(tmp_path, split="all")
    assert (scene.H, scene.W, scene.focal, scene.cx, scene.cy) == (H, W, F, W / 2 + 0.5, H / 2 - 0.25)
    assert scene.images.dtype == torch.uint8
    assert [p.name for p in scene.image_paths] == sorted(photos)
    for k, name in enumerate(sorted(photos)):
        np.testing.assert_array_equal(scene.images[k].numpy(), photos[name])
    # One similarity maps the true poses onto the loaded ones.
    errors = pose_errors(poses, scene.poses.double().numpy())
    assert errors.rotation_degrees.max() < 1e-3 and errors.centre_error.max() < 1e-5
    # The 360 framing: farthest camera at distance 1, mean camera up along +z, box [-1, 1]^3.
    assert not scene.ndc and scene.bbox.tolist() == [[-1.0] * 3, [1.0] * 3]
    assert scene.poses[:, :3, 3].norm(dim=-1).max() == pytest.approx(1.0, abs=1e-6)
    up = scene.poses[:, :3, 1].mean(0)
    torch.testing.assert_close(up / up.norm(), torch.tensor([0.0, 0.0, 1.0]), atol=1e-6, rtol=0)
    # Cameras looked at the origin, which stays their focus point: the central rays pass through it.
    axes = scene.poses[:, :3, 2]
    assert torch.linalg.cross(scene.poses[:, :3, 3], axes).norm(dim=-1).max() < 1e-5
    assert 0 < scene.near < 0.1 and scene.far == pytest.approx(2 * math.sqrt(3))


def test_text_and_binary_models_read_alike(tmp_path):
    poses, points = forward_rig(6)
    write_colmap(tmp_path / "bin", {1: ("OPENCV", W, H, (30.0, 31.0, 20.0, 15.0, 0.1, -0.01, 1e-3, -2e-3))},
                 [(k + 1, poses[k], 1, f"a/{k}.png") for k in range(6)], points, binary=True)  # fmt: skip
    write_colmap(tmp_path / "txt", {1: ("OPENCV", W, H, (30.0, 31.0, 20.0, 15.0, 0.1, -0.01, 1e-3, -2e-3))},
                 [(k + 1, poses[k], 1, f"a/{k}.png") for k in range(6)], points, binary=False)  # fmt: skip
    a, b = read_model(tmp_path / "bin"), read_model(tmp_path / "txt")
    assert a.cameras == b.cameras and a.cameras[1].model == "OPENCV"
    assert [i.name for i in a.images] == [i.name for i in b.images] == [f"a/{k}.png" for k in range(6)]
    for x, y in zip(a.images, b.images, strict=True):
        np.testing.assert_allclose(x.qvec, y.qvec, rtol=0, atol=1e-15)
        np.testing.assert_allclose(x.tvec, y.tvec, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(a.points, points)
    np.testing.assert_array_equal(b.points, points)


def test_forward_facing_capture_is_framed_like_llff(tmp_path):
    poses, points = forward_rig(9)
    _capture(tmp_path, poses, points)
    assert is_forward_facing(poses) and not is_forward_facing(orbit_rig(9))
    scene = load_colmap(tmp_path, split="all")
    assert (
        scene.ndc and (scene.near, scene.far) == (0.0, 1.0) and scene.bbox.tolist() == [[-1.0] * 3, [1.0] * 3]
    )
    np.testing.assert_allclose(average_pose(scene.poses.double().numpy()), np.eye(4), atol=1e-5)
    world = load_colmap(tmp_path, split="all", ndc=False)
    assert not world.ndc and world.bbox is None
    # The nearest content (1st percentile of the depths a view sees) lands at 1 / BD_FACTOR.
    assert world.near == pytest.approx(0.9 / BD_FACTOR)
    assert world.far > 12.0 / 3.1 / BD_FACTOR  # the farthest points are ~4x the nearest
    errors = pose_errors(poses, world.poses.double().numpy())
    assert errors.rotation_degrees.max() < 1e-3
    train, test = load_colmap(tmp_path), load_colmap(tmp_path, split="test", holdout=4)
    assert len(train) == 7 and [p.name for p in test.image_paths] == [
        "img_000.png",
        "img_004.png",
        "img_008.png",
    ]
    torch.testing.assert_close(train.poses[0], scene.poses[1])  # splits share one frame


def test_camera_models_map_to_intrinsics():
    def camera(model, params):
        return colmap_camera(ColmapCamera(1, model, 100, 80, params), Path("m"))

    assert camera("SIMPLE_PINHOLE", (50.0, 49.0, 41.0)) == Camera(100, 80, 50.0, 50.0, 49.0, 41.0)
    assert camera("PINHOLE", (50.0, 52.0, 49.0, 41.0)) == Camera(100, 80, 50.0, 52.0, 49.0, 41.0)
    assert camera("SIMPLE_RADIAL", (50.0, 49.0, 41.0, 0.1)) == Camera(100, 80, 50.0, 50.0, 49.0, 41.0, 0.1)
    assert camera("RADIAL", (50.0, 49.0, 41.0, 0.1, -0.02)) == Camera(
        100, 80, 50.0, 50.0, 49.0, 41.0, 0.1, -0.02
    )
    assert camera("OPENCV", (50.0, 52.0, 49.0, 41.0, 0.1, -0.02, 0.003, 0.004)) == Camera(
        100, 80, 50.0, 52.0, 49.0, 41.0, 0.1, -0.02, 0.003, 0.004
    )
    with pytest.raises(
        DatasetError, match=r"^m: camera 1 uses COLMAP model OPENCV_FISHEYE, which is not supported"
    ):
        camera("OPENCV_FISHEYE", (50.0,) * 8)


def _pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A smooth colour function of the undistorted normalised image coordinates."""
    return np.stack(
        [0.5 + 0.4 * np.sin(3 * x + 1), 0.5 + 0.4 * np.cos(4 * y), 0.5 + 0.3 * np.sin(2 * x - 3 * y)], -1
    )


def _undistort(camera: Camera, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert the distortion by fixed-point iteration (converges for mild distortion)."""
    x, y = xd.copy(), yd.copy()
    for _ in range(100):
        dx, dy = camera.distort(x, y)
        x, y = x + (xd - dx), y + (yd - dy)
    return x, y


@pytest.mark.parametrize("k1, fy", [(-0.15, 100.0), (0.15, 104.0)])  # barrel; pincushion, non-square pixels
def test_distorted_photos_are_undistorted_into_a_pinhole_camera(tmp_path, k1, fy):
    params = (100.0, fy, 61.0, 44.0, k1, 0.02, 0.01, -0.008)
    camera = Camera(120, 90, *params)
    v, u = np.mgrid[0:90, 0:120] + 0.5
    photo = _pattern(*_undistort(camera, (u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy))
    (tmp_path / "images").mkdir()
    names = [f"{k}.png" for k in range(3)]
    for name in names:
        iio.imwrite(tmp_path / "images" / name, np.round(photo * 255).astype(np.uint8))
    poses = orbit_rig(3)
    write_colmap(tmp_path / "sparse", {1: ("OPENCV", 120, 90, params)},
                 [(k + 1, poses[k], 1, names[k]) for k in range(3)], np.zeros((1, 3)))  # fmt: skip
    scene = load_colmap(tmp_path, split="all")
    assert (scene.W, scene.H, scene.cx, scene.cy) == (120, 90, 61.0, 44.0)
    zoom = scene.focal / 100.0
    # Barrel distortion keeps the field of view; pincushion corners and the taller pixels need a zoom.
    assert zoom == 1.0 if k1 < 0 else zoom > 1.04
    expected = _pattern((u - scene.cx) / scene.focal, (v - scene.cy) / scene.focal)
    error = np.abs(scene.image(1).numpy() - expected)
    assert error.max() < 0.01 and error.mean() < 0.0015


def test_cameras_of_different_fields_of_view_share_the_narrowest(tmp_path):
    poses = orbit_rig(4)
    names = [f"{k}.png" for k in range(4)]
    write_photos(tmp_path / "images", names, W, H)
    cameras = {
        1: ("PINHOLE", W, H, (F, F, W / 2, H / 2)),
        2: ("SIMPLE_PINHOLE", W, H, (1.2 * F, W / 2, H / 2)),
    }
    write_colmap(
        tmp_path / "sparse",
        cameras,
        [(k + 1, poses[k], 1 + k % 2, names[k]) for k in range(4)],
        np.zeros((1, 3)),
    )
    scene = load_colmap(tmp_path, split="all")
    # The border pixel centres of the shared camera just reach the edge of the narrower photo.
    assert scene.focal == pytest.approx(1.2 * F * (W / 2 - 0.5) / (W / 2), rel=1e-5)


def test_non_integer_downscale_scales_images_and_intrinsics(tmp_path):
    photos = _capture(tmp_path, orbit_rig(3), np.zeros((1, 3)))
    scene = load_colmap(tmp_path, split="all", downscale=2.5)
    assert (scene.W, scene.H) == (16, 12)
    assert (scene.focal, scene.cx, scene.cy) == pytest.approx(
        (F / 2.5, (W / 2 + 0.5) / 2.5, (H / 2 - 0.25) / 2.5)
    )
    expected = downscale(photos["img_001.png"] / 255.0, 2.5)
    np.testing.assert_allclose(scene.image(1).numpy(), expected, atol=0.5 / 255 + 1e-6)


def _truncate(path: Path, keep: int) -> None:
    path.write_bytes(path.read_bytes()[:keep])


COLMAP_BREAKAGES = {
    "fisheye camera": (
        lambda r: write_colmap(
            r / "sparse" / "0",
            {7: ("OPENCV_FISHEYE", W, H, (F, F, 20.0, 15.0, 0, 0, 0, 0))},
            [(1, np.eye(4), 7, "img_000.png")],
            np.zeros((1, 3)),
        ),
        r"camera 7 uses COLMAP model OPENCV_FISHEYE, which is not supported \(supported: SIMPLE_PINHOLE",
    ),  # fmt: skip
    "truncated images.bin": (
        lambda r: _truncate(r / "sparse/0/images.bin", 50),
        r"images\.bin: malformed COLMAP file",
    ),
    "truncated points3D.bin": (
        lambda r: _truncate(r / "sparse/0/points3D.bin", 60),
        r"points3D\.bin: malformed",
    ),
    "trailing bytes": (
        lambda r: (r / "sparse/0/cameras.bin").write_bytes((r / "sparse/0/cameras.bin").read_bytes() + b"x"),
        r"cameras\.bin: 1 unexpected bytes",
    ),
    "unknown model id": (
        lambda r: (r / "sparse/0/cameras.bin").write_bytes(struct.pack("<QiiQQ", 1, 7, 99, W, H)),
        r"cameras\.bin: camera 7 has unknown model id 99",
    ),
    "missing camera": (
        lambda r: write_colmap(
            r / "sparse" / "0",
            {3: ("PINHOLE", W, H, (F, F, 20.0, 15.0))},
            [(1, np.eye(4), 7, "img_000.png")],
            np.zeros((1, 3)),
        ),
        r"image img_000\.png uses camera 7, which is not in the model",
    ),  # fmt: skip
    "no images": (
        lambda r: write_colmap(
            r / "sparse" / "0", {7: ("PINHOLE", W, H, (F, F, 20.0, 15.0))}, [], np.zeros((1, 3))
        ),
        r"no views \(the dataset is empty\)",
    ),
    "photo size": (
        lambda r: write_photos(r / "images", ["img_002.png"], W + 2, H),
        r"img_002\.png: image is 42x30 but its camera is 40x30",
    ),
    "folding distortion": (
        lambda r: write_colmap(
            r / "sparse" / "0",
            {7: ("SIMPLE_RADIAL", W, H, (F, 20.0, 15.0, -1.5))},
            [(1, np.eye(4), 7, "img_000.png")],
            np.zeros((1, 3)),
        ),
        r"distortion k1=-1\.5, k2=0 folds over within the image",
    ),  # fmt: skip
    "corrupt photo": (
        lambda r: (r / "images/img_001.png").write_bytes(b"nope"),
        r"img_001\.png: cannot decode",
    ),
}


@pytest.mark.parametrize("breakage", COLMAP_BREAKAGES)
def test_colmap_errors_name_file_and_problem(tmp_path, breakage):
    _capture(tmp_path, orbit_rig(4), np.zeros((3, 3)))
    breaker, message = COLMAP_BREAKAGES[breakage]
    breaker(tmp_path)
    with pytest.raises(DatasetError, match=message) as info:
        load_colmap(tmp_path, split="all")
    assert str(tmp_path) in str(info.value) and "\n" not in str(info.value)


def test_colmap_text_errors_and_missing_files(tmp_path):
    _capture(tmp_path, orbit_rig(4), np.zeros((3, 3)), binary=False)
    cameras = tmp_path / "sparse/0/cameras.txt"
    cameras.write_text("7 PINHOLE 40 30 36.0 36.0 20.0\n")
    with pytest.raises(
        DatasetError, match=r"cameras\.txt: camera 7 \(PINHOLE\) has 3 parameters, expected 4"
    ):
        load_colmap(tmp_path)
    cameras.write_text("7 PINHOLE 40 30 36.0 36.0 20.0 fifteen\n")
    with pytest.raises(DatasetError, match=r"cameras\.txt: malformed COLMAP file \(ValueError"):
        load_colmap(tmp_path)
    (tmp_path / "images/img_003.png").unlink()
    cameras.write_text("7 PINHOLE 40 30 36.0 36.0 20.0 15.0\n")
    with pytest.raises(MissingFileError, match=r"img_003\.png: image file not found"):
        load_colmap(tmp_path, split="all")
    (tmp_path / "sparse/0/points3D.txt").unlink()
    with pytest.raises(MissingFileError, match=r"no COLMAP model in sparse/0/, sparse/ or the folder itself"):
        load_colmap(tmp_path)
    with pytest.raises(DatasetError, match="unknown scene format"):
        detect_format(tmp_path)
