"""Exports of a trained scene: a mesh by marching cubes over the density, a coloured point cloud
from rendered depth, and raw depth and opacity maps.

    from mixer_nerf.export import export_mesh, export_points, export_depth
    export_mesh("runs/lego/checkpoint.pt", "runs/lego/export/mesh.ply", resolution=256)

The mesh and the point cloud need the ``export`` extra (PyMCubes, trimesh).
"""

from .depth import export_depth
from .errors import ExportError
from .mesh import export_mesh, extract_mesh
from .points import export_points

__all__ = ["ExportError", "export_depth", "export_mesh", "export_points", "extract_mesh"]
