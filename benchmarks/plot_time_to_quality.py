"""Plot and tabulate the curves written by ``benchmarks.time_to_quality``.

    python -m benchmarks.plot_time_to_quality [PATH ...] [--targets 25,28,31] [--add FILE ...] \
        [--highlight RE]

Each PATH is a runs file (``<scene>_<device>.json``, a list of runs) or a folder of them (default
``benchmarks/results/time_to_quality``); for each file, writes ``<scene>_<device>.png`` and ``.md``
beside it. ``--targets`` are the PSNRs (dB) whose time to reach the table gives. ``--add`` first
merges the runs of each FILE (e.g. curves run side by side on several GPUs) into the runs file of
its name in the first PATH folder, each in place of a run of its label. ``--highlight`` draws the
runs whose label matches a regular expression in colour, with a legend, and the others thin and
grey behind them (a record holds every run of its history; the table keeps them all).
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from benchmarks.harness import RESULTS  # noqa: E402
from benchmarks.time_to_quality import save_runs  # noqa: E402


def curve_figure(records: list[dict], highlight: str | None = None) -> plt.Figure:
    """Val PSNR against training time, one line per run; a finished run's final PSNR dashed on to
    the last checkpoint. Runs whose label does not match ``highlight`` (a regular expression; None:
    every run matches) are drawn thin and grey, without a legend entry."""
    shown = [highlight is None or re.search(highlight, r["label"]) is not None for r in records]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    end = max((pt["seconds"] for r in records for pt in r["curve"]), default=0.0)
    # 20 colours, then markers: a record of 20+ runs keeps every highlighted line distinct
    styles = itertools.cycle([(c, m) for m in "os^D" for c in plt.get_cmap("tab20").colors])
    for r, bright in zip(records, shown, strict=True):
        xs, ys = [pt["seconds"] for pt in r["curve"]], [pt["val_psnr"] for pt in r["curve"]]
        if bright:
            color, marker = next(styles)
            ax.plot(xs, ys, marker=marker, color=color, label=r["label"], zorder=2)
        else:
            color = "0.8"
            ax.plot(xs, ys, color=color, linewidth=0.8, zorder=1)
        last = r["curve"][-1] if r["curve"] else {}
        if last.get("finished"):  # its final model stands for the checkpoints after it
            ax.plot([last["seconds"], end], [last["val_psnr"]] * 2, linestyle="--", color=color,
                    zorder=2 if bright else 1)
    data = records[0]["data"] if records else ""
    ax.set(xlabel="training time (s)", ylabel="val PSNR (dB)", title=Path(data).name or data)
    ax.grid(alpha=0.3)
    if any(shown):
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    fig.tight_layout()
    return fig


def plot(path: str | Path, targets_db: tuple[float, ...] = (25.0, 28.0, 31.0),
         highlight: str | None = None) -> None:
    """Plot (:func:`curve_figure`) and tabulate one runs file; the table gives every run's PSNR at
    each checkpoint, on its training views at its last checkpoint (where it has one) and its first
    checkpoint at or above each of ``targets_db``. A run that finished (its last point
    ``"finished"``: the trainer's ``--steps`` reached) stands at its final PSNR after that, marked †."""
    path = Path(path)
    records = json.loads(path.read_text())
    fig = curve_figure(records, highlight)
    fig.savefig(path.with_suffix(".png"), dpi=120)
    plt.close(fig)
    seconds = sorted({pt["seconds"] // 1 for r in records for pt in r["curve"]})
    rows = ["| method | " + " | ".join(f"~{int(s)} s" for s in seconds) + " | samples/ray | steps | "
            + "train views at the end | "
            + " | ".join(f"first checkpoint >= {t} dB" for t in targets_db) + " |",
            "|---|" + "---:|" * (len(seconds) + 3 + len(targets_db))]
    for r in records:
        by_time = {pt["seconds"] // 1: f"{pt['val_psnr']:.2f}" for pt in r["curve"]}
        last = r["curve"][-1] if r["curve"] else {}
        if last.get("finished"):
            by_time.update({s: f"{last['val_psnr']:.2f}†" for s in seconds if s > last["seconds"] // 1})
        cells = [by_time.get(s, "") for s in seconds]
        reached = [next((f"{pt['seconds']:.0f} s" for pt in r["curve"] if pt["val_psnr"] >= t),
                        f"not by {last.get('seconds', 0):.0f} s") for t in targets_db]
        fit = f"{last['train_psnr']:.2f}" if "train_psnr" in last else ""  # runs before --train-views: none
        rows.append(f"| {r['label']} | " + " | ".join(cells)
                    + f" | {last.get('samples_per_ray', float('nan')):.1f} | {last.get('step', '')}"
                    + f" | {fit} | " + " | ".join(reached) + " |")
    if any(r["curve"] and r["curve"][-1].get("finished") for r in records):
        rows += ["", "† finished (the trainer's --steps) before this checkpoint: its final model."]
    device = records[0]["device"] if records else ""
    path.with_suffix(".md").write_text(
        f"# Validation PSNR against training time ({device})\n\n" + "\n".join(rows) + "\n", encoding="utf-8")
    print(path)
    print("\n".join(rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", nargs="*", default=[str(RESULTS / "time_to_quality")],
                        help="runs files or folders of them")
    parser.add_argument("--targets", default="25,28,31", help="comma-separated PSNRs in dB")
    parser.add_argument("--add", nargs="+", default=[], metavar="FILE", help="runs files to merge in first")
    parser.add_argument("--highlight", metavar="RE", help="plot in colour only the runs whose label matches")
    args = parser.parse_args()
    targets = tuple(float(t) for t in args.targets.split(","))
    for added in map(Path, args.add):
        save_runs(Path(args.paths[0]) / added.name, json.loads(added.read_text()))
    for given in map(Path, args.paths):
        for runs in sorted(given.glob("*.json")) if given.is_dir() else [given]:
            plot(runs, targets, args.highlight)


if __name__ == "__main__":
    main()
