"""Validation curves of an ablation's runs, and their plot against training time and steps."""

from __future__ import annotations

import math
from pathlib import Path

from ..train.logbook import CsvLog
from ..train.output import atomic_path

PRESET_COLORS = {"A": "tab:blue", "B": "tab:orange", "C": "tab:green", "D": "tab:red"}
SEED_STYLES = ("-", "--", ":", "-.")


def val_curve(val_log: CsvLog) -> list[tuple[int, float, float]]:
    """(step, training seconds, validation PSNR) rows of a run's ``val_log.csv``, finite ones only."""
    rows = [(int(r["step"]), float(r["seconds"]), float(r["psnr"])) for r in val_log.rows()]
    return [row for row in rows if math.isfinite(row[2])]


def plot_curves(curves: dict[str, list[tuple[int, float, float]]], path: Path) -> Path:
    """Validation PSNR against training seconds and against steps, one line per run (named
    ``<preset>_seed<seed>``: colour by preset, line style by seed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (by_time, by_step) = plt.subplots(1, 2, figsize=(11, 4))
    seeds = sorted({name.split("_seed")[1] for name in curves}, key=int)
    for name, curve in curves.items():
        if not curve:
            continue
        preset, seed = name.split("_seed")
        style = {"color": PRESET_COLORS[preset], "linestyle": SEED_STYLES[seeds.index(seed) % len(SEED_STYLES)],
                 "marker": "o", "markersize": 3, "label": f"{preset} seed {seed}"}
        steps, seconds, psnr = zip(*curve)
        by_time.plot(seconds, psnr, **style)
        by_step.plot(steps, psnr, **style)
    by_time.set(xlabel="training time (s)", ylabel="validation PSNR (dB)", title="PSNR against time")
    by_step.set(xlabel="step", ylabel="validation PSNR (dB)", title="PSNR against steps")
    for ax in (by_time, by_step):
        ax.grid(alpha=0.3)
    by_step.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return path
