"""Evaluating a checkpoint on held-out views: PSNR, SSIM and (when its weights are installed)
LPIPS per image and on average, written as ``metrics.json`` and ``metrics.csv`` next to the
rendered images."""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from . import metrics
from .data import load_split
from .train.output import atomic_path, ensure_writable_folder, write_text_atomic
from .train.restore import load_trained
from .train.scenes import held_out_split, locate_scene
from .video import colorize_depth, depth_range, to_uint8, write_png

SPLITS = ("test", "val", "train")
SSIM_MIN_SIZE = 11  # SSIM's Gaussian window


def evaluate(
    ckpt: str | Path,
    data: str | Path | None = None,
    split: str | None = None,
    out: str | Path | None = None,
    device: str | None = None,
    backend: str | None = None,
    max_images: int | None = None,
    render_samples: int | None = None,
    lpips: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Render every view of a split with a checkpoint and score it against the ground truth.

    Args:
        ckpt: checkpoint file.
        data: scene folder; default: the one the checkpoint was trained on (it must hold the same
            cameras: a moved copy of it).
        split: "test", "val" or "train"; default "test", or "val" when the scene has no test views.
        out: output folder; default ``<checkpoint folder>/eval_<split>``. Receives
            ``images/NNN.png``, ``depth/NNN.png``, ``metrics.csv`` and ``metrics.json``.
        max_images: score only the first this many views.
        render_samples: most samples shaded at once (default: the run's setting).
        lpips: False: no LPIPS (None, with a note saying why), even where its weights are installed.

    Returns:
        The content of ``metrics.json``: {"summary": {...}, "images": [...], "notes": [...]}.
    """
    if split is not None and split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    run = load_trained(ckpt, device=device, backend=backend, render_samples=render_samples)
    folder, fmt = locate_scene(run.cfg, run.scene, data, run.path)
    if split is None:
        scene, split = held_out_split(folder, fmt, "test", run.cfg.downscale, run.cfg.val_holdout)
    else:  # the run's own splits: its val views where it carved them out of train
        scene = load_split(folder, fmt, split, run.cfg.downscale, run.cfg.val_holdout)
    out = Path(out) if out is not None else run.path.parent / f"eval_{split}"
    for sub in ("images", "depth"):
        ensure_writable_folder(out / sub)

    n = len(scene) if max_images is None else min(max_images, len(scene))
    lpips_reason = metrics.lpips_unavailable_reason() or (None if lpips else "LPIPS skipped: not asked for")
    lpips_min = metrics.LPIPS_MIN_SIZE
    if lpips_reason is None and min(scene.H, scene.W) < lpips_min:
        lpips_reason = f"LPIPS skipped: images are smaller than {lpips_min}x{lpips_min}"
    notes = [lpips_reason] if lpips_reason else []
    if min(scene.H, scene.W) < SSIM_MIN_SIZE:
        notes.append(f"SSIM skipped: images are smaller than {SSIM_MIN_SIZE}x{SSIM_MIN_SIZE}")
    log(f"evaluating {run.path} (step {run.step}) on {n} {split} views of {folder}")

    rows = []
    for i in range(n):
        rays_o, rays_d = scene.rays_for_image(i)
        result = run.render(rays_o, rays_d)
        pred = result.color.reshape(scene.H, scene.W, 3).clamp(0, 1).cpu()
        depth, opacity = (
            result.depth.reshape(scene.H, scene.W).cpu(),
            result.opacity.reshape(scene.H, scene.W).cpu(),
        )
        target = scene.image(i).cpu()
        stem = f"{i:03d}"
        write_png(out / "images" / f"{stem}.png", to_uint8(pred))
        lo, hi = depth_range([depth], [opacity], fallback=(scene.near, scene.far))
        write_png(out / "depth" / f"{stem}.png", colorize_depth(depth, opacity, lo, hi))
        rows.append(
            {
                "index": i,
                "name": Path(scene.image_paths[i]).name if i < len(scene.image_paths) else stem,
                "psnr": float(metrics.psnr(pred, target)),
                "ssim": float(metrics.ssim(pred, target)) if min(scene.H, scene.W) >= SSIM_MIN_SIZE else None,
                "lpips": _lpips(pred, target) if lpips_reason is None else None,
            }
        )
        log(f"  {rows[-1]['name']}: PSNR {rows[-1]['psnr']:.2f} dB")

    summary = {
        "checkpoint": str(run.path),
        "step": run.step,
        "scene": str(folder),
        "split": split,
        "images": n,
        **{f"mean_{k}": _mean([r[k] for r in rows]) for k in ("psnr", "ssim", "lpips")},
    }
    record = {"summary": summary, "images": rows, "notes": notes}
    write_text_atomic(out / "metrics.json", json.dumps(record, indent=1))
    with atomic_path(out / "metrics.csv") as tmp, tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["index", "name", "psnr", "ssim", "lpips"])
        writer.writeheader()
        writer.writerows(rows)
    record["out"] = str(out)
    return record


def _lpips(pred: torch.Tensor, target: torch.Tensor) -> float | None:
    value = metrics.lpips(pred, target)
    return None if value is None else float(value)


def _mean(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None and not math.isnan(v)]
    return sum(present) / len(present) if present else None
