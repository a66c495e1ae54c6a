"""Training on 1 against N GPUs: samples per second, steps, time to a PSNR, held-out quality.

    python -m benchmarks.distributed_scaling --runs runs --out benchmarks/results/train_step/distributed_h100x2 \
        --device "2x NVIDIA H100 80GB HBM3" lego_1gpu lego_2gpu fern_1gpu fern_2gpu

Each name is a run folder of ``mixer-nerf train --devices N`` under ``--runs`` (its
``summary.json``, ``train_log.csv``, ``val_log.csv`` and ``eval_*/metrics.json``). The runs are
grouped by scene (the name before the first ``_``); the first run of a scene is the baseline of
its ratios. Writes ``<out>.json`` (the logs and the numbers), ``<out>.md`` (the table) and
``<out>.png`` (validation PSNR against training seconds).

Samples per second integrate rank 0's logged ``rays_per_s * samples_per_ray`` over the run (each
rank draws its own batch of the same sample budget) times the number of processes.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _csv(path: Path) -> list[dict[str, float]]:
    with open(path, newline="") as f:
        return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in csv.DictReader(f)]


def load_run(folder: Path) -> dict:
    """One run folder -> its summary, logs, evaluation and derived rates."""
    summary = json.loads((folder / "summary.json").read_text())
    train, val = _csv(folder / "train_log.csv"), _csv(folder / "val_log.csv")
    metrics = json.loads(next(folder.glob("eval_*/metrics.json")).read_text())["summary"]
    samples = sum(b["rays_per_s"] * b["samples_per_ray"] * (b["seconds"] - a["seconds"])
                  for a, b in zip(train, train[1:]))
    span = train[-1]["seconds"] - train[0]["seconds"]
    return {
        "name": folder.name, "processes": summary["processes"], "steps": summary["step"],
        "train_seconds": summary["train_seconds"],
        "ms_per_step": 1000 * summary["train_seconds"] / summary["step"],
        "samples_per_s": summary["processes"] * samples / span,
        "eval": {k: metrics[k] for k in ("split", "images", "mean_psnr", "mean_ssim", "mean_lpips") if k in metrics},
        "val_log": val, "train_log": train,
    }


def seconds_to(val_log: list[dict[str, float]], psnr: float) -> float | None:
    """Training seconds of the first validation at or above ``psnr`` dB, None if never."""
    return next((row["seconds"] for row in val_log if row["psnr"] >= psnr), None)


def table(scenes: dict[str, list[dict]], targets: dict[str, list[float]]) -> list[str]:
    rows = ["| run | processes | steps | ms/step | samples/s | vs 1 GPU | held-out PSNR / SSIM / LPIPS | "
            "time to target PSNRs (val, 3 views) |", "|---|---:|---:|---:|---:|---:|---|---|"]
    for scene, runs in scenes.items():
        base = runs[0]
        for run in runs:
            e = run["eval"]
            reach = ", ".join(f"{t:g} dB: " + (f"{s:.0f} s" if (s := seconds_to(run["val_log"], t)) is not None
                                               else "not reached") for t in targets[scene])
            rows.append(
                f"| {run['name']} | {run['processes']} | {run['steps']} | {run['ms_per_step']:.2f} | "
                f"{run['samples_per_s'] / 1e6:.2f}M | {run['samples_per_s'] / base['samples_per_s']:.2f}x | "
                f"{e['mean_psnr']:.2f} / {e['mean_ssim']:.4f} / {e.get('mean_lpips', float('nan')):.4f} "
                f"({e['split']}, {e['images']} views) | {reach} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("names", nargs="+", help="run folders under --runs")
    parser.add_argument("--runs", default="runs")
    parser.add_argument("--out", required=True, help="output path without suffix")
    parser.add_argument("--device", required=True, help="the machine, in words, for the title")
    parser.add_argument("--targets", default="lego=28,31,33,35;fern=22,23,24,25",
                        help="per scene: PSNRs whose time to reach the table gives")
    args = parser.parse_args()

    scenes: dict[str, list[dict]] = {}
    for name in args.names:
        run = load_run(Path(args.runs) / name)
        scenes.setdefault(name.split("_")[0], []).append(run)
    targets = {k: [float(t) for t in v.split(",")]
               for k, v in (item.split("=") for item in args.targets.split(";"))}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"device": args.device, "scenes": scenes}, indent=1))
    rows = table(scenes, targets)
    out.with_suffix(".md").write_text(f"# 1 against N GPUs ({args.device})\n\n" + "\n".join(rows) + "\n")
    fig, axes = plt.subplots(1, len(scenes), figsize=(5 * len(scenes), 3.8), squeeze=False)
    for ax, (scene, runs) in zip(axes[0], scenes.items()):
        for run in runs:
            ax.plot([r["seconds"] for r in run["val_log"]], [r["psnr"] for r in run["val_log"]],
                    marker=".", label=f"{run['processes']} GPU{'s' if run['processes'] > 1 else ''}")
        ax.set(title=scene, xlabel="training time (s)", ylabel="val PSNR (dB, 3 views)")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)
    print("\n".join(rows))


if __name__ == "__main__":
    main()
