"""Camera paths: nerfstudio's camera-path JSON (frames and interpolated keyframes), the dataset's
own cameras, and ``render --path`` with each."""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from mixer_nerf import cli
from mixer_nerf.render.camera_path import CameraPathError, read_nerfstudio_path
from mixer_nerf.train import load_checkpoint

RENDER_FLAGS = ["--backend", "torch", "--device", "cpu"]


def pose(rotation: np.ndarray, position) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, position
    return m


def write(tmp_path, spec, name="path.json"):
    path = tmp_path / name
    path.write_text(json.dumps(spec))
    return path


def test_camera_path_frames_are_used_as_they_are(tmp_path):
    a, b = pose(np.eye(3), [0, 0, 4]), pose(Rotation.from_euler("z", 30, degrees=True).as_matrix(), [1, 2, 3])
    spec = {
        "render_height": 30,
        "render_width": 40,
        "camera_path": [{"camera_to_world": m.ravel().tolist(), "fov": 60, "aspect": 4 / 3} for m in (a, b)],
    }
    cams = read_nerfstudio_path(write(tmp_path, spec))
    assert (len(cams), cams.H, cams.W, cams.cx, cams.cy) == (2, 30, 40, 20.0, 15.0)
    torch.testing.assert_close(cams.poses, torch.tensor(np.stack([a, b]), dtype=torch.float32))
    assert cams.focals[0].item() == pytest.approx(15 / math.tan(math.radians(30)))


def test_keyframes_are_interpolated_to_seconds_times_fps(tmp_path):
    quarter = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    keys = [pose(np.eye(3), [0, 0, 4]), pose(quarter, [4, 0, 0])]
    spec = {
        "render_height": 8,
        "render_width": 8,
        "seconds": 1,
        "fps": 5,
        "keyframes": [
            {"matrix": json.dumps(keys[0].T.ravel().tolist()), "fov": 40},  # column-major
            {"matrix": keys[1].T.ravel().tolist(), "fov": 60},
        ],
    }
    cams = read_nerfstudio_path(write(tmp_path, spec))
    assert len(cams) == 5
    torch.testing.assert_close(cams.poses[[0, -1]].double(), torch.tensor(np.stack(keys)), atol=1e-6, rtol=0)
    middle = cams.poses[2].double().numpy()
    half = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    np.testing.assert_allclose(middle[:3, :3], half, atol=1e-6)
    np.testing.assert_allclose(middle[:3, 3], [2, 0, 2], atol=1e-6)
    assert cams.focals[2].item() == pytest.approx(4 / math.tan(math.radians(25)), rel=1e-5)


@pytest.mark.parametrize(
    "spec, message",
    [
        ([1, 2], "expected a JSON object"),
        ({"render_width": 8, "camera_path": []}, "'render_height' must be a positive integer"),
        ({"render_height": 8, "render_width": 8}, "needs a non-empty 'camera_path' or 'keyframes'"),
        (
            {"render_height": 8, "render_width": 8, "camera_path": [{"camera_to_world": [1, 2], "fov": 50}]},
            "camera_path[0].camera_to_world must be 16 finite numbers",
        ),
        (
            {
                "render_height": 8,
                "render_width": 8,
                "camera_path": [{"camera_to_world": [2.0] * 16, "fov": 50}],
            },
            "does not hold a rotation",
        ),
        (
            {
                "render_height": 8,
                "render_width": 8,
                "camera_path": [{"camera_to_world": np.eye(4).ravel().tolist(), "fov": 180}],
            },
            "field of view in (0, 180)",
        ),
        (
            {
                "render_height": 8,
                "render_width": 8,
                "fps": 30,
                "keyframes": [{"matrix": np.eye(4).ravel().tolist(), "fov": 50}],
            },
            "'seconds' must be a positive number",
        ),
    ],
)
def test_bad_schemas_name_the_file_and_the_field(tmp_path, spec, message):
    path = write(tmp_path, spec)
    with pytest.raises(CameraPathError) as info:
        read_nerfstudio_path(path)
    assert str(info.value).startswith(str(path)) and message in str(info.value)


def test_unreadable_files(tmp_path):
    with pytest.raises(CameraPathError, match="cannot read"):
        read_nerfstudio_path(tmp_path / "missing.json")
    with pytest.raises(CameraPathError, match="not valid JSON"):
        read_nerfstudio_path(_text(tmp_path / "bad.json", "{"))


def _text(path, text):
    path.write_text(text)
    return path


def render(ckpt, out, *argv):
    return cli.main(["render", "--ckpt", str(ckpt), "--out", str(out), *argv, *RENDER_FLAGS])


def test_render_along_the_dataset_cameras_and_the_same_cameras_from_a_file(
    tiny_occupancy_run, tmp_path, capsys
):
    ckpt = tiny_occupancy_run / "checkpoint.pt"
    scene = load_checkpoint(ckpt)["scene"]
    assert render(ckpt, tmp_path / "train", "--path", "train") == 0
    assert "video (train, 4 frames" in capsys.readouterr().out
    fov = math.degrees(2 * math.atan(scene["H"] / 2 / scene["focal"]))
    spec = {
        "render_height": scene["H"],
        "render_width": scene["W"],
        "camera_path": [{"camera_to_world": p.ravel().tolist(), "fov": fov} for p in scene["train_poses"]],
    }
    assert render(ckpt, tmp_path / "file", "--path", str(write(tmp_path, spec, "train_path.json"))) == 0
    for i in range(4):
        a = iio.imread(tmp_path / "train" / "depth" / f"frame_{i:04d}.png").astype(int)
        b = iio.imread(tmp_path / "file" / "depth" / f"frame_{i:04d}.png").astype(int)
        assert np.abs(a - b).max() <= 1  # the file's float32 fov round trip
    assert render(ckpt, tmp_path / "test", "--path", "test", "--scale", "0.5") == 0
    frames = sorted((tmp_path / "test" / "depth").glob("frame_*.png"))
    assert len(frames) == 4 and iio.imread(frames[0]).shape[:2] == (8, 8)


def test_render_refuses_a_bad_camera_path_in_one_line(tiny_occupancy_run, tmp_path, capsys):
    path = write(tmp_path, {"render_height": 8, "render_width": 8, "camera_path": "none"})
    assert render(tiny_occupancy_run / "checkpoint.pt", tmp_path / "o", "--path", str(path)) == 1
    err = capsys.readouterr().err
    assert "'camera_path' must be a list" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()
    with pytest.raises(SystemExit) as info:
        cli.main(["render", "--ckpt", "x", "--path", "path.yaml"])
    assert info.value.code == 2


def test_dataset_paths_of_a_run_with_a_carved_val_split_are_the_views_its_eval_scores(tmp_path):
    """A Blender run with --val-holdout: "test" is the scene's own val views when it ships no test
    split, "val" every K-th training view, as eval scores them."""
    from types import SimpleNamespace

    from capture_files import write_blender_scene
    from mixer_nerf.data import load_split
    from mixer_nerf.train import TrainConfig
    from mixer_nerf.video import path_cameras

    root = write_blender_scene(tmp_path / "scene", train=6, val=2)
    run = SimpleNamespace(cfg=TrainConfig(data=str(root), val_holdout=4), scene={})
    test, val = path_cameras(run, "test", 0), path_cameras(run, "val", 0)
    torch.testing.assert_close(test.poses, load_split(root, "blender", "val").poses)
    torch.testing.assert_close(val.poses, load_split(root, "blender", "train").poses[::4])
