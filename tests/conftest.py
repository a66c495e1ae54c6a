"""Shared fixtures: tiny generated scenes in both formats, and the optional real data."""

from __future__ import annotations

import os
import random

# MIXER_NERF_TEST_GPUS=N spreads pytest-xdist workers over N GPUs (worker k sees GPU k mod N); it
# must be set before anything initialises CUDA, hence before the imports below.
_gpus, _worker = int(os.environ.get("MIXER_NERF_TEST_GPUS") or 0), os.environ.get("PYTEST_XDIST_WORKER", "")
if _gpus > 1 and _worker.startswith("gw"):
    os.environ["CUDA_VISIBLE_DEVICES"] = str(int(_worker[2:]) % _gpus)

from collections.abc import Iterator  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from mixer_nerf.data.blender import write_blender_split  # noqa: E402
from mixer_nerf.data.images import write_png  # noqa: E402
from mixer_nerf.data.procedural import orbit_poses  # noqa: E402

LLFF_HWF = (32.0, 48.0, 40.0)  # full-resolution H, W, focal of the llff_scene fixture
LLFF_FACTOR = 4  # its images are in images_4/


@pytest.fixture
def gen() -> torch.Generator:
    """A CPU generator seeded afresh each run (inputs drawn new every time), its seed printed so
    that pytest shows it when a test fails."""
    seed = random.getrandbits(32)
    print(f"seed={seed}")
    return torch.Generator().manual_seed(seed)


@pytest.fixture
def blender_scene(tmp_path: Path) -> Path:
    """Blender scene with splits train (3 views) and test (2), 8x8 random RGBA images, cameras on
    a sphere of radius 4 looking at the origin."""
    rng = np.random.default_rng(0)
    root = tmp_path / "blender"
    for seed, (split, n) in enumerate((("train", 3), ("test", 2))):
        write_blender_split(root, split, rng.uniform(size=(n, 8, 8, 4)), orbit_poses(n, seed), 0.69)
    return root


@pytest.fixture
def llff_scene(tmp_path: Path) -> Path:
    """LLFF scene of 10 forward-facing views: poses_bounds.npy at 32x48 full resolution and
    8x12 random RGB images in images_4/."""
    rng = np.random.default_rng(1)
    root = tmp_path / "llff"
    n = 10
    rows = []
    for k in range(n):
        yaw = 0.05 * (k - n / 2)  # OpenGL camera turned about y, looking roughly down -z
        right = np.array([np.cos(yaw), 0.0, -np.sin(yaw)])
        up = np.array([0.0, 1.0, 0.0])
        back = np.cross(right, up)
        centre = np.array([0.2 * k, 0.1 * np.sin(k), 0.05 * k])
        llff = np.stack([-up, right, back, centre, LLFF_HWF], axis=-1)  # [down, right, back] order
        rows.append(np.concatenate([llff.ravel(), [2.0 + 0.1 * k, 20.0 + k]]))
    root.mkdir()
    np.save(root / "poses_bounds.npy", np.array(rows))
    h, w = int(LLFF_HWF[0]) // LLFF_FACTOR, int(LLFF_HWF[1]) // LLFF_FACTOR
    for k in range(n):
        write_png(root / f"images_{LLFF_FACTOR}" / f"img_{k:03d}.png", rng.uniform(size=(h, w, 3)))
    return root


@pytest.fixture
def shared_data() -> Path:
    """The project's real scenes at ``../shared/data`` beside the repository, or skip."""
    path = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    if not path.is_dir():
        pytest.skip(f"real data not present at {path}")
    return path


@pytest.fixture(scope="session")
def tiny_occupancy_run(tmp_path_factory) -> Iterator[Path]:
    """A checkpoint of 6 occupancy-sampler steps on a 16x16 built-in scene (2-layer model, an 8^3
    grid), trained on the CPU with the reference ops; its folder is returned. The scene is cached
    in the session's temporary folder while the fixture lives."""
    from test_train import tiny_config

    from mixer_nerf.train import Trainer

    out = tmp_path_factory.mktemp("occupancy") / "run"
    env = pytest.MonkeyPatch()
    env.setenv("MIXER_NERF_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
    cfg = tiny_config(out, sampler="occupancy", val_every=6, ckpt_every=6)
    Trainer(cfg, log=lambda _: None).fit()
    yield out
    env.undo()
