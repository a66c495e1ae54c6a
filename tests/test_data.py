"""Scene loaders (Blender, LLFF, procedural), rays, NDC, and loader error reporting."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from capture_files import write_blender_scene

import mixer_nerf.data as data
from mixer_nerf.data import (
    DatasetError,
    MissingFileError,
    camera_rays,
    ensure_procedural_scene,
    load_blender,
    load_llff,
    load_scene,
    load_split,
    ndc_rays,
)
from mixer_nerf.data.images import check_downscale, downscaled_size
from mixer_nerf.data.images import downscale as downscale_image
from mixer_nerf.data.llff import BD_FACTOR, average_pose, llff_to_opengl, recenter_poses, split_indices
from mixer_nerf.data.procedural import render
from mixer_nerf.train.sampler import RaySampler

LLFF_FACTOR = 4  # the llff_scene fixture provides images_4/


# ---------------------------------------------------------------- rays


def test_camera_rays_known_pixel_direction():
    origins, dirs = camera_rays(4, 6, 2.0, torch.eye(4))
    assert origins.shape == dirs.shape == (4, 6, 3)
    # Pixel (col 0, row 0) has its centre at (0.5, 0.5); principal point (3, 2).
    torch.testing.assert_close(dirs[0, 0], torch.tensor([-1.25, 0.75, -1.0]))
    torch.testing.assert_close(dirs[3, 5], torch.tensor([1.25, -0.75, -1.0]))
    assert torch.count_nonzero(origins) == 0


def test_camera_rays_apply_pose_and_batch():
    c2w = torch.eye(4)
    c2w[:3, :3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # yaw +90 deg
    c2w[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    o, d = camera_rays(3, 3, 1.0, c2w, cx=1.0, cy=1.0)
    # Pixel (1, 1) sits at (1.5, 1.5): camera direction (0.5, -0.5, -1) rotated by c2w.
    torch.testing.assert_close(d[1, 1], c2w[:3, :3] @ torch.tensor([0.5, -0.5, -1.0]))
    torch.testing.assert_close(o[1, 1], c2w[:3, 3])
    ob, db = camera_rays(3, 3, 1.0, torch.stack([torch.eye(4), c2w]), cx=1.0, cy=1.0)
    assert db.shape == (2, 3, 3, 3)
    torch.testing.assert_close(db[1], d)
    torch.testing.assert_close(ob[1], o)


def test_ndc_maps_near_plane_to_minus_one_and_infinity_to_one():
    o = torch.zeros(1, 3)
    d = torch.tensor([[0.0, 0.0, -1.0]])
    o_ndc, d_ndc = ndc_rays(10, 10, 5.0, 1.0, o, d)
    torch.testing.assert_close(o_ndc, torch.tensor([[0.0, 0.0, -1.0]]))
    torch.testing.assert_close(o_ndc + d_ndc, torch.tensor([[0.0, 0.0, 1.0]]))


def test_ndc_rays_pass_through_projected_world_points():
    H, W, focal, near = 12, 16, 10.0, 1.0
    torch.manual_seed(0)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    o, d = (x.reshape(-1, 3) for x in camera_rays(H, W, focal, c2w))
    o_ndc, d_ndc = ndc_rays(H, W, focal, near, o, d)
    for t in (2.0, 5.0, 40.0):
        p = o + t * d
        proj = torch.stack(
            [-2 * focal / W * p[:, 0] / p[:, 2], -2 * focal / H * p[:, 1] / p[:, 2], 1 + 2 * near / p[:, 2]],
            -1,
        )
        s = (proj[:, 2] - o_ndc[:, 2]) / d_ndc[:, 2]
        assert ((s > 0) & (s < 1)).all()
        torch.testing.assert_close(o_ndc + s[:, None] * d_ndc, proj)


# ---------------------------------------------------------------- Scene


def _scene(ndc: bool = False) -> data.Scene:
    torch.manual_seed(0)
    poses = torch.eye(4).repeat(2, 1, 1)
    poses[1, :3, 3] = torch.tensor([0.5, 0.0, 1.0])
    return data.Scene(
        images=torch.rand(2, 3, 5, 3), poses=poses, H=3, W=5, focal=4.0, cx=2.5, cy=1.5,
        near=0.0, far=1.0, ndc=ndc,
    )  # fmt: skip


@pytest.mark.parametrize("ndc", [False, True])
def test_scene_rays_agree_between_access_paths(ndc):
    scene = _scene(ndc)
    o_all, d_all, rgb = scene.all_rays()
    assert o_all.shape == d_all.shape == rgb.shape == (2 * 3 * 5, 3)
    o1, d1 = scene.rays_for_image(1)
    torch.testing.assert_close(o_all[15:], o1)
    torch.testing.assert_close(d_all[15:], d1)
    img, pix = torch.tensor([1, 0, 1]), torch.tensor([0, 7, 14])
    o, d = scene.rays_at(img, pix)
    flat = img * 15 + pix
    torch.testing.assert_close(o, o_all[flat])
    torch.testing.assert_close(d, d_all[flat])
    torch.testing.assert_close(scene.colors_at(img, pix), rgb[flat])
    torch.testing.assert_close(rgb[flat[2]], scene.images[1, 2, 4])


def test_scene_ndc_override_gives_world_rays():
    scene = _scene(ndc=True)
    o, d = scene.rays_for_image(0, ndc=False)
    o_ref, d_ref = _scene(ndc=False).rays_for_image(0)
    torch.testing.assert_close(o, o_ref)
    torch.testing.assert_close(d, d_ref)
    o_ndc, _ = scene.rays_for_image(0)
    torch.testing.assert_close(o_ndc[:, 2], torch.full((15,), -1.0))  # all start on the near plane


def _uint8_scene() -> data.Scene:
    scene = _scene()
    generator = torch.Generator().manual_seed(1)
    images = torch.randint(0, 256, (2, 3, 5, 3), dtype=torch.uint8, generator=generator)
    return dataclasses.replace(scene, images=images)


def test_uint8_images_read_as_float_through_every_access_path():
    scene = _uint8_scene().to("cpu")
    assert scene.images.dtype == torch.uint8 and scene.device == torch.device("cpu")
    expected = scene.images.float() / 255
    img, pix = torch.tensor([1, 0, 1]), torch.tensor([0, 7, 14])
    colors = scene.colors_at(img, pix)
    assert colors.dtype == torch.float32
    torch.testing.assert_close(colors, expected.reshape(2, 15, 3)[img, pix], rtol=0, atol=0)
    torch.testing.assert_close(scene.image(1), expected[1], rtol=0, atol=0)
    torch.testing.assert_close(scene.all_rays()[2], expected.reshape(-1, 3), rtol=0, atol=0)
    o, d, rgb = RaySampler(scene, batch_rays=64, seed=0).sample()
    assert o.dtype == d.dtype == rgb.dtype == torch.float32 and rgb.shape == (64, 3)
    assert ((rgb * 255).round() == rgb * 255).all() and 0 <= rgb.min() and rgb.max() <= 1
    with pytest.raises(ValueError, match="uint8 or float32"):
        dataclasses.replace(scene, images=scene.images.double())


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")
def test_cuda_scene_keeps_images_pinned_on_the_host_and_sends_pixels(monkeypatch):
    assert _uint8_scene().to("cuda").images.is_cuda  # small captures go to the GPU whole
    # a capture larger than a quarter of the GPU's free memory stays on the host
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda device=None: (16, 1 << 30))
    scene = _uint8_scene().to("cuda")
    assert scene.images.device.type == "cpu" and scene.images.is_pinned()
    assert scene.images.dtype == torch.uint8
    assert scene.poses.is_cuda and scene.device.type == "cuda"
    img = torch.tensor([1, 0, 1], device="cuda")
    pix = torch.tensor([0, 7, 14], device="cuda")
    colors = scene.colors_at(img, pix)
    assert colors.is_cuda and colors.dtype == torch.float32
    torch.testing.assert_close(colors.cpu(), _uint8_scene().colors_at(img.cpu(), pix.cpu()))
    assert scene.image(0).is_cuda
    sampler = RaySampler(scene, batch_rays=32, seed=0)
    assert all(t.is_cuda and t.dtype == torch.float32 for t in sampler.sample())


def test_fractional_downscale_averages_exact_footprints():
    img = np.random.default_rng(0).uniform(size=(10, 15, 3))
    # Averaging 2.5 x 2.5 footprints is averaging 5 x 5 blocks of the image doubled in size.
    doubled = np.repeat(np.repeat(img, 2, axis=0), 2, axis=1)
    np.testing.assert_allclose(downscale_image(img, 2.5), downscale_image(doubled, 5), atol=1e-12)
    assert downscale_image(img, 4.5).shape == (2, 3, 3)  # partial footprints at the edges are dropped
    assert downscaled_size(15, 4.5) == 3 and downscaled_size(15, 2.5) == 6
    for bad in (0.5, float("nan"), float("inf"), "2", True):
        with pytest.raises(ValueError, match="downscale must be a number >= 1"):
            check_downscale(bad)


def test_blender_and_llff_take_fractional_downscales(blender_scene, llff_scene):
    full = load_blender(blender_scene)
    small = load_blender(blender_scene, downscale=2.5)
    assert (small.H, small.W) == (3, 3)
    # Pixel coordinates scale by 1 / 2.5: the cropped 7.5-pixel image keeps the principal point.
    assert (small.focal, small.cx, small.cy) == pytest.approx((full.focal / 2.5, 1.6, 1.6))
    expected = downscale_image(full.images[1].numpy(), 2.5)
    np.testing.assert_allclose(small.images[1].numpy(), expected, atol=1e-6)
    llff = load_llff(llff_scene, factor=LLFF_FACTOR, downscale=2.5)
    ref = load_llff(llff_scene, factor=LLFF_FACTOR)
    assert (llff.H, llff.W) == (3, 4) and llff.images.dtype == torch.uint8
    assert (llff.focal, llff.cx, llff.cy) == pytest.approx((ref.focal / 2.5, 6 / 2.5, 4 / 2.5))
    expected = downscale_image(ref.image(0).numpy(), 2.5)
    np.testing.assert_allclose(llff.image(0).numpy(), expected, atol=0.5 / 255 + 1e-6)  # rounded to 8 bits


def test_scene_rejects_inconsistent_shapes():
    with pytest.raises(ValueError, match="poses"):
        data.Scene(torch.zeros(2, 3, 5, 3), torch.zeros(3, 4, 4), 3, 5, 1.0, 2.5, 1.5, 2.0, 6.0)


# ---------------------------------------------------------------- Blender


def _composited_png(path: Path, bg: float) -> np.ndarray:
    rgba = iio.imread(path).astype(np.float32) / 255.0
    return rgba[..., :3] * rgba[..., 3:] + bg * (1.0 - rgba[..., 3:])


def test_blender_loads_poses_images_and_conventions(blender_scene):
    meta = json.loads((blender_scene / "transforms_train.json").read_text())
    scene = load_blender(blender_scene, "train", background="black")
    assert len(scene) == 3 and (scene.H, scene.W) == (8, 8)
    np.testing.assert_allclose(
        scene.poses.numpy(), [f["transform_matrix"] for f in meta["frames"]], atol=1e-6
    )
    assert scene.focal == pytest.approx(4.0 / math.tan(0.345))
    np.testing.assert_allclose(
        scene.images[1].numpy(), _composited_png(blender_scene / "train/r_1.png", 0.0), atol=1e-6
    )
    assert (scene.near, scene.far, scene.ndc, scene.split) == (2.0, 6.0, False, "train")
    assert scene.bbox.tolist() == [[-1.5] * 3, [1.5] * 3]
    assert scene.image_paths[2] == blender_scene / "train" / "r_2.png"
    white = load_blender(blender_scene, "test")
    assert len(white) == 2 and white.background.tolist() == [1.0, 1.0, 1.0]
    np.testing.assert_allclose(
        white.images[0].numpy(), _composited_png(blender_scene / "test/r_0.png", 1.0), atol=1e-6
    )


def test_blender_downscale_averages_areas(blender_scene):
    full = load_blender(blender_scene, downscale=1)
    half = load_blender(blender_scene, downscale=2)
    assert (half.H, half.W) == (4, 4) and half.focal == pytest.approx(full.focal / 2)
    torch.testing.assert_close(half.images[0, 1, 2], full.images[0, 2:4, 4:6].mean(dim=(0, 1)))
    with pytest.raises(DatasetError, match="not divisible"):
        load_blender(blender_scene, downscale=3)


def _edit_json(root: Path, edit) -> None:
    path = root / "transforms_train.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


BLENDER_BREAKAGES = {
    "malformed JSON": (lambda r: (r / "transforms_train.json").write_text("{ not json"), "not valid JSON"),
    "no camera_angle_x": (lambda r: _edit_json(r, lambda m: m.pop("camera_angle_x")), "camera_angle_x"),
    "no frames": (lambda r: _edit_json(r, lambda m: m.pop("frames")), "'frames'"),
    "no file_path": (
        lambda r: _edit_json(r, lambda m: m["frames"][1].pop("file_path")),
        r"frames\[1\].*file_path",
    ),
    "no matrix": (
        lambda r: _edit_json(r, lambda m: m["frames"][0].pop("transform_matrix")),
        "transform_matrix",
    ),
    "3x3 pose": (
        lambda r: _edit_json(r, lambda m: m["frames"][2].update(transform_matrix=np.eye(3).tolist())),
        r"frames\[2\].transform_matrix must be 4x4",
    ),
    "empty": (lambda r: _edit_json(r, lambda m: m.update(frames=[])), "empty"),
    "size mismatch": (
        lambda r: iio.imwrite(r / "train/r_1.png", np.zeros((4, 4, 4), np.uint8)),
        r"r_1\.png.*one size",
    ),
    "corrupt image": (
        lambda r: (r / "train/r_0.png").write_bytes(b"not a png at all"),
        r"r_0\.png: cannot decode",
    ),
}


@pytest.mark.parametrize("breakage", BLENDER_BREAKAGES)
def test_blender_errors_name_file_and_problem(blender_scene, breakage):
    breaker, message = BLENDER_BREAKAGES[breakage]
    breaker(blender_scene)
    with pytest.raises(DatasetError, match=message) as info:
        load_blender(blender_scene)
    assert str(blender_scene) in str(info.value)


def test_blender_missing_files(blender_scene):
    with pytest.raises(FileNotFoundError, match=r"transforms_val\.json"):
        load_blender(blender_scene, "val")
    (blender_scene / "train" / "r_2.png").unlink()
    with pytest.raises(MissingFileError, match=r"r_2\.png"):
        load_blender(blender_scene)


# ---------------------------------------------------------------- LLFF


def test_llff_axis_conversion_on_known_pose():
    # An LLFF camera whose "down" is world -y, "right" world +x and "back" world +z is the
    # OpenGL camera with identity rotation.
    llff = np.array([[0.0, 1.0, 0.0, 5.0], [-1.0, 0.0, 0.0, 6.0], [0.0, 0.0, 1.0, 7.0]])
    expected = np.eye(4)
    expected[:3, 3] = [5.0, 6.0, 7.0]
    np.testing.assert_allclose(llff_to_opengl(llff), expected)


def test_recentred_poses_average_to_identity(llff_scene):
    gl = llff_to_opengl(np.load(llff_scene / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)[:, :, :4])
    np.testing.assert_allclose(average_pose(recenter_poses(gl)), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(recenter_poses(gl[:1]), np.eye(4)[None], atol=1e-12)


def test_llff_poses_round_trip_up_to_the_documented_similarity(llff_scene):
    arr = np.load(llff_scene / "poses_bounds.npy")
    m = arr[:, :15].reshape(-1, 3, 5)
    gl = np.zeros((len(m), 4, 4))
    gl[:, :3, :] = np.stack([m[:, :, 1], -m[:, :, 0], m[:, :, 2], m[:, :, 3]], -1)
    gl[:, 3, 3] = 1
    scale = 1.0 / (BD_FACTOR * arr[:, 15:].min())
    scene = load_llff(llff_scene, factor=LLFF_FACTOR, split="all", ndc=False)
    poses = scene.poses.double().numpy()
    # Recentring is one rigid transform for all views, so relative poses survive (scaled).
    for i, j in [(0, 1), (3, 9)]:
        rel_loaded = np.linalg.inv(poses[i]) @ poses[j]
        rel_true = np.linalg.inv(gl[i]) @ gl[j]
        np.testing.assert_allclose(rel_loaded[:3, :3], rel_true[:3, :3], atol=1e-5)
        np.testing.assert_allclose(rel_loaded[:3, 3], scale * rel_true[:3, 3], atol=1e-5)
    np.testing.assert_allclose(poses[:, :3, 3].mean(0), 0.0, atol=1e-5)
    assert scene.near == pytest.approx(0.9 / BD_FACTOR) and scene.far == pytest.approx(29 * scale)
    assert scene.bbox is None


def test_llff_intrinsics_ndc_and_holdout(llff_scene):
    train = load_llff(llff_scene, factor=LLFF_FACTOR)
    test = load_llff(llff_scene, factor=LLFF_FACTOR, split="test")
    full_focal = np.load(llff_scene / "poses_bounds.npy")[0, 14]
    assert (train.H, train.W) == (8, 12) and train.focal == pytest.approx(full_focal / LLFF_FACTOR)
    assert [p.name for p in test.image_paths] == ["img_000.png", "img_008.png"]
    assert len(train) == 8 and "img_008.png" not in {p.name for p in train.image_paths}
    assert len(load_llff(llff_scene, factor=LLFF_FACTOR, split="all", holdout=0)) == 10
    expected = iio.imread(llff_scene / "images_4/img_003.png").astype(np.float32) / 255
    np.testing.assert_allclose(train.image(2).numpy(), expected, atol=1e-6)
    assert train.images.dtype == torch.uint8
    assert train.ndc and (train.near, train.far) == (0.0, 1.0)
    assert train.bbox.tolist() == [[-1.0] * 3, [1.0] * 3]
    o, _ = train.rays_for_image(0)
    torch.testing.assert_close(o[:, 2], torch.full((96,), -1.0))
    with pytest.raises(DatasetError, match="empty"):
        load_llff(llff_scene, factor=LLFF_FACTOR, split="test", holdout=0)


def _save_rows(root: Path, rows: np.ndarray) -> None:
    np.save(root / "poses_bounds.npy", rows)


LLFF_BREAKAGES = {
    "wrong pose shape": (
        lambda r: _save_rows(r, np.load(r / "poses_bounds.npy")[:, :15]),
        r"poses_bounds\.npy.*\(N, 17\)",
    ),
    "empty": (lambda r: _save_rows(r, np.zeros((0, 17))), r"poses_bounds\.npy.*empty"),
    "corrupt npy": (
        lambda r: (r / "poses_bounds.npy").write_bytes(b"garbage"),
        r"poses_bounds\.npy: cannot read",
    ),
    "image count": (
        lambda r: (r / "images_4/img_009.png").unlink(),
        r"images_4: holds 9 images but .* 10 poses",
    ),
    "size vs hwf": (
        lambda r: _save_rows(r, np.load(r / "poses_bounds.npy") * np.r_[[1.0] * 4, 2.0, [1.0] * 12]),
        r"img_001\.png: image is 12x8.*factor 4",
    ),
    "size mismatch": (
        lambda r: iio.imwrite(r / "images_4/img_003.png", np.zeros((8, 10, 3), np.uint8)),
        r"img_003\.png.*one size",
    ),
    "corrupt image": (
        lambda r: (r / "images_4/img_005.png").write_bytes(b"\x89PNG broken"),
        r"img_005\.png: cannot decode",
    ),
}


@pytest.mark.parametrize("breakage", LLFF_BREAKAGES)
def test_llff_errors_name_file_and_problem(llff_scene, breakage):
    breaker, message = LLFF_BREAKAGES[breakage]
    breaker(llff_scene)
    with pytest.raises(DatasetError, match=message):
        load_llff(llff_scene, factor=LLFF_FACTOR)


def test_llff_missing_files(llff_scene):
    with pytest.raises(MissingFileError, match="images_2"):
        load_llff(llff_scene, factor=2)
    (llff_scene / "poses_bounds.npy").unlink()
    with pytest.raises(FileNotFoundError, match=r"poses_bounds\.npy"):
        load_llff(llff_scene, factor=LLFF_FACTOR)


# ---------------------------------------------------------------- procedural scene and load_scene


def test_procedural_scene_generates_caches_and_loads(tmp_path, monkeypatch):
    monkeypatch.setenv("MIXER_NERF_CACHE", str(tmp_path))
    start = time.perf_counter()
    root = ensure_procedural_scene(resolution=(16, 20), n_train=6, n_val=2, n_test=3)
    assert time.perf_counter() - start < 3.0
    assert root.parent == tmp_path / "procedural"
    assert ensure_procedural_scene(resolution=(16, 20), n_train=6, n_val=2, n_test=3) == root
    assert ensure_procedural_scene(resolution=16, n_train=6, n_val=2, n_test=3) != root
    assert not list(root.parent.glob(".*"))  # no leftover temporary folders
    scene = load_scene(root, split="test")
    assert len(scene) == 3 and (scene.H, scene.W) == (16, 20)
    alpha = iio.imread(root / "train/r_0.png")[..., 3]
    assert alpha.min() == 0 and alpha.max() == 255 and ((alpha > 0) & (alpha < 255)).any()
    cam = scene.poses[:, :3, 3]
    torch.testing.assert_close(cam.norm(dim=-1), torch.full((3,), 4.0))
    assert (cam[:, 2] > 0).all()
    # Every camera looks at the origin: its central ray passes through it.
    torch.testing.assert_close(
        torch.linalg.cross(-cam, -scene.poses[:, :3, 2]), torch.zeros(3, 3), atol=1e-5, rtol=0
    )


def test_procedural_render_hits_the_sphere_from_above():
    c2w = np.eye(4)
    c2w[:3, 3] = [0.45, -0.35, 4.1]  # 4 above the sphere's centre, looking straight down
    rgba = render(16, 16, c2w)
    assert rgba.shape == (16, 16, 4) and rgba.dtype == np.float32
    assert (rgba[7:9, 7:9, 3] == 1.0).all()
    assert rgba[0, 0, 3] == rgba[-1, -1, 3] == 0.0
    assert (rgba[..., :3] >= 0).all() and (rgba[..., :3] <= 1).all()


def test_load_scene_detects_format(blender_scene, llff_scene, tmp_path, monkeypatch):
    assert load_scene(blender_scene).focal == load_blender(blender_scene).focal
    assert load_scene(llff_scene, factor=LLFF_FACTOR, split="test").ndc
    assert len(load_scene(llff_scene, format="llff", factor=LLFF_FACTOR, split="all")) == 10
    with pytest.raises(DatasetError, match="unknown scene format"):
        load_scene(tmp_path)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_scene(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="format"):
        load_scene(blender_scene, format="mesh")
    tiny = ensure_procedural_scene(resolution=8, n_train=2, n_val=1, n_test=1, cache_dir=tmp_path)
    monkeypatch.setattr(data, "ensure_procedural_scene", lambda: tiny)
    assert load_scene(None, split="val").image_paths[0].is_relative_to(tiny)


# ---------------------------------------------------------------- real data (optional)


def test_real_lego(shared_data):
    train = load_scene(shared_data / "lego_400")
    val = load_scene(shared_data / "lego_400", split="val")
    assert len(train) == 100 and len(val) == 25
    assert (val.H, val.W) == (400, 400) and val.focal == pytest.approx(
        0.5 * 400 / math.tan(0.5 * 0.6911112070083618)
    )
    assert 0.0 <= float(val.images.min()) and float(val.images.max()) <= 1.0
    # nerf_synthetic cameras look at the origin from ~4 units away.
    centre = val.H // 2 * val.W + val.W // 2
    o, d = val.rays_at(torch.arange(25), torch.full((25,), centre))
    closest = torch.linalg.cross(-o, d / d.norm(dim=-1, keepdim=True)).norm(dim=-1)
    assert (closest < 0.1).all() and ((o.norm(dim=-1) - 4.03).abs() < 0.1).all()


def test_real_fern(shared_data):
    scene = load_scene(shared_data / "fern_8", split="all")
    assert len(scene) == 20 and (scene.H, scene.W) == (378, 504)
    assert [p.name for p in load_scene(shared_data / "fern_8", split="test").image_paths] == [
        scene.image_paths[i].name for i in (0, 8, 16)
    ]
    assert len(load_scene(shared_data / "fern_8")) == 17
    np.testing.assert_allclose(average_pose(scene.poses.double().numpy()), np.eye(4), atol=1e-4)
    # Forward facing: every camera looks roughly down -z of the recentred frame.
    assert (scene.poses[:, 2, 2] > 0.9).all()
    o, d = scene.rays_for_image(3)
    assert torch.isfinite(o).all() and torch.isfinite(d).all()
    torch.testing.assert_close(o[:, 2], torch.full((378 * 504,), -1.0))  # all start on the near plane
    assert (d[:, 2] > 0).all() and ((o + d)[:, 2] - 1).abs().max() < 1e-5  # and end at infinity


@pytest.mark.parametrize("n, holdout, val_holdout", [(20, 8, 8), (10, 8, 3), (12, 4, 2), (9, 3, 5)])
def test_val_holdout_carves_a_val_split_out_of_train(n, holdout, val_holdout):
    splits = {s: split_indices(n, s, holdout, Path("x"), val_holdout) for s in ("train", "val", "test")}
    assert np.array_equal(splits["test"], split_indices(n, "test", holdout, Path("x")))  # test never moves
    assert not set(splits["val"]) & set(splits["test"]) and not set(splits["val"]) & set(splits["train"])
    assert sorted([*splits["train"], *splits["val"], *splits["test"]]) == list(range(n))
    assert np.array_equal(split_indices(n, "val", holdout, Path("x")), splits["test"])  # the default


def test_val_holdout_reaches_the_llff_loader(llff_scene):
    val = load_llff(llff_scene, factor=LLFF_FACTOR, split="val", val_holdout=4)
    train = load_llff(llff_scene, factor=LLFF_FACTOR, val_holdout=4)
    assert [p.name for p in val.image_paths] == ["img_001.png", "img_005.png"]  # every 4th of 1-7 and 9
    assert len(train) == 6 and not {p.name for p in val.image_paths} & {p.name for p in train.image_paths}
    with pytest.raises(ValueError, match="val_holdout must be >= 0"):
        split_indices(10, "val", 8, Path("x"), -1)
    with pytest.raises(DatasetError, match="split 'train' is empty"):  # every non-test view to val
        split_indices(10, "train", 8, Path("x"), 1)


@pytest.mark.parametrize("n_train, holdout", [(10, 4), (7, 3), (5, 2), (3, 8)])
@pytest.mark.parametrize("has_test", [True, False])
def test_val_holdout_carves_a_blender_val_split_out_of_train(tmp_path, n_train, holdout, has_test):
    """val: every K-th training view from the first, train the others; test: the scene's test views,
    or its own val views where it ships none (nothing was tuned on them)."""
    tests = {"test": 2} if has_test else {}
    root = write_blender_scene(tmp_path / "scene", size=4, train=n_train, val=3, **tests)

    def names(split: str, val_holdout: int = holdout) -> list[str]:
        scene = load_split(root, "blender", split, val_holdout=val_holdout)
        return [f"{p.parent.name}/{p.name}" for p in scene.image_paths]

    val, train = names("val"), names("train")
    assert val == [f"train/r_{k}.png" for k in range(0, n_train, holdout)]
    assert not set(val) & set(train) and len(val) + len(train) == n_train
    assert set(val) | set(train) == {f"train/r_{k}.png" for k in range(n_train)}
    shipped = [f"test/r_{k}.png" for k in range(2)] if has_test else [f"val/r_{k}.png" for k in range(3)]
    assert names("test") == shipped
    assert names("val", val_holdout=0) == [f"val/r_{k}.png" for k in range(3)]  # the default: as shipped


def test_a_blender_val_holdout_that_leaves_no_training_view_is_refused(tmp_path):
    root = write_blender_scene(tmp_path / "scene", size=4, train=1, val=1)
    with pytest.raises(DatasetError, match="val_holdout 2 leaves the 'train' split empty"):
        load_split(root, "blender", "train", val_holdout=2)
    with pytest.raises(ValueError, match="val_holdout must be >= 0"):
        load_split(root, "blender", "train", val_holdout=-1)


def test_subset_views_tool_trains_on_every_kth_view_and_keeps_the_held_out_ones(tmp_path):
    """tools/subset_views.py (the sparse-view screens): every K-th training view from the first, the
    other splits as they are, the images read from the source scene."""
    import importlib.util

    path = Path(__file__).parents[1] / "tools" / "subset_views.py"
    spec = importlib.util.spec_from_file_location("subset_views", path)
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    source = write_blender_scene(tmp_path / "scene", size=4, train=7, val=3, test=2)
    assert tool.subset_views(source, tmp_path / "subset", 3) == 3
    full, subset = load_split(source, "blender", "train"), load_split(tmp_path / "subset", "blender", "train")
    assert torch.equal(subset.images, full.images[::3]) and torch.equal(subset.poses, full.poses[::3])
    for split in ("val", "test"):
        assert torch.equal(load_split(tmp_path / "subset", "blender", split).images,
                           load_split(source, "blender", split).images)
    with pytest.raises(FileNotFoundError, match="no transforms_train.json"):
        tool.subset_views(tmp_path, tmp_path / "other", 2)
    with pytest.raises(ValueError, match="--every must be >= 1"):
        tool.subset_views(source, tmp_path / "other", 0)
