"""What each skip saves when rendering a trained occupancy-sampler model, one full val image.

Called by ``time_to_quality.py --skip-report`` at the end of a training curve (same model, same
call). For each combination of skips it renders val view 0 at full resolution (deterministic
samples, no grad) and reports the marched and shaded MLP samples per ray, the render time, the
PSNR against the ground truth and against the render with no skipping at all. Then it renders
every val view with all skips and with box clipping only, for their mean PSNRs. Without box
clipping a ray would march from the scene's near to its far plane at the same step: that count
is given, not rendered.
"""

from __future__ import annotations

import copy
import dataclasses
import time

import torch

from benchmarks.validation import validate
from mixer_nerf.metrics import psnr
from mixer_nerf.train.sampling import image_renderer

# (label, occupancy grid on, early termination on); box clipping is on in all of them.
VARIANTS = [
    ("all skips (grid + early termination + box)", True, True),
    ("no early termination", True, False),
    ("no occupancy grid", False, True),
    ("box clipping only", False, False),
]


def _render(trainer, grid, early_stop_eps: float, rays_o, rays_d) -> tuple[torch.Tensor, int, int]:
    """(colour (R, 3), marched samples, shaded samples) of all rays, in the trainer's chunks."""
    scene = trainer.train_scene
    marching = dataclasses.replace(trainer.cfg.marching(), early_stop_eps=early_stop_eps)
    renderer = image_renderer(trainer.cfg, trainer.fields, scene.near, scene.far, trainer.background,
                              grid=grid, marching=marching)
    result, shaded, marched = renderer.render_counted(rays_o, rays_d)
    return result.color, marched, shaded


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _timed(fn, repeats: int = 3) -> tuple[object, float]:
    fn()  # warm-up
    _sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        _sync()
        times.append(time.perf_counter() - start)
    return result, sorted(times)[len(times) // 2]


def skip_report(trainer, val) -> dict:
    """Render val view 0 under every skip combination; returns a JSON-ready dict."""
    grid = trainer.fields.grid
    full_grid = copy.deepcopy(grid)
    full_grid.occupied = torch.ones(grid.resolution, dtype=torch.bool)
    rays_o, rays_d = val.rays_for_image(0)
    truth = val.image(0)
    num_rays = rays_o.shape[0]
    trainer.fields.eval()
    rows, images = [], {}
    for label, use_grid, early in VARIANTS:
        g = grid if use_grid else full_grid
        eps = trainer.cfg.early_stop_eps if early else 0.0
        (color, marched, shaded), seconds = _timed(lambda: _render(trainer, g, eps, rays_o, rays_d))
        images[label] = color.reshape(val.H, val.W, 3).clamp(0, 1)
        rows.append({"variant": label, "render_ms": round(seconds * 1e3, 1),
                     "marched_per_ray": round(marched / num_rays, 2), "shaded_per_ray": round(shaded / num_rays, 2),
                     "psnr": round(psnr(images[label], truth).item(), 3)})
    reference = images[VARIANTS[-1][0]]
    for row in rows[:-1]:
        diff = psnr(images[row["variant"]], reference).item()
        row["psnr_vs_no_skip"] = round(diff, 2) if diff != float("inf") else "identical"
    all_views = {}
    for label, use_grid, early in (VARIANTS[0], VARIANTS[-1]):
        g, eps = (grid if use_grid else full_grid), (trainer.cfg.early_stop_eps if early else 0.0)
        render = lambda o, d, g=g, eps=eps: _render(trainer, g, eps, o, d)[0]  # noqa: E731
        all_views[label] = round(validate(render, val), 3)
    scene = trainer.train_scene
    unclipped = (scene.far - scene.near) / grid.step_size  # marching steps in t
    trainer.fields.train()
    return {"view": 0, "pixels": num_rays, "step_size": grid.step_size, "rows": rows,
            "mean_psnr_all_views": {"views": len(val), **all_views},
            "no_box_clipping_marched_per_ray": round(unclipped, 1), "dense_nerf_per_ray": 64 + 128}

