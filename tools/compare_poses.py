"""Compare the poses ``mixer-nerf prepare`` solved with an LLFF scene's ``poses_bounds.npy``.

Usage: python tools/compare_poses.py PREPARED LLFF_SCENE [--factor 8] [--json FILE]

PREPARED is a prepare output folder (its COLMAP model in ``sparse/``); LLFF_SCENE holds
``poses_bounds.npy`` whose rows are the images of ``images_{factor}/`` in name order, matched to
the prepared images by file name. The prepared camera centres are aligned onto LLFF's by the
least-squares similarity (scale, rotation, translation), then per view: the rotation error
(degrees) and the camera-centre error as a fraction of the scene extent, the diagonal of the box
holding LLFF's camera centres (the stricter choice: the scene itself is far larger than the
cameras' spread in a forward-facing capture).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from mixer_nerf.data.colmap import colmap_to_opengl, find_model
from mixer_nerf.data.colmap_model import read_model
from mixer_nerf.data.images import list_images
from mixer_nerf.data.llff import llff_to_opengl, read_poses_bounds
from mixer_nerf.data.pose_alignment import pose_errors


def compare(prepared: Path, llff: Path, factor: int) -> dict:
    folder = find_model(prepared)
    if folder is None:
        raise SystemExit(f"{prepared}: no COLMAP model")
    model = read_model(folder)
    poses, _, _ = read_poses_bounds(llff / "poses_bounds.npy")
    names = [p.name for p in list_images(llff / ("images" if factor == 1 else f"images_{factor}"))]
    reference = dict(zip(names, llff_to_opengl(poses), strict=True))
    solved = {image.name: colmap_to_opengl(image.qvec, image.tvec) for image in model.images}
    common = sorted(set(solved) & set(reference))
    errors = pose_errors(np.stack([solved[n] for n in common]), np.stack([reference[n] for n in common]))
    centres = np.stack([reference[n][:3, 3] for n in common])
    extent = float(np.linalg.norm(centres.max(axis=0) - centres.min(axis=0)))
    relative = errors.centre_error / extent
    worst = int(np.argmax(errors.rotation_degrees))
    return {
        "registered": len(common),
        "reference_views": len(names),
        "max_rotation_degrees": float(errors.rotation_degrees.max()),
        "mean_rotation_degrees": float(errors.rotation_degrees.mean()),
        "worst_rotation_view": common[worst],
        "max_centre_error_fraction": float(relative.max()),
        "mean_centre_error_fraction": float(relative.mean()),
        "extent": extent,
        "similarity_scale": errors.alignment.scale,
    }


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("prepared", type=Path)
    parser.add_argument("llff", type=Path)
    parser.add_argument("--factor", type=int, default=8, help="LLFF image folder images_FACTOR (default 8)")
    parser.add_argument("--json", type=Path, help="also write the result here")
    args = parser.parse_args(argv)
    result = compare(args.prepared, args.llff, args.factor)
    print(
        f"registered {result['registered']} of {result['reference_views']}; rotation error max "
        f"{result['max_rotation_degrees']:.3f} deg (mean {result['mean_rotation_degrees']:.3f}); "
        f"camera-centre error max {100 * result['max_centre_error_fraction']:.3f}% of the extent "
        f"(mean {100 * result['mean_centre_error_fraction']:.3f}%)"
    )
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
