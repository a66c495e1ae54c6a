"""What an ablation trains: the shared settings, the presets, the seeds, and their run folders."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..model.config import PRESETS, ModelConfig, preset_config
from ..train.config import TrainConfig
from ..train.output import write_text_atomic

PLAN_FILE = "ablation.json"
PER_RUN_SETTINGS = ("preset", "seed", "out", "progress", "ckpt_every", "log_every")
"""TrainConfig fields that differ between the runs of one ablation (or do not change results)."""


class AblationError(ValueError):
    """A bad ablation request (unknown preset, no seeds, a plan that does not match the folder)."""


@dataclass(frozen=True)
class AblationPlan:
    """``base``: the settings every run shares (its preset, seed and out are replaced per run).
    ``target_psnr``: the validation PSNR whose time-to-reach is tabulated (None: the lowest best
    validation PSNR among the runs, so that every run reaches it). ``split`` and ``max_images``: the
    held-out views scored (see :func:`mixer_nerf.evaluate.evaluate`). ``lpips``: score LPIPS too
    (False: PSNR and SSIM only, the table's LPIPS columns empty)."""

    base: TrainConfig
    presets: tuple[str, ...]
    seeds: tuple[int, ...]
    out: Path
    target_psnr: float | None = None
    split: str | None = None
    max_images: int | None = None
    lpips: bool = True

    def __post_init__(self) -> None:
        if not self.presets:
            raise AblationError("no presets to train")
        if not self.seeds:
            raise AblationError("no seeds to train")
        for preset in self.presets:  # the shared model overrides must make a valid model for each
            try:
                preset_config(preset, **self.base.model_overrides)
            except (TypeError, ValueError) as e:
                raise AblationError(f"model overrides for preset {preset}: {e}") from e

    def runs(self) -> list[tuple[str, int]]:
        """Every (preset, seed), presets first."""
        return [(preset, seed) for preset in self.presets for seed in self.seeds]

    def run_config(self, preset: str, seed: int) -> TrainConfig:
        return dataclasses.replace(self.base, preset=preset, seed=seed, out=str(self.run_folder(preset, seed)))

    def run_folder(self, preset: str, seed: int) -> Path:
        return self.out / f"{preset}_seed{seed}"

    def settings(self) -> dict[str, Any]:
        """What a resumed ablation must share with the one that started: every run setting but
        the per-run ones, as JSON values."""
        shared = {k: v for k, v in self.base.to_dict().items() if k not in PER_RUN_SETTINGS}
        # Shared, or a resume could mix runs with and without LPIPS in one table; kept only when off, so
        # that the plans written before this setting existed (all with LPIPS) still match on resume.
        if not self.lpips:
            shared["lpips"] = False
        return json.loads(json.dumps(shared))

    def claim_folder(self, resume: bool) -> None:
        """Create ``out`` and write the plan, refusing a folder whose runs were started by another
        ablation (or by this one, without ``resume``). A plan with no run started yet (e.g. refused
        before training) is simply replaced."""
        path = self.out / PLAN_FILE
        if path.exists() and any(self.out.glob("*_seed*/checkpoint.pt")):
            if not resume:
                raise AblationError(f"{self.out}: already holds an ablation; pass --resume to continue it "
                                    "or choose another --out")
            self.check_settings()
        self.out.mkdir(parents=True, exist_ok=True)
        # Atomic: processes sharing the folder (one per GPU) read it while another writes it.
        write_text_atomic(path, json.dumps({"presets": list(self.presets), "seeds": list(self.seeds),
                                    "settings": self.settings()}, indent=1))


    def check_settings(self) -> None:
        """Refuse a folder whose plan was written with other shared settings (a missing plan passes)."""
        plan = saved_plan(self.out)
        if plan is None:
            return
        saved, settings = plan["settings"], self.settings()
        # A plan written before a setting existed matches its default; one written before a setting
        # joined PER_RUN_SETTINGS still holds it.
        defaults = json.loads(json.dumps(TrainConfig().to_dict()))
        differs = sorted(k for k in (set(saved) | set(settings)) - set(PER_RUN_SETTINGS)
                         if saved.get(k, defaults.get(k)) != settings.get(k))
        if differs:
            raise AblationError(f"{self.out / PLAN_FILE}: the ablation there was started with other settings "
                                f"({', '.join(differs)})")


def saved_plan(out: Path) -> dict[str, Any] | None:
    """The plan the ablation in ``out`` was started with (its presets, seeds and shared settings),
    or None where there is none."""
    path = out / PLAN_FILE
    return json.loads(path.read_text()) if path.is_file() else None


def parse_presets(text: str) -> tuple[str, ...]:
    """"ABCD", "A,D" or "a d" -> ("A", "B", "C", "D"), ("A", "D"), ...; in the order given."""
    letters = [c for c in text.upper() if c not in ", "]
    unknown = sorted(set(letters) - set(PRESETS))
    if unknown:
        raise AblationError(f"unknown preset(s) {', '.join(unknown)} in {text!r} (choose from {''.join(PRESETS)})")
    if not letters:
        raise AblationError("no presets given (e.g. --presets ABCD)")
    return tuple(dict.fromkeys(letters))


def parse_seeds(text: str) -> tuple[int, ...]:
    """"0,1" -> (0, 1)."""
    parts = [p for p in text.replace(" ", ",").split(",") if p]
    if not parts:
        raise AblationError("no seeds given (e.g. --seeds 0,1)")
    try:
        seeds = tuple(dict.fromkeys(int(p) for p in parts))
    except ValueError:
        raise AblationError(f"seeds must be integers separated by commas, got {text!r}") from None
    return seeds


def parse_model_overrides(items: list[str]) -> dict[str, Any]:
    """["se_per_point=true", "width=128", "skips=[4]"] -> {"se_per_point": True, ...}: values are
    JSON (true/false, numbers, lists), else strings, and must have the type of the ModelConfig
    field they set (so that "False" cannot pass for a true string)."""
    defaults = {f.name: f.default for f in dataclasses.fields(ModelConfig)}
    overrides: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise AblationError(f"model override {item!r} is not NAME=VALUE")
        if name not in defaults:
            raise AblationError(f"unknown model setting {name!r} in --model-override (see ModelConfig)")
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = text
        if not _same_kind(value, defaults[name]):
            raise AblationError(f"model setting {name} takes a value like {json.dumps(defaults[name])}, got {text!r}")
        overrides[name] = value
    return overrides


def _same_kind(value: Any, default: Any) -> bool:
    if isinstance(default, bool) or isinstance(value, bool):
        return type(value) is type(default)
    if isinstance(default, tuple):
        return isinstance(value, list)
    if isinstance(default, float):
        return isinstance(value, (int, float))
    return type(value) is type(default)
