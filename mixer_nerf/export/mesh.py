"""A mesh of a trained scene: marching cubes over the density in the occupancy grid's box, with
vertex colours rendered from the field."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from ..render import render_rays
from ..train.output import ensure_writable_folder
from ..train.restore import TrainedRun, load_trained
from .errors import ExportError, require_mcubes, require_trimesh

MESH_FORMATS = (".ply", ".obj", ".glb")
COLOR_SAMPLES = 32  # samples of the short ray through each vertex that renders its colour
CHUNK = 65536


def density_volume(
    density_fn: Callable[[torch.Tensor], torch.Tensor],
    aabb: torch.Tensor,
    occupied: torch.Tensor,
    resolution: int,
    device: torch.device,
) -> np.ndarray:
    """(R, R, R) float32 densities at the lattice ``linspace(aabb[0], aabb[1], R)`` on each axis.

    Only points in occupied cells of ``occupied`` (X, Y, Z), dilated by one cell so that a surface
    crossing a cell border is kept, are evaluated; the others and the volume's outer layer are 0,
    which closes the surface inside the box.
    """
    lo, hi = aabb[0].cpu(), aabb[1].cpu()
    axes = [torch.linspace(float(lo[i]), float(hi[i]), resolution) for i in range(3)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    cells = torch.tensor(occupied.shape)
    index = (
        ((points - lo) / (hi - lo) * cells)
        .floor()
        .long()
        .clamp(min=torch.zeros(3, dtype=torch.long), max=cells - 1)
    )
    dilated = F.max_pool3d(occupied[None, None].float().cpu(), 3, stride=1, padding=1)[0, 0] > 0
    keep = dilated[index[:, 0], index[:, 1], index[:, 2]].nonzero().squeeze(1)
    volume = torch.zeros(len(points))
    with torch.no_grad():
        for start in range(0, len(keep), CHUNK):
            rows = keep[start : start + CHUNK]
            volume[rows] = density_fn(points[rows].to(device)).reshape(-1).float().cpu()
    volume = volume.reshape(resolution, resolution, resolution)
    volume[[0, -1]] = volume[:, [0, -1]] = volume[:, :, [0, -1]] = 0
    return volume.numpy()


def extract_mesh(
    density_fn: Callable[[torch.Tensor], torch.Tensor],
    aabb: torch.Tensor,
    occupied: torch.Tensor,
    resolution: int,
    threshold: float,
    device: torch.device,
) -> Any:
    """The ``threshold`` level set of the density as a ``trimesh.Trimesh`` (world coordinates,
    outward normals, no colours); see :func:`density_volume` for the points evaluated.

    Raises:
        ExportError: the density never reaches ``threshold`` inside the occupied cells.
    """
    mcubes, trimesh = require_mcubes(), require_trimesh()
    volume = density_volume(density_fn, aabb, occupied, resolution, device)
    vertices, faces = mcubes.marching_cubes(volume.astype(np.float64), float(threshold))
    if len(faces) == 0:
        raise ExportError(
            f"no surface at density {threshold:g}: the largest density in the occupied cells is "
            f"{volume.max():.3g}; lower --threshold"
        )
    lo, hi = aabb[0].cpu().double().numpy(), aabb[1].cpu().double().numpy()
    mesh = trimesh.Trimesh(lo + vertices / (resolution - 1) * (hi - lo), faces, process=True)
    if mesh.volume < 0:  # marching cubes' winding depends on the sign convention: normals point out
        mesh.invert()
    return mesh


def surface_colors(
    run: TrainedRun, vertices: torch.Tensor, normals: torch.Tensor, reach: float
) -> torch.Tensor:
    """(V, 3) colours of surface points, each rendered by a ray of length 2 ``reach`` that enters
    along the outward normal and crosses the surface at its middle."""
    field, fine = run.fields.runners(run.cfg.precision, run.device)
    background = run.scene["background"].to(run.device, torch.float32)
    colors = []
    with torch.no_grad():
        for start in range(0, len(vertices), CHUNK // COLOR_SAMPLES):
            v = vertices[start : start + CHUNK // COLOR_SAMPLES].to(run.device, torch.float32)
            n = normals[start : start + CHUNK // COLOR_SAMPLES].to(run.device, torch.float32)
            out = render_rays(
                field,
                v + reach * n,
                -n,
                0.0,
                2 * reach,
                COLOR_SAMPLES,
                0,
                fine,
                stratified=False,
                background=background,
                backend=run.cfg.backend,
            )
            colors.append(out.coarse.color.clamp(0, 1).cpu())
    return torch.cat(colors)


def export_mesh(
    ckpt: str | Path,
    out: str | Path,
    resolution: int = 256,
    threshold: float = 10.0,
    device: str | None = None,
    backend: str | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Write the mesh of a checkpoint trained with an occupancy grid to ``out`` (.ply, .obj, .glb).

    Returns:
        {"mesh", "vertices", "faces", "watertight", "bounds" (2, 3), "scene_box" (2, 3)}.

    Raises:
        ExportError: bad arguments, no grid in the checkpoint, an NDC scene, no surface.
    """
    out = Path(out)
    if out.suffix not in MESH_FORMATS:
        raise ExportError(f"{out}: mesh files are {', '.join(MESH_FORMATS)}")
    if resolution < 8:
        raise ExportError(f"resolution must be at least 8, got {resolution}")
    if not threshold > 0:
        raise ExportError(f"threshold must be a positive density, got {threshold}")
    require_mcubes(), require_trimesh()
    run = load_trained(ckpt, device=device, backend=backend)
    grid = run.fields.grid
    if grid is None:
        raise ExportError(
            f"{run.path}: trained with the {run.cfg.sampler} sampler, which keeps no occupancy grid; "
            "mesh export needs one (train with --sampler occupancy)"
        )
    if run.scene["ndc"]:
        raise ExportError(f"{run.path}: a forward-facing (NDC) scene has no bounded surface to mesh")
    ensure_writable_folder(out.parent)
    field = run.fields.runners(run.cfg.precision, run.device)[0]
    log(
        f"marching cubes at {resolution}^3 over {int(grid.occupied.sum())} occupied of {grid.num_cells} cells"
    )
    mesh = extract_mesh(field.density, grid.aabb, grid.occupied, resolution, threshold, run.device)
    cell = float((grid.aabb[1] - grid.aabb[0]).max()) / (resolution - 1)
    normals = torch.from_numpy(np.array(mesh.vertex_normals))
    colors = surface_colors(run, torch.from_numpy(np.array(mesh.vertices)), normals, reach=2 * cell)
    mesh.visual.vertex_colors = (colors.numpy() * 255 + 0.5).astype(np.uint8)
    mesh.export(out)
    return {
        "mesh": str(out),
        "vertices": len(mesh.vertices),
        "faces": len(mesh.faces),
        "watertight": bool(mesh.is_watertight),
        "bounds": mesh.bounds.tolist(),
        "scene_box": grid.aabb.cpu().tolist(),
    }
