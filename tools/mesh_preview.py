"""Load an exported mesh with trimesh, print its vertex count, bounds and watertightness, and draw
a shaded preview PNG with matplotlib (no OpenGL needed).

Usage: python tools/mesh_preview.py MESH OUT.png [--views 3] [--max-faces 200000]

Each view looks at the mesh from an azimuth step of 360 / views degrees, 30 degrees above the
xy plane (z up, as in nerf_synthetic). Faces take the mean of their vertex colours, scaled by a
Lambert term of a light at the camera; more than ``--max-faces`` faces are drawn as a random
subset (seed 0), which thins the surface but keeps its shape.
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh")
    parser.add_argument("out")
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--max-faces", type=int, default=200_000)
    args = parser.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import trimesh
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    mesh = trimesh.load(args.mesh)
    print(f"{args.mesh}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces, "
          f"watertight {mesh.is_watertight}, bounds {mesh.bounds.round(3).tolist()}")  # fmt: skip
    faces = np.arange(len(mesh.faces))
    if len(faces) > args.max_faces:
        faces = np.random.default_rng(0).choice(faces, args.max_faces, replace=False)
    triangles = mesh.vertices[mesh.faces[faces]]
    colors = mesh.visual.vertex_colors[mesh.faces[faces]][..., :3].mean(axis=1) / 255
    fig = plt.figure(figsize=(5 * args.views, 5))
    for k in range(args.views):
        azimuth, elevation = 360 * k / args.views + 30, 30
        a, e = np.radians(azimuth), np.radians(elevation)
        to_camera = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        shade = 0.35 + 0.65 * np.clip(mesh.face_normals[faces] @ to_camera, 0, 1)[:, None]
        ax = fig.add_subplot(1, args.views, k + 1, projection="3d")
        shaded = np.clip(colors * shade, 0, 1)
        ax.add_collection3d(Poly3DCollection(triangles, facecolors=shaded, linewidths=0))
        lo, hi = mesh.bounds
        centre, half = (lo + hi) / 2, (hi - lo).max() / 2
        ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
               zlim=(centre[2] - half, centre[2] + half))  # fmt: skip
        ax.view_init(elev=elevation, azim=azimuth)
        ax.set_box_aspect((1, 1, 1))
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"preview: {args.out}")


if __name__ == "__main__":
    main()
