"""Long-run numerical stability and multi-seed convergence of training.

1. Stability: a long run at a high learning rate (10x the sampler's default) in bf16 on the built-in
   procedural scene and on Lego, checking the loss, every gradient and every parameter for NaN/Inf
   after every step; reports the first failure (none expected) and the final PSNR.
2. Convergence: short runs with several seeds on Lego and Fern at the default learning rate;
   validation PSNR after N steps per seed, and its spread across seeds.

    python -m benchmarks.long_run_stability                  # GPU defaults: <= 8 minutes on one H100
    python -m benchmarks.long_run_stability --tiny           # CPU smoke test at toy size (~1 minute)

Uses the project's trainer (:class:`mixer_nerf.train.Trainer`, one ``train_step`` at a time). The
checks stay on the device (first bad step per watched tensor, as the trainer's own guard does) and
are read back every ``--check-every`` steps, so they cost no host sync per step; the step they
report is still exact. Every run stops at its step count or its share of ``--budget`` seconds,
whichever comes first. Writes ``<out>/<device>.json`` and ``.md`` (default
``benchmarks/results/long_run_stability/``; device ``cpu``, ``h100``, ...), the runs' training folders
under ``--runs``, and prints a table last.
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from benchmarks.harness import RESULTS, device_tag
from mixer_nerf.metrics import psnr
from mixer_nerf.train import TrainConfig, Trainer
from mixer_nerf.train.config import SAMPLER_RECIPES

TINY_MODEL = {"depth": 2, "width": 32, "skips": (), "view_width": 16, "pos_freqs": 4, "dir_freqs": 2}


@dataclass
class RunReport:
    phase: str  # "stability" or "convergence"
    scene: str
    seed: int
    lr: float
    precision: str
    steps: int  # steps done
    seconds: float  # training time (validation excluded)
    first_failure: str | None  # "step N: what", or None
    final_loss: float | None
    val_psnr: float | None
    notes: list[str] = field(default_factory=list)


class FiniteMonitor:
    """Records, on the device, the first step at which the loss, any gradient or any parameter
    stops being finite; :meth:`first_failure` reads it back (one sync)."""

    def __init__(self, names: list[str], params: list[torch.Tensor], device: torch.device) -> None:
        self.names, self.params = names, params
        self.first = {
            "loss": torch.full((1,), -1, dtype=torch.int64, device=device),
            "gradient": torch.full((len(params),), -1, dtype=torch.int64, device=device),
            "parameter": torch.full((len(params),), -1, dtype=torch.int64, device=device),
        }

    def observe(self, step: int, loss: torch.Tensor) -> None:
        grads = [p.grad if p.grad is not None else torch.zeros(1, device=p.device) for p in self.params]
        bad = {
            "loss": ~torch.isfinite(loss.detach().reshape(1)),
            "gradient": ~torch.isfinite(torch.stack(torch._foreach_norm(grads))),
            "parameter": ~torch.isfinite(torch.stack(torch._foreach_norm([p.detach() for p in self.params]))),
        }
        for key, flags in bad.items():
            first = self.first[key]
            first.copy_(torch.where(flags & (first < 0), step, first))

    def first_failure(self) -> str | None:
        found = []
        for key, first in self.first.items():
            steps = first.cpu()
            for index in torch.nonzero(steps >= 0).flatten().tolist():
                what = key if key == "loss" else f"{key} of {self.names[index]}"
                found.append((int(steps[index]), what))
        if not found:
            return None
        step = min(s for s, _ in found)
        return f"step {step}: " + ", ".join(w for s, w in found if s == step)


def train_and_watch(
    cfg: TrainConfig, phase: str, scene: str, seconds: float, check_every: int, val_rays: int
) -> RunReport:
    """Run ``cfg.steps`` steps (or ``seconds`` of training), watching every step; then validate."""
    trainer = Trainer(cfg, log=lambda _: None)
    monitor = FiniteMonitor(trainer.param_names, trainer.params, trainer.device)
    failure, loss = None, None
    trainer.clock.start()
    while trainer.step < cfg.steps and trainer.clock.now() < seconds:
        loss = trainer.train_step()["loss"]
        monitor.observe(trainer.step, loss)
        if trainer.step % check_every == 0 and (failure := monitor.first_failure()):
            break
    elapsed = trainer.clock.pause()
    failure = failure or monitor.first_failure()
    notes = [] if trainer.step == cfg.steps else [f"stopped by the time budget ({seconds:.0f} s)"]
    score = None if failure else held_out_psnr(trainer, val_rays)
    return RunReport(
        phase=phase,
        scene=scene,
        seed=cfg.seed,
        lr=trainer.cfg.lr,
        precision=trainer.cfg.precision,
        steps=trainer.step,
        seconds=round(elapsed, 2),
        first_failure=failure,
        final_loss=None if loss is None else float(loss),
        val_psnr=None if score is None else round(score, 3),
        notes=notes,
    )


def held_out_psnr(trainer: Trainer, num_rays: int) -> float:
    """PSNR of the trainer's renders of ``num_rays`` held-out pixels, the same pixels for every seed
    (whole validation images would cost minutes on a CPU and are not needed to compare seeds)."""
    scene = trainer.val_scene
    gen = torch.Generator().manual_seed(0)
    flat = torch.randint(len(scene) * scene.H * scene.W, (num_rays,), generator=gen).to(scene.device)
    image_idx, pixel_idx = flat // (scene.H * scene.W), flat % (scene.H * scene.W)
    rays_o, rays_d = scene.rays_at(image_idx, pixel_idx)
    rgb = trainer.render_rgb(rays_o.float(), rays_d.float())
    return float(psnr(rgb.clamp(0, 1)[None], scene.colors_at(image_idx, pixel_idx)[None]))  # a 1 x M image


def scenes(args) -> dict[str, str | None]:
    """name -> data folder (None: the procedural scene); missing folders are reported and skipped."""
    found = {"procedural": None}
    for name, path in (("lego", args.data), ("fern", args.fern)):
        if path and Path(path).is_dir():
            found[name] = str(path)
        else:
            print(f"skipping {name}: no scene folder at {path}")
    return found


def base_config(args, data: str | None, out: Path, **changes) -> TrainConfig:
    settings = {
        "data": data,
        "out": str(out),
        "steps": args.stability_steps,
        "batch_rays": args.batch_rays,
        "num_coarse": args.num_coarse,
        "num_fine": args.num_fine,
        "device": args.device,
        "precision": args.precision,
        "sampler": args.sampler,
        "progress": False,
        "check_grads": True,
        "downscale": args.downscale if data and "lego" in data else 1,
        "procedural_resolution": 16 if args.tiny else 100,
        "procedural_views": 8 if args.tiny else 100,
        "model_overrides": TINY_MODEL if args.tiny else {},
        # The trainer's own validation/checkpoint cadence never triggers: this script drives steps.
        "val_every": 10**9,
        "ckpt_every": 10**9,
        "log_every": 10**9,
    }
    return TrainConfig(**{**settings, **changes})


HEADER = (
    f"{'phase':<12}{'scene':<12}{'seed':>5}{'lr':>9}{'prec':>6}{'steps':>7}{'sec':>8}"
    f"{'loss':>10}{'val PSNR':>10}  first non-finite"
)


def row(r: RunReport) -> str:
    loss = "-" if r.final_loss is None else f"{r.final_loss:.4f}"
    score = "-" if r.val_psnr is None else f"{r.val_psnr:.2f}"
    notes = f"  ({'; '.join(r.notes)})" if r.notes else ""
    return (
        f"{r.phase:<12}{r.scene:<12}{r.seed:>5}{r.lr:>9.1e}{r.precision:>6}{r.steps:>7}{r.seconds:>8.1f}"
        f"{loss:>10}{score:>10}  {r.first_failure or 'none'}{notes}"
    )


def table(reports: list[RunReport]) -> str:
    """One row per run, then the PSNR spread across seeds of each convergence scene."""
    lines = [HEADER, *(row(r) for r in reports)]
    for scene in dict.fromkeys(r.scene for r in reports if r.phase == "convergence"):
        values = [r.val_psnr for r in reports if r.phase == "convergence" and r.scene == scene and r.val_psnr]
        if values:
            spread = statistics.pstdev(values) if len(values) > 1 else 0.0
            lines.append(
                f"convergence {scene}: PSNR mean {statistics.mean(values):.2f} dB, std {spread:.2f}, "
                f"min {min(values):.2f}, max {max(values):.2f} over {len(values)} seeds"
            )
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=".data/lego_400", help="Lego (Blender) folder")
    parser.add_argument("--fern", default=".data/fern_8", help="Fern (LLFF) folder")
    parser.add_argument("--out", type=Path, default=RESULTS / "long_run_stability",
                        help="folder of the result files")
    parser.add_argument("--runs", type=Path, default=Path("runs/long_run_stability"),
                        help="folder of the runs' training outputs")
    parser.add_argument(
        "--device", choices=("cpu", "cuda"), default="cuda" if torch.cuda.is_available() else "cpu"
    )
    parser.add_argument(
        "--precision", choices=("bf16", "tf32", "fp32"), help="default: bf16 on CUDA, fp32 on CPU"
    )
    parser.add_argument("--tiny", action="store_true", help="toy sizes for a CPU smoke test")
    parser.add_argument("--stability-steps", type=int, default=3000)
    parser.add_argument("--stability-lr", type=float,
                        help="default: 10x the sampler's recipe (occupancy 4e-2, hierarchical 5e-3)")
    parser.add_argument("--convergence-steps", type=int, default=500)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--batch-rays", type=int, default=4096)
    parser.add_argument("--num-coarse", type=int, default=64)
    parser.add_argument("--num-fine", type=int, default=128)
    parser.add_argument("--downscale", type=int, default=2, help="Lego image downscale (validation renders)")
    parser.add_argument("--val-rays", type=int, default=65536, help="held-out pixels scored after each run")
    parser.add_argument("--sampler", choices=("auto", "occupancy", "hierarchical"), default="auto")
    parser.add_argument("--budget", type=float, default=400.0, help="seconds of training in all (not setup)")
    parser.add_argument(
        "--check-every", type=int, help="read the monitor back every N steps (default 50, CPU 1)"
    )
    args = parser.parse_args(argv)
    if args.tiny:
        args.stability_steps, args.convergence_steps = (
            min(args.stability_steps, 30),
            min(args.convergence_steps, 15),
        )
        args.batch_rays, args.num_coarse, args.num_fine = 64, 8, 8
        args.downscale, args.val_rays, args.budget = 8, 1024, min(args.budget, 60.0)
        args.sampler = "hierarchical"  # the occupancy sampler's fine marching step is slow on a CPU
    if args.stability_lr is None:  # the stability scenes are bounded: "auto" samples by occupancy
        sampler = "hierarchical" if args.sampler == "hierarchical" else "occupancy"
        args.stability_lr = 10 * SAMPLER_RECIPES[sampler]["lr"]
    if args.precision is None:
        args.precision = "bf16" if args.device == "cuda" else "fp32"
    if args.check_every is None:
        args.check_every = 50 if args.device == "cuda" else 1
    return args


def write_results(args: argparse.Namespace, argv: list[str] | None, reports: list[RunReport]) -> str:
    """Write ``<out>/<device>.json`` and ``.md`` (the command and the table); return the table."""
    failed = [r for r in reports if r.first_failure]
    text = (table(reports) + f"\n\n{len(failed)} of {len(reports)} runs went non-finite"
            + ("" if failed else " (none expected)"))
    given = sys.argv[1:] if argv is None else argv
    command = shlex.join(["python", "-m", "benchmarks.long_run_stability", *given])
    settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    tag = device_tag(args.device)
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"settings": settings, "runs": [asdict(r) for r in reports]}
    (args.out / f"{tag}.json").write_text(json.dumps(record, indent=1))
    (args.out / f"{tag}.md").write_text(
        f"# Long-run stability and multi-seed convergence ({tag}, {time.strftime('%Y-%m-%d')})\n\n"
        f"`{command}`\n\n```\n{text}\n```\n")
    return text


def main(argv=None) -> list[RunReport]:
    args = parse_args(argv)
    found = scenes(args)
    stability = [name for name in ("procedural", "lego") if name in found]
    convergence = [name for name in ("lego", "fern") if name in found]
    # A stability run gets 2.5x the time of a convergence run.
    share = args.budget / max(2.5 * len(stability) + len(convergence) * len(args.seeds), 1)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    reports = []
    print(HEADER)
    for name in stability:
        cfg = base_config(
            args,
            found[name],
            args.runs / stamp / f"stability_{name}",
            lr=args.stability_lr,
            lr_final=args.stability_lr / 10,
        )
        reports.append(train_and_watch(cfg, "stability", name, 2.5 * share, args.check_every, args.val_rays))
        print(row(reports[-1]), flush=True)
    for name in convergence:
        for seed in args.seeds:
            cfg = base_config(
                args,
                found[name],
                args.runs / stamp / f"convergence_{name}_seed{seed}",
                steps=args.convergence_steps,
                seed=seed,
            )
            reports.append(train_and_watch(cfg, "convergence", name, share, args.check_every, args.val_rays))
            print(row(reports[-1]), flush=True)
    print()
    print(write_results(args, argv, reports))
    return reports


if __name__ == "__main__":
    main()
