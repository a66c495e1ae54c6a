"""The ablation table: per-preset means and spreads over seeds, change against preset A, cost and
time to a PSNR; written as markdown, JSON and CSV beside a plot of the validation curves."""

from __future__ import annotations

import csv
import json
import math
import statistics
from pathlib import Path
from typing import Any

from ..train.config import DEFAULT_STEPS, FORWARD_FACING_PROPOSAL_STEPS
from ..train.logbook import CsvLog
from ..train.loss_spikes import spike_steps
from ..train.output import atomic_path, write_text_atomic
from .curves import plot_curves, val_curve
from .plan import AblationPlan

PRESET_NAMES = {"A": "NeRF", "B": "NeRF + SE", "C": "NeRF + MLCA", "D": "Mixer-NeRF"}
METRICS = ("psnr", "ssim", "lpips")
DIGITS = (2, 4, 4)  # SSIM and LPIPS of converged runs differ in the fourth decimal (Lego: 0.987, 0.0048)
PRESET_COLUMNS = ["preset", "model", "seeds", *(f"{m}_{k}" for m in METRICS for k in ("mean", "spread")),
                  *(f"{m}_change_vs_A" for m in METRICS), "params", "steps_per_s", "seconds_to_target"]
RUN_COLUMNS = ["preset", "seed", "status", "steps", "train_seconds", "steps_per_s", "params", *METRICS,
               "seconds_to_target", "eval_split", "eval_views", "loss_spikes", "run"]
MAX_VIEW_COLUMNS = 8  # per-view PSNR in the markdown for scenes with few held-out views (Fern: 3)


def build_table(plan: AblationPlan, records: list[dict[str, Any]]) -> dict[str, Any]:
    """The table of ``records`` (one per run, see ``runner.run_one``) for ``plan``.

    ``spread`` is the sample standard deviation over seeds (None with one seed); a mean ignores
    failed runs; ``seconds_to_target`` is the training time of the first validation at or above
    ``target_psnr`` (None where a run never reached it; a preset's mean only when all its runs did).
    """
    curves = {(r["preset"], r["seed"]): val_curve(CsvLog(Path(r["run"]) / "val_log.csv")) for r in records}
    target = plan.target_psnr if plan.target_psnr is not None else _reachable_target(curves.values())
    runs = [{**r, "seconds_to_target": _seconds_to(curves[(r["preset"], r["seed"])], target),
             "view_psnr": _view_psnr(Path(r["run"])), "loss_spikes": _loss_spikes(Path(r["run"]))}
            for r in records]
    presets = [_preset_row(p, [r for r in runs if r["preset"] == p]) for p in plan.presets
               if any(r["preset"] == p for r in runs)]  # a report may hold presets not started yet
    reference = next((row for row in presets if row["preset"] == "A"), None)
    for row in presets:
        for m in METRICS:
            row[f"{m}_change_vs_A"] = _difference(row[f"{m}_mean"], reference and reference[f"{m}_mean"])
    base = plan.base
    notes = sorted({n for r in runs for n in r.get("notes", [])})
    if reference is None:
        notes.append("preset A is not in this ablation: no change against A")
    return {
        "scene": base.data or "built-in procedural scene",
        "budget": {"steps": base.steps, "time_budget_s": base.time_budget},
        "seeds": list(plan.seeds),
        "model_overrides": json.loads(json.dumps(base.model_overrides)),
        "sampler": base.sampler,
        "target_psnr": target,
        "presets": presets,
        "runs": runs,
        "notes": notes,
        "curves": {f"{p}_seed{s}": c for (p, s), c in curves.items()},
    }


def write_table(table: dict[str, Any], out: Path) -> list[Path]:
    """``ablation.md``, ``table.json``, ``table.csv`` (one row per preset), ``runs.csv`` (one row
    per run) and ``curves.png`` in ``out``; returns their paths."""
    paths = [out / "ablation.md", out / "table.json", out / "table.csv", out / "runs.csv", out / "curves.png"]
    write_text_atomic(paths[0], markdown(table))
    write_text_atomic(paths[1], json.dumps(table, indent=1))
    _write_csv(paths[2], PRESET_COLUMNS, table["presets"])
    _write_csv(paths[3], RUN_COLUMNS, table["runs"])
    plot_curves(table["curves"], paths[4])
    return paths


