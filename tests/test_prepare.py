"""``mixer-nerf prepare``: poses of the procedural scene rendered as photos (with pycolmap), video
frames, and one-line errors for inputs it cannot use."""

from __future__ import annotations

import importlib.util
import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from mixer_nerf.cli import main
from mixer_nerf.data import load_scene
from mixer_nerf.data.images import write_png
from mixer_nerf.data.pose_alignment import pose_errors
from mixer_nerf.data.procedural import CAMERA_ANGLE_X, CAMERA_RADIUS, render
from mixer_nerf.data.rays import camera_rays
from mixer_nerf.prepare import PrepareError, extract_frames, prepare

needs_pycolmap = pytest.mark.skipif(
    importlib.util.find_spec("pycolmap") is None, reason="pycolmap not installed"
)
GROUND_Z = -0.8  # the procedural shapes stand on this plane
CELL = 0.2  # ground tiles: random colours give SIFT corners the procedural shapes alone lack


def _arc_poses(n: int, degrees: float) -> np.ndarray:
    """(n, 4, 4) OpenGL cameras on an arc at 35 degrees elevation, looking at the origin."""
    azimuth = np.radians(np.linspace(0.0, degrees, n))
    elevation = np.radians(35.0)
    back = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                     np.full(n, np.sin(elevation))], -1)  # fmt: skip
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right, axis=-1, keepdims=True)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :] = np.stack([right, np.cross(back, right), back, CAMERA_RADIUS * back], axis=-1)
    return poses


def _photo(size: int, c2w: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """The procedural scene over a tiled ground plane, as an opaque (size, size, 3) photo."""
    rgba = render(size, size, c2w)
    focal = 0.5 * size / math.tan(0.5 * CAMERA_ANGLE_X)
    o, d = (x.numpy() for x in camera_rays(size, size, focal, torch.from_numpy(c2w)))
    t = (GROUND_Z - o[..., 2]) / d[..., 2]
    cell = np.floor((o + t[..., None] * d)[..., :2] / CELL).astype(np.int64) % len(palette)
    ground = np.where((t > 0)[..., None], palette[cell[..., 0], cell[..., 1]], 0.5)
    return rgba[..., :3] * rgba[..., 3:] + ground * (1.0 - rgba[..., 3:])


@needs_pycolmap
def test_prepare_solves_the_poses_of_rendered_photos(tmp_path):
    poses = _arc_poses(12, 100.0)
    palette = np.random.default_rng(0).uniform(0.1, 0.9, (64, 64, 3))
    for k, c2w in enumerate(poses):
        write_png(tmp_path / "photos" / f"view_{k:02d}.png", _photo(192, c2w, palette))
    lines = []
    summary = prepare(tmp_path / "photos", tmp_path / "scene", log=lines.append)
    assert summary["registered"] == summary["images"] == 12 and summary["matcher"] == "exhaustive"
    assert [line[:5] for line in lines if line.startswith("[")] == [f"[{k}/5]" for k in range(1, 6)]
    scene = load_scene(tmp_path / "scene", split="all")
    assert len(scene) == 12 and scene.images.dtype == torch.uint8 and not scene.ndc  # a 100-degree arc
    assert [p.name for p in scene.image_paths] == [f"view_{k:02d}.png" for k in range(12)]
    errors = pose_errors(scene.poses.double().numpy(), poses)
    # 192-pixel views with a 40-degree field of view leave COLMAP some rotation/focal ambiguity.
    assert errors.rotation_degrees.max() < 5.0 and errors.centre_error.max() < 0.03 * CAMERA_RADIUS


@needs_pycolmap
def test_prepare_refuses_unusable_inputs(tmp_path):
    photos = tmp_path / "photos"
    for k in range(2):
        write_png(photos / f"{k}.png", np.full((16, 16, 3), 0.5))
    with pytest.raises(PrepareError, match=r"photos: 2 image\(s\); COLMAP needs at least 3"):
        prepare(photos, tmp_path / "out", log=lambda _: None)
    assert not (tmp_path / "out").exists()  # nothing left behind to block a retry
    with pytest.raises(PrepareError, match="a single image"):
        prepare(photos / "0.png", tmp_path / "out", log=lambda _: None)
    with pytest.raises(FileNotFoundError, match="no such folder or video"):
        prepare(tmp_path / "nowhere", tmp_path / "out", log=lambda _: None)
    with pytest.raises(PrepareError, match="exists and is not empty"):
        prepare(photos, tmp_path, log=lambda _: None)


@needs_pycolmap
def test_prepare_reports_failed_registration(tmp_path):
    rng = np.random.default_rng(0)
    for k in range(4):  # unrelated noise: features, but no consistent geometry
        write_png(tmp_path / "noise" / f"{k}.png", rng.uniform(size=(64, 64, 3)))
    with pytest.raises(
        PrepareError, match=r"^COLMAP registered \d of 4 images in one model \(needs 3\); try "
    ) as info:
        prepare(tmp_path / "noise", tmp_path / "out", log=lambda _: None)
    assert "\n" not in str(info.value)


@pytest.mark.skipif(importlib.util.find_spec("imageio_ffmpeg") is None, reason="imageio-ffmpeg not installed")
def test_video_frames_are_taken_every_kth(tmp_path):
    frames = np.zeros((10, 32, 48, 3), np.uint8)
    frames[:, :, :, 0] = np.arange(10)[:, None, None] * 25  # a red ramp over time
    iio.imwrite(tmp_path / "clip.mp4", frames, plugin="FFMPEG", fps=10)
    names = extract_frames(tmp_path / "clip.mp4", tmp_path / "frames", every=3)
    assert names == ["frame_00000.jpg", "frame_00003.jpg", "frame_00006.jpg", "frame_00009.jpg"]
    reds = [iio.imread(tmp_path / "frames" / n)[..., 0].mean() for n in names]
    assert reds == pytest.approx([0, 75, 150, 225], abs=8)


def test_undecodable_video_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "clip.mp4").write_bytes(b"not a video at all")
    with pytest.raises(PrepareError, match=r"clip\.mp4: cannot decode as a video"):
        extract_frames(tmp_path / "clip.mp4", tmp_path / "frames", every=1)
    assert main(["prepare", str(tmp_path / "clip.mp4"), str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("mixer-nerf: error: ") and "\n" not in err
