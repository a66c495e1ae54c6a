"""Plot and tabulate the curves written by ``benchmarks.time_to_quality``.

    python -m benchmarks.plot_time_to_quality benchmarks/results/ttq
Writes ``time_to_quality.png`` and ``time_to_quality.md`` in that folder.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


# Time to quality: the first checkpoint at or above each of these validation PSNRs.
TARGETS_DB = (25.0, 28.0, 31.0)


def main(folder: str) -> None:
    root = Path(folder)
    records = [json.loads(p.read_text()) for p in sorted(root.glob("*.json"))]
    fig, ax = plt.subplots(figsize=(6, 4))
    seconds = sorted({pt["seconds"] // 1 for r in records for pt in r["curve"]})
    rows = ["| method | " + " | ".join(f"~{int(s)} s" for s in seconds) + " | samples/ray | steps | "
            + " | ".join(f"first checkpoint >= {t} dB" for t in TARGETS_DB) + " |",
            "|---|" + "---:|" * (len(seconds) + 2 + len(TARGETS_DB))]
    for r in records:
        xs = [pt["seconds"] for pt in r["curve"]]
        ys = [pt["val_psnr"] for pt in r["curve"]]
        ax.plot(xs, ys, marker="o", label=r["label"])
        by_time = {pt["seconds"] // 1: pt["val_psnr"] for pt in r["curve"]}
        last = r["curve"][-1] if r["curve"] else {}
        cells = [f"{by_time[s]:.2f}" if s in by_time else "" for s in seconds]
        reached = [next((f"{pt['seconds']:.0f} s" for pt in r["curve"] if pt["val_psnr"] >= t),
                        f"not by {last.get('seconds', 0):.0f} s") for t in TARGETS_DB]
        rows.append(f"| {r['label']} | " + " | ".join(cells)
                    + f" | {last.get('samples_per_ray', float('nan')):.1f} | {last.get('step', '')} | "
                    + " | ".join(reached) + " |")
    ax.set(xlabel="training time (s)", ylabel="val PSNR (dB)", title=records[0]["data"] if records else "")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(root / "time_to_quality.png", dpi=120)
    device = records[0]["device"] if records else ""
    (root / "time_to_quality.md").write_text(f"# Validation PSNR against training time ({device})\n\n" + "\n".join(rows) + "\n")
    print("\n".join(rows))


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "benchmarks/results/ttq")