def markdown(table: dict[str, Any]) -> str:
    budget = table["budget"]
    limit = (f"{budget['steps']} steps" if budget["steps"] else
             f"the trainer's default steps ({FORWARD_FACING_PROPOSAL_STEPS} with the proposal sampler on "
             f"forward-facing scenes, else {DEFAULT_STEPS})")
    limit += (f" or {budget['time_budget_s']:g} s of training, whichever comes first"
              if budget["time_budget_s"] else "")
    overrides = ", ".join(f"{k}={json.dumps(v)}" for k, v in table["model_overrides"].items()) or "none"
    target = "-" if table["target_psnr"] is None else f"{table['target_psnr']:.1f} dB"
    lines = [
        f"# Ablation on {table['scene']}",
        "",
        f"Each run: {limit}; seeds {', '.join(map(str, table['seeds']))}; sampler {table['sampler']}; "
        f"model overrides: {overrides}. Scores: mean ± spread (standard deviation) over seeds on the "
        f"held-out views; change against preset A; s to {target}: training seconds to that validation PSNR.",
        "",
        f"| Preset | Model | PSNR ↑ | SSIM ↑ | LPIPS ↓ | ΔPSNR | ΔSSIM | ΔLPIPS | Params | Steps/s | s to {target} |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in table["presets"]:
        lines.append("| " + " | ".join([
            row["preset"], row["model"],
            *(_pm(row[f"{m}_mean"], row[f"{m}_spread"], d) for m, d in zip(METRICS, DIGITS)),
            *(_num(row[f"{m}_change_vs_A"], d, signed=True) for m, d in zip(METRICS, DIGITS)),
            _num(row["params"], 0), _num(row["steps_per_s"], 1), _num(row["seconds_to_target"], 1),
        ]) + " |")
    lines += ["", "Runs:", "", "| Preset | Seed | Status | Steps | Train s | Steps/s | PSNR | SSIM | LPIPS | "
              f"s to {target} | Views | Loss spikes at step |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in table["runs"]:
        lines.append("| " + " | ".join([
            r["preset"], str(r["seed"]), r["status"], str(r["steps"]), _num(r["train_seconds"], 1),
            _num(r["steps_per_s"], 1), *(_num(r[m], d) for m, d in zip(METRICS, DIGITS)),
            _num(r["seconds_to_target"], 1), f"{r['eval_views']} {r['eval_split'] or ''}".strip(),
            ", ".join(f"{step:,}" for step in r["loss_spikes"]) or "-",
        ]) + " |")
    lines += _view_lines(table["runs"])
    if table["notes"]:
        lines += ["", *(f"Note: {n}" for n in table["notes"])]
    return "\n".join(lines) + "\n"


def _view_psnr(run: Path) -> dict[str, float] | None:
    """PSNR of each held-out view of a scored run (its ``eval/metrics.json``), by view name."""
    path = run / "eval" / "metrics.json"
    if not path.is_file():
        return None
    return {image["name"]: image["psnr"] for image in json.loads(path.read_text())["images"]}


def _loss_spikes(run: Path) -> list[int]:
    """Steps of the run's ``train_log.csv`` at which its logged colour loss (from ``psnr``) spiked:
    the trainer's note."""
    rows = CsvLog(run / "train_log.csv").rows()
    return spike_steps((int(row["step"]), 10 ** (-float(row["psnr"]) / 10)) for row in rows)


def _view_lines(runs: list[dict[str, Any]]) -> list[str]:
    """A per-view PSNR table where the scored runs share at most MAX_VIEW_COLUMNS views: with few
    held-out views one view can decide a mean (a floater, or a view the others do not constrain)."""
    scored = [r for r in runs if r.get("view_psnr")]
    names = list(scored[0]["view_psnr"]) if scored else []
    if not names or len(names) > MAX_VIEW_COLUMNS or any(list(r["view_psnr"]) != names for r in scored):
        return []
    return ["", "PSNR per held-out view:", "", "| Preset | Seed | " + " | ".join(names) + " |",
            "|---|---|" + "---|" * len(names),
            *("| " + " | ".join([r["preset"], str(r["seed"]), *(_num(r["view_psnr"][n], 2) for n in names)]) + " |"
              for r in scored)]


def _preset_row(preset: str, runs: list[dict[str, Any]]) -> dict[str, Any]:
    row: dict[str, Any] = {"preset": preset, "model": PRESET_NAMES[preset], "seeds": len(runs)}
    for m in METRICS:
        row[f"{m}_mean"], row[f"{m}_spread"] = _mean_spread([r[m] for r in runs])
    row["params"] = next((r["params"] for r in runs if r["params"] is not None), None)
    row["steps_per_s"] = _mean_spread([r["steps_per_s"] for r in runs])[0]
    times = [r["seconds_to_target"] for r in runs]
    row["seconds_to_target"] = None if None in times else statistics.fmean(times)
    return row


def _mean_spread(values: list[float | None]) -> tuple[float | None, float | None]:
    present = [v for v in values if v is not None and math.isfinite(v)]
    if not present:
        return None, None
    return statistics.fmean(present), statistics.stdev(present) if len(present) > 1 else None


def _reachable_target(curves) -> float | None:
    """The lowest best validation PSNR of the runs, rounded down to 0.1 dB: every run reaches it."""
    bests = [max(psnr for _, _, psnr in c) for c in curves if c]
    return math.floor(min(bests) * 10) / 10 if bests else None


def _seconds_to(curve: list[tuple[int, float, float]], target: float | None) -> float | None:
    if target is None:
        return None
    return next((seconds for _, seconds, psnr in curve if psnr >= target), None)


def _difference(value: float | None, reference: float | None) -> float | None:
    return None if value is None or reference is None else value - reference


def _pm(mean: float | None, spread: float | None, digits: int) -> str:
    if mean is None:
        return "-"
    return f"{mean:.{digits}f}" + ("" if spread is None else f" ± {spread:.{digits}f}")


def _num(value: float | None, digits: int, signed: bool = False) -> str:
    if value is None:
        return "-"
    return f"{value:{'+' if signed else ''}.{digits}f}" if digits else f"{value:,.0f}"


def _write_csv(path: Path, columns: list[str], rows: list[dict[str, Any]]) -> None:
    with atomic_path(path) as tmp, tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        # A list (a run's loss-spike steps) as one space-separated cell
        writer.writerows({k: " ".join(map(str, v)) if isinstance(v, list) else v for k, v in row.items()}
                         for row in rows)
