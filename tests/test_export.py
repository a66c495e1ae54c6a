"""``mixer-nerf export``: marching cubes on an analytic density and on a tiny trained run, the PLY
point cloud, raw depth maps, and each refusal in one line."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch

from mixer_nerf import cli
from mixer_nerf.export import ExportError, export_mesh, extract_mesh
from mixer_nerf.export.mesh import density_volume
from mixer_nerf.train import load_checkpoint, save_checkpoint
from mixer_nerf.train.restore import load_trained

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("mcubes")

FLAGS = ["--backend", "torch", "--device", "cpu"]
BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
RADIUS = 0.6


def ball(x: torch.Tensor) -> torch.Tensor:
    """Density 40 inside a ball of RADIUS, falling smoothly through 20 at its surface."""
    return 40 * torch.sigmoid(20 * (RADIUS - x.norm(dim=-1)))


def test_a_ball_becomes_a_closed_sphere_with_outward_normals():
    mesh = extract_mesh(ball, BOX, torch.ones(4, 4, 4, dtype=torch.bool), 48, 20.0, torch.device("cpu"))
    assert mesh.is_watertight and mesh.volume > 0
    radii = np.linalg.norm(mesh.vertices, axis=1)
    voxel = 2 / 47
    assert np.abs(radii - RADIUS).max() < voxel
    assert mesh.volume == pytest.approx(4 / 3 * math.pi * RADIUS**3, rel=0.03)
    assert (np.einsum("ij,ij->i", mesh.vertex_normals, mesh.vertices) > 0).all()


def test_only_occupied_cells_and_their_neighbours_are_evaluated():
    occupied = torch.zeros(4, 4, 4, dtype=torch.bool)
    occupied[0, 0, 0] = True
    seen = []
    volume = density_volume(lambda x: seen.append(x) or ball(x), BOX, occupied, 16, torch.device("cpu"))
    points = torch.cat(seen)
    assert (points < 0.0 + 1e-6).all()  # cell (0, 0, 0) dilated by one cell reaches x = 0
    assert len(points) == 8**3 and (volume[8:] == 0).all()
    assert volume[0].max() == 0  # the outer layer closes the surface


def test_a_threshold_above_every_density_is_refused():
    with pytest.raises(ExportError, match="no surface at density 50: the largest density .* is 40"):
        extract_mesh(ball, BOX, torch.ones(2, 2, 2, dtype=torch.bool), 16, 50.0, torch.device("cpu"))


def half_max_density(ckpt, resolution) -> float:
    run = load_trained(ckpt, device="cpu", backend="torch")
    field, grid = run.fields.runners("fp32", run.device)[0], run.fields.grid
    return float(density_volume(field.density, grid.aabb, grid.occupied, resolution, run.device).max()) / 2


def test_export_mesh_of_a_trained_run_opens_in_trimesh(tiny_occupancy_run, tmp_path, capsys):
    ckpt = tiny_occupancy_run / "checkpoint.pt"
    threshold = half_max_density(ckpt, 24)
    out = tmp_path / "mesh.ply"
    argv = [
        "export",
        "mesh",
        "--ckpt",
        str(ckpt),
        "--out",
        str(out),
        "--resolution",
        "24",
        "--threshold",
        str(threshold),
        *FLAGS,
    ]
    assert cli.main(argv) == 0
    mesh = trimesh.load(out)
    printed = capsys.readouterr().out
    assert f"({len(mesh.vertices)} vertices, {len(mesh.faces)} faces, watertight)" in printed
    assert "scene box (-1.500, -1.500, -1.500) to (1.500, 1.500, 1.500)" in printed
    assert mesh.is_watertight and len(mesh.vertices) > 0
    assert (mesh.bounds[0] >= -1.5).all() and (mesh.bounds[1] <= 1.5).all()
    colors = mesh.visual.vertex_colors
    assert colors.shape == (len(mesh.vertices), 4) and (colors[:, 3] == 255).all()


def test_export_points_and_depth(tiny_occupancy_run, tmp_path, capsys):
    ckpt = tiny_occupancy_run / "checkpoint.pt"
    out = tmp_path / "points.ply"
    argv = ["export", "points", "--ckpt", str(ckpt), "--out", str(out), "--min-opacity", "0.01", *FLAGS]
    assert cli.main(argv) == 0
    cloud = trimesh.load(out)
    assert f"({len(cloud.vertices)} points from 4 views)" in capsys.readouterr().out
    assert len(cloud.vertices) > 0 and cloud.colors.shape == (len(cloud.vertices), 4)

    depth_dir = tmp_path / "depth"
    argv = [
        "export",
        "depth",
        "--ckpt",
        str(ckpt),
        "--out",
        str(depth_dir),
        "--path",
        "turntable",
        "--frames",
        "2",
    ]
    assert cli.main([*argv, *FLAGS]) == 0
    assert "2 views" in capsys.readouterr().out
    depth, opacity = np.load(depth_dir / "depth_0001.npy"), np.load(depth_dir / "opacity_0001.npy")
    assert depth.shape == opacity.shape == (16, 16) and depth.dtype == np.float32
    assert (opacity >= 0).all() and (opacity <= 1 + 1e-6).all()
    assert (depth_dir / "depth_0001.png").is_file()
    OpenEXR = pytest.importorskip("OpenEXR")
    channels = OpenEXR.File(str(depth_dir / "depth_0001.exr")).channels()
    np.testing.assert_array_equal(channels["Z"].pixels, depth)
    np.testing.assert_array_equal(channels["A"].pixels, opacity)


def test_a_checkpoint_without_a_grid_is_refused(tiny_occupancy_run, tmp_path, capsys):
    state = load_checkpoint(tiny_occupancy_run / "checkpoint.pt")
    state["train_config"]["sampler"] = "hierarchical"
    state["model"] = {k: v for k, v in state["model"].items() if not k.startswith("grid.")}
    ckpt = tmp_path / "checkpoint.pt"
    save_checkpoint(ckpt, {k: v for k, v in state.items() if k not in ("format", "version")})
    assert cli.main(["export", "mesh", "--ckpt", str(ckpt), "--out", str(tmp_path / "m.ply"), *FLAGS]) == 1
    err = capsys.readouterr().err
    assert "hierarchical sampler, which keeps no occupancy grid" in err and str(ckpt) in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "m.ply").exists()


def test_bad_arguments_and_missing_libraries(tiny_occupancy_run, tmp_path, monkeypatch, capsys):
    ckpt = str(tiny_occupancy_run / "checkpoint.pt")
    with pytest.raises(ExportError, match="mesh files are .ply, .obj, .glb"):
        export_mesh(ckpt, tmp_path / "mesh.stl")
    with pytest.raises(ExportError, match="resolution must be at least 8"):
        export_mesh(ckpt, tmp_path / "mesh.ply", resolution=4)
    monkeypatch.setitem(sys.modules, "mcubes", None)  # import mcubes now raises ImportError
    assert cli.main(["export", "mesh", "--ckpt", ckpt, "--out", str(tmp_path / "m.ply"), *FLAGS]) == 1
    assert "pip install 'mixer_nerf[export]'" in capsys.readouterr().err
