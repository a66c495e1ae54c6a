"""Training, resuming and scoring the runs of an ablation, one after another."""

from __future__ import annotations

import gc
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..model import ModelConfig
from ..train.checkpoint import load_checkpoint
from ..train.config import TrainConfig
from ..train.fields import model_config_from_dict, model_notes
from ..train.logbook import CsvLog
from ..train.output import RunFiles, write_text_atomic
from ..train.sampling import make_fields, recipe_notes
from .plan import AblationError, AblationPlan
from .table import build_table, write_table

RUN_RECORD = "ablation_run.json"
COMPLETE = ("finished", "time budget reached")
STALE_FILES = ("train_log.csv", "val_log.csv", "summary.json", "config.json")


def run_ablation(plan: AblationPlan, resume: bool = False, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train and score every preset x seed of ``plan`` (skipping those already done, resuming
    those with a checkpoint), then write the table and the plot into ``plan.out``.

    Returns the table (the content of ``table.json``).
    Raises:
        AblationError: LPIPS is unavailable while ``plan.lpips`` asks for it (see :func:`check_lpips`);
            ``plan.out`` holds another ablation, or ``resume`` is False and it holds one.
    """
    check_lpips(plan)
    plan.claim_folder(resume)
    table = build_table(plan, run_each(plan, plan.runs(), log))
    paths = write_table(table, plan.out)
    log(f"ablation table: {', '.join(str(p) for p in paths)}")
    return table


def report(plan: AblationPlan, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Write the table of ``plan.out`` from its runs as they are, training and scoring nothing: the
    finished runs with their records, an unfinished one (logs but no record, e.g. a GPU call ran
    out) as a row without scores at its last logged step, a run not started left out.

    Returns the table. Raises AblationError where ``plan.out`` holds an ablation of other settings
    or no run at all.
    """
    plan.check_settings()
    records = []
    for preset, seed in plan.runs():
        files = RunFiles(plan.run_folder(preset, seed))
        if (files.root / RUN_RECORD).is_file():
            # the folder as found now: a record names the path it was trained at
            records.append({**json.loads((files.root / RUN_RECORD).read_text()), "run": str(files.root)})
        elif (files.root / "train_log.csv").is_file():
            records.append(_unfinished_record(preset, seed, files))
        else:
            log(f"preset {preset}, seed {seed}: not started, left out")
    if not records:
        raise AblationError(f"{plan.out}: no run of this ablation has started")
    table = build_table(plan, records)
    paths = write_table(table, plan.out)
    log(f"ablation table: {', '.join(str(p) for p in paths)}")
    return table


def _unfinished_record(preset: str, seed: int, files: RunFiles) -> dict[str, Any]:
    last = (CsvLog(files.root / "train_log.csv").rows() or [{"step": 0, "seconds": 0.0}])[-1]
    steps, seconds = int(last["step"]), float(last["seconds"])
    summary = _read_summary(files)
    return {
        "preset": preset,
        "seed": seed,
        "run": str(files.root),
        "status": f"unfinished ({summary['status']})" if summary else "unfinished",
        "steps": steps,
        "train_seconds": seconds,
        "steps_per_s": steps / seconds if seconds > 0 else None,
        "params": checkpoint_model(files.checkpoint)[0] if files.checkpoint.is_file() else None,
        **_no_scores(),
    }


def check_lpips(plan: AblationPlan) -> None:
    """Refuse, before anything is trained or written, an ablation that asks for LPIPS (``plan.lpips``)
    where its weights are not installed: its runs would be scored without it, for good once their
    checkpoints are gone. A table without LPIPS is made on purpose only (``--no-lpips``).

    Raises:
        AblationError: one line: what is missing, how to install it, and ``--no-lpips``.
    """
    from .. import metrics

    reason = metrics.lpips_unavailable_reason()
    if plan.lpips and reason is not None:
        raise AblationError(f"{reason}; nothing trained: install them, or pass --no-lpips to train and "
                            "score the runs without LPIPS")


def run_each(plan: AblationPlan, runs: list[tuple[str, int]], log: Callable[[str], None]) -> list[dict[str, Any]]:
    """The records of ``runs`` (preset, seed) of ``plan``, one after another (see :func:`run_one`)."""
    records = []
    for i, (preset, seed) in enumerate(runs, 1):
        log(f"[{i}/{len(runs)}] preset {preset}, seed {seed}: {plan.run_folder(preset, seed)}")
        records.append(run_one(plan, preset, seed, log))
        r = records[-1]
        log(f"[{i}/{len(runs)}] preset {preset}, seed {seed}: {r['status']} at step {r['steps']} "
            f"({r['train_seconds']:.1f} s), held-out PSNR {_fmt(r['psnr'])}")
    return records


def run_one(plan: AblationPlan, preset: str, seed: int, log: Callable[[str], None]) -> dict[str, Any]:
    """One run's record (also ``<run>/ablation_run.json``): trained, resumed or read back."""
    cfg = plan.run_config(preset, seed)
    files = RunFiles(Path(cfg.out))
    record_path = files.root / RUN_RECORD
    if record_path.is_file():
        log("  done earlier, skipped")
        return json.loads(record_path.read_text())
    summary = _read_summary(files)
    if summary is None or not _ended(summary):
        summary = _train(cfg, files, log)
    record = {
        "preset": preset,
        "seed": seed,
        "run": str(files.root),
        "status": summary["status"],
        "steps": summary["step"],
        "train_seconds": summary["train_seconds"],
        "steps_per_s": summary["step"] / summary["train_seconds"] if summary["train_seconds"] > 0 else None,
        **_scores(plan, cfg, files, complete=summary["status"] in COMPLETE),
    }
    params, model, trained = checkpoint_model(files.checkpoint)
    record.update(params=params, notes=record["notes"] + model_notes(model) + recipe_notes(trained))
    write_text_atomic(record_path, json.dumps(record, indent=1))
    return record


def checkpoint_model(ckpt: Path) -> tuple[int, ModelConfig, TrainConfig]:
    """The trainable parameters of a checkpoint's fields (both MLPs, proposal networks; not
    buffers), its model configuration and the settings it trained with."""
    state = load_checkpoint(ckpt)
    model = model_config_from_dict(state["model_config"])
    trained = TrainConfig.from_dict(state["train_config"])
    fields = make_fields(trained, model, state["scene"].get("bbox"))
    return sum(p.numel() for p in fields.parameters() if p.requires_grad), model, trained


def _train(cfg: TrainConfig, files: RunFiles, log: Callable[[str], None]) -> dict[str, Any]:
    from ..train import NonFiniteError, Trainer

    resume = files.checkpoint.is_file()
    if not resume:  # a run killed before its first checkpoint left logs that a fresh start would extend
        for name in STALE_FILES:
            (files.root / name).unlink(missing_ok=True)
    trainer = Trainer(cfg, resume=resume, log=lambda line: log(f"  {line}"))
    log(f"  {'resuming at step ' + str(trainer.step) if resume else 'training'}: sampler {trainer.cfg.sampler}, "
        f"{trainer.cfg.steps} steps" + (f" or {cfg.time_budget:g} s" if cfg.time_budget else ""))
    try:
        return trainer.fit()
    except NonFiniteError as e:  # the table shows the run as failed; the other runs go on
        log(f"  {e}")
        return _read_summary(files)
    finally:
        # A trainer sits in reference cycles: only the cycle collector frees its GPU memory (its
        # CUDA graphs' pools among it), which this run's evaluation and the next run need.
        del trainer
        gc.collect()


def _scores(plan: AblationPlan, cfg: TrainConfig, files: RunFiles, complete: bool) -> dict[str, Any]:
    """Held-out means of a complete run (None for a failed one) and the notes of its evaluation."""
    if not complete:
        return _no_scores()
    from ..evaluate import evaluate

    record = evaluate(files.checkpoint, split=plan.split, out=files.root / "eval", device=cfg.device,
                      backend=cfg.backend, max_images=plan.max_images, lpips=plan.lpips, log=lambda _: None)
    s = record["summary"]
    return {"psnr": s["mean_psnr"], "ssim": s["mean_ssim"], "lpips": s["mean_lpips"], "eval_split": s["split"],
            "eval_views": s["images"], "notes": record["notes"]}


def _no_scores() -> dict[str, Any]:
    return {"psnr": None, "ssim": None, "lpips": None, "eval_split": None, "eval_views": 0, "notes": []}


def _read_summary(files: RunFiles) -> dict[str, Any] | None:
    return json.loads(files.summary.read_text()) if files.summary.is_file() else None


def _ended(summary: dict[str, Any]) -> bool:
    """Finished, out of time, or failed for good (non-finite): nothing left to train."""
    return summary["status"] in COMPLETE or summary["status"].startswith("non-finite")


def _fmt(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.2f} dB"
