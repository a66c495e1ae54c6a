"""The paper's ablation: presets x seeds trained under one budget (equal steps or equal training
time), each scored on held-out views, summarised in one table and one plot.

    from mixer_nerf.ablation import AblationPlan, run_ablation
    table = run_ablation(AblationPlan(base=TrainConfig(data="lego", steps=20_000), presets=("A", "D"),
                                      seeds=(0, 1), out=Path("runs/ablate_lego")))

Every run lives in ``<out>/<preset>_seed<seed>/`` (a normal run folder plus ``eval/`` and
``ablation_run.json``); ``<out>`` also receives ``ablation.json`` (the plan), ``ablation.md``,
``table.json``, ``table.csv``, ``runs.csv`` and ``curves.png``.
"""

from .plan import AblationError, AblationPlan, parse_model_overrides, parse_presets, parse_seeds
from .runner import run_ablation

__all__ = ["AblationError", "AblationPlan", "parse_model_overrides", "parse_presets", "parse_seeds", "run_ablation"]
