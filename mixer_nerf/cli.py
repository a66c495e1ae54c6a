"""The ``mixer-nerf`` command line: train, eval, render, demo and ablate.

Errors a user can fix (missing or malformed data, unwritable output, bad checkpoints, a run that
went non-finite) print one line naming the file and exit with status 1; usage errors exit with 2.
Set ``MIXER_NERF_DEBUG=1`` to see the full traceback instead.
"""

from __future__ import annotations

import argparse
import errno
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .data import FORMATS
from .render.image_renderer import RENDER_SAMPLES
from .train.config import BACKENDS, DEMO_SETTINGS, PRECISIONS, PRESETS, SAMPLERS, TrainConfig

DEMO_OUT = "runs/demo"
DEMO_VIDEO_FRAMES = 40
VIDEO_PATHS = ("auto", "turntable", "spiral")

# Train options whose default depends on the scene (demo or real data) are None in argparse, so
# that only what the user typed overrides TrainConfig's defaults or DEMO_SETTINGS.
TRAIN_OPTIONS: dict[str, dict[str, Any]] = {
    "--format": {"choices": FORMATS, "help": "scene format (default: detected)"},
    "--preset": {"choices": PRESETS, "help": "A NeRF, B +SE, C +MLCA, D Mixer-NeRF (default D)"},
    "--steps": {"type": int, "help": "training steps, also the length of the lr schedule"},
    "--batch-rays": {"type": int, "help": "rays per step"},
    "--num-coarse": {"type": int, "help": "coarse samples per ray"},
    "--num-fine": {"type": int, "help": "fine samples per ray (0: no fine pass)"},
    "--lr": {"type": float, "help": "learning rate after the warm-up (default: occupancy sampler "
             "4e-3, hierarchical 5e-4), decaying exponentially to --lr-final"},
    "--lr-final": {"type": float, "help": "learning rate at the end of the run, --steps or "
                   "--time-budget, whichever comes first (default: lr/10)"},
    "--lr-warmup": {"type": int, "metavar": "STEPS",
                    "help": "linear learning-rate warm-up (default: occupancy 200, hierarchical 0)"},
    "--lr-hold": {"type": float, "metavar": "FRACTION",
                  "help": "fraction of the run at --lr before the decay to --lr-final starts (default: "
                  "occupancy sampler 0.5, hierarchical 0)"},
    "--precision": {"choices": PRECISIONS, "help": "MLP precision (default: tf32 on CUDA, fp32 on CPU)"},
    "--seed": {"type": int, "help": "random seed"},
    "--val-every": {"type": int, "help": "validate every N steps"},
    "--ckpt-every": {"type": int, "help": "checkpoint every N steps (a killed run loses at most N)"},
    "--time-budget": {"type": float, "metavar": "SECONDS", "help": "stop after this much training time"},
    "--downscale": {"type": float, "help": "image downscale, any factor >= 1"},
    "--sampler": {
        "choices": SAMPLERS,
        "help": "occupancy (skip empty space, occluded samples, missed rays), "
        "hierarchical (NeRF's dense coarse + fine), auto (occupancy for bounded scenes such as Blender's, hierarchical for forward-facing LLFF)",
    },
    "--target-samples": {
        "type": int,
        "help": "occupancy sampler: MLP samples per step (the ray batch adapts)",
    },
    "--early-stop-eps": {"type": float, "help": "stop rays whose transmittance falls below this (0: never)"},
    "--empty-space-weight": {
        "type": float,
        "help": "occupancy sampler: weight of the loss that keeps density out of the cells the grid "
        "marks empty, applied at each grid refresh (default 1e-2; 0: off)",
    },
    "--bf16-density-passes": {
        "action": argparse.BooleanOptionalAction,
        "help": "occupancy sampler: no-grad density passes (grid refreshes, early termination) in bf16 "
        "(default: on CUDA)",
    },
    "--grid-resolution": {"type": int, "help": "occupancy grid cells per axis"},
}


class UserError(Exception):
    """A problem the user can fix; printed as one line."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mixer-nerf", description="Train, evaluate and render Mixer-NeRF.")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    train = commands.add_parser("train", help="train a model (no --data: the built-in demo, end to end)")
    train.add_argument(
        "--data", help="scene folder (Blender or LLFF); default: the built-in procedural scene"
    )
    _add_train_options(train, default_out="runs/<scene>; runs/demo without --data")

    evaluate = commands.add_parser("eval", help="score a checkpoint on held-out views")
    evaluate.add_argument("--ckpt", required=True, help="checkpoint file (e.g. runs/demo/checkpoint.pt)")
    evaluate.add_argument("--data", help="scene folder (default: the one trained on)")
    evaluate.add_argument(
        "--split",
        choices=("test", "val", "train"),
        help="default: test, or val when the scene has no test views",
    )
    evaluate.add_argument("--out", help="output folder (default: <checkpoint folder>/eval_<split>)")
    evaluate.add_argument("--max-images", type=int, help="score only the first N views")
    _add_device_options(evaluate)

    render = commands.add_parser("render", help="render a turntable/spiral video and depth maps")
    render.add_argument("--ckpt", required=True, help="checkpoint file")
    render.add_argument("--frames", type=int, default=120, help="number of frames (default 120)")
    render.add_argument(
        "--path",
        choices=VIDEO_PATHS,
        default="auto",
        help="camera path (default: spiral for forward-facing scenes, else turntable)",
    )
    render.add_argument("--fps", type=int, default=30)
    render.add_argument("--scale", type=float, default=1.0, help="resolution relative to the training images")
    render.add_argument("--out", help="output folder (default: <checkpoint folder>/video)")
    _add_device_options(render)

    demo = commands.add_parser(
        "demo", help="train, evaluate and render the built-in scene (a few CPU minutes)"
    )
    _add_train_options(demo, default_out=DEMO_OUT)
    demo.set_defaults(data=None)
    _add_prepare_parser(commands)
    _add_ablate_parser(commands)
    return parser


def _add_prepare_parser(commands: argparse._SubParsersAction) -> None:
    from .prepare import CAMERA_MODELS, DEFAULT_CAMERA_MODEL, DEFAULT_EVERY, EXHAUSTIVE_MAX, MATCHERS

    prepare = commands.add_parser(
        "prepare", help="solve the camera poses of your photos or video with COLMAP (needs .[prepare])"
    )
    prepare.add_argument("input", help="folder of photos (png/jpg) or a video file")
    prepare.add_argument("out", help="new scene folder (COLMAP model + undistorted images) for train --data")
    prepare.add_argument(
        "--every", type=int, default=DEFAULT_EVERY, help="video: keep every N-th frame (default %(default)s)"
    )
    prepare.add_argument(
        "--matcher", choices=MATCHERS, default="auto",
        help=f"feature matching (auto: exhaustive for up to {EXHAUSTIVE_MAX} photos, sequential for more "
        "or a video)",
    )  # fmt: skip
    prepare.add_argument(
        "--camera-model", choices=CAMERA_MODELS, default=DEFAULT_CAMERA_MODEL,
        help=f"COLMAP camera model to solve for (default {DEFAULT_CAMERA_MODEL})",
    )  # fmt: skip
    prepare.add_argument("--verbose", action="store_true", help="show COLMAP's own log")


def train_config_from_args(args: argparse.Namespace) -> TrainConfig:
    """TrainConfig defaults, then the demo settings when no --data is given, then what was typed.
    A resumed train takes only what was typed (its checkpoint holds the rest)."""
    resumed_run = args.command in ("train", "demo") and args.resume
    values: dict[str, Any] = {} if args.data or resumed_run else dict(DEMO_SETTINGS)
    typed = {flag.lstrip("-").replace("-", "_") for flag in TRAIN_OPTIONS} | {"data", "device", "backend",
                                                                               "render_samples"}
    values.update({k: getattr(args, k) for k in typed if getattr(args, k, None) is not None})
    values["out"] = args.out or (f"runs/{Path(args.data).name}" if args.data else DEMO_OUT)
    values["progress"] = not args.no_progress
    return TrainConfig(**values)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return COMMANDS[args.command](args)
    except KeyboardInterrupt:
        print("mixer-nerf: interrupted (the last checkpoint is kept)", file=sys.stderr)
        return 130
    except Exception as e:
        if os.environ.get("MIXER_NERF_DEBUG") or not _is_user_error(e):
            raise
        print(f"mixer-nerf: error: {e}", file=sys.stderr)
        return 1


def run_train(args: argparse.Namespace) -> int:
    cfg = train_config_from_args(args)
    if args.data is None and not args.resume:
        chosen = {k: getattr(cfg, k) for k in DEMO_SETTINGS}
        print(
            "no --data: training on the built-in procedural scene with CPU-friendly settings:\n  "
            + ", ".join(f"{k}={v}" for k, v in chosen.items())
        )
    summary = _train(cfg, args.resume, args.overwrite)
    ckpt = Path(summary["checkpoint"])
    views = args.eval_views
    held_out = None if views == 0 else _evaluate(ckpt, device=cfg.device, backend=cfg.backend, max_images=views)
    video = (
        _render(ckpt, DEMO_VIDEO_FRAMES, device=cfg.device, backend=cfg.backend)
        if args.data is None
        else None
    )
    _report(summary, held_out, video)
    return 0


def run_eval(args: argparse.Namespace) -> int:
    from .evaluate import evaluate

    if args.max_images is not None and args.max_images < 1:
        raise UserError(f"--max-images must be positive, got {args.max_images}")
    _check_render_samples(args)
    record = evaluate(
        args.ckpt, data=args.data, split=args.split, out=args.out, device=args.device, backend=args.backend,
        max_images=args.max_images, render_samples=args.render_samples,
    )
    _print_eval(record)
    return 0


def run_render(args: argparse.Namespace) -> int:
    from .video import render_video

    _check_render_samples(args)
    result = render_video(
        args.ckpt,
        out=args.out,
        frames=args.frames,
        path=args.path,
        fps=args.fps,
        scale=args.scale,
        device=args.device,
        backend=args.backend,
        render_samples=args.render_samples,
    )
    _print_video(result)
    return 0


def _check_render_samples(args: argparse.Namespace) -> None:
    if args.render_samples is not None and args.render_samples < 1:
        raise UserError(f"--render-samples must be positive, got {args.render_samples}")


def run_prepare(args: argparse.Namespace) -> int:
    from .prepare import prepare

    prepare(args.input, args.out, every=args.every, matcher=args.matcher, camera_model=args.camera_model,
            verbose=args.verbose)  # fmt: skip
    return 0


def run_ablate(args: argparse.Namespace) -> int:
    import dataclasses

    from .ablation import AblationPlan, parse_model_overrides, parse_presets, parse_seeds, run_ablation

    if args.steps is None and args.time_budget is None:
        raise UserError("give --steps N (equal steps) or --time-budget SECONDS (equal training time)")
    if args.max_images is not None and args.max_images < 1:
        raise UserError(f"--max-images must be positive, got {args.max_images}")
    base = train_config_from_args(args)
    overrides = {**base.model_overrides, **parse_model_overrides(args.model_override)}
    plan = AblationPlan(
        base=dataclasses.replace(base, model_overrides=overrides), presets=parse_presets(args.presets),
        seeds=parse_seeds(args.seeds), out=Path(args.out), target_psnr=args.target_psnr, split=args.split,
        max_images=args.max_images,
    )
    table = run_ablation(plan, resume=args.resume)
    print(f"table: {Path(args.out) / 'ablation.md'}")
    for row in table["presets"]:
        psnr = "-" if row["psnr_mean"] is None else f"{row['psnr_mean']:.2f} dB"
        print(f"  preset {row['preset']} ({row['model']}): held-out PSNR {psnr} over {row['seeds']} seed(s)")
    return 0


COMMANDS = {"train": run_train, "eval": run_eval, "render": run_render, "demo": run_train, "prepare": run_prepare,
            "ablate": run_ablate}


def _train(cfg: TrainConfig, resume: bool, overwrite: bool) -> dict[str, Any]:
    from .train import Trainer

    trainer = Trainer(cfg, resume=resume, overwrite=overwrite)
    c = trainer.cfg
    sampling = (
        f"occupancy-grid sampling, ~{c.target_samples} samples per step"
        if c.sampler == "occupancy"
        else f"{c.batch_rays} rays x ({c.num_coarse} + {c.num_fine}) samples"
    )
    print(
        f"training {c.steps} steps on {c.device} ({c.precision}, backend {c.backend}), preset {c.preset}, "
        f"{sampling} -> {trainer.files.root}"
    )
    summary = trainer.fit()
    print(f"training {summary['status']} at step {summary['step']} after {summary['train_seconds']:.1f} s")
    return summary


def _evaluate(ckpt: Path, **kwargs: Any) -> dict[str, Any]:
    from .evaluate import evaluate

    return evaluate(ckpt, log=lambda _: None, **kwargs)


def _render(ckpt: Path, frames: int, **kwargs: Any) -> dict[str, Any]:
    from .video import render_video

    return render_video(ckpt, frames=frames, log=lambda _: None, **kwargs)


def _report(summary: dict[str, Any], held_out: dict[str, Any] | None, video: dict[str, Any] | None) -> None:
    root = Path(summary["checkpoint"]).parent
    print(f"checkpoint:   {summary['checkpoint']}")
    print(f"logs:         {root / 'train_log.csv'}, {root / 'val_log.csv'}, plot {summary['curves']}")
    if held_out is not None:
        _print_eval(held_out)
    if video is not None:
        _print_video(video)


def _print_eval(record: dict[str, Any]) -> None:
    s = record["summary"]
    scores = ", ".join(
        f"{name} {s[f'mean_{name}']:.4g}"
        for name in ("psnr", "ssim", "lpips")
        if s[f"mean_{name}"] is not None
    )
    print(f"eval ({s['split']}, {s['images']} views): {scores}")
    print(f"  renders and metrics in {record['out']} (metrics.json, metrics.csv, images/, depth/)")
    for note in record["notes"]:
        print(f"  note: {note}")


def _print_video(result: dict[str, Any]) -> None:
    print(f"video ({result['path']}, {result['frames']} frames, {result['format']}): {result['video']}")
    print(f"  depth: {result['depth_video']} and {result['depth_frames']}/")


def _add_train_options(parser: argparse.ArgumentParser, default_out: str) -> None:
    for flag, options in TRAIN_OPTIONS.items():
        parser.add_argument(flag, default=None, **options)
    parser.add_argument("--out", help=f"run folder (default: {default_out})")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint "
                        "(a new --steps extends it; --device moves it; other settings must match)")
    parser.add_argument("--overwrite", action="store_true", help="delete the run in --out and start over")
    parser.add_argument("--eval-views", type=_eval_views, metavar="N|none",
                        help="held-out views scored after training (default: all; none: skip)")
    _add_device_options(parser)
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _eval_views(text: str) -> int:
    """``--eval-views``: a positive count, or "none" (0)."""
    if text == "none":
        return 0
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a positive number of views or 'none', got {text!r}")
    return int(text)


def _add_ablate_parser(commands: Any) -> None:
    ablate = commands.add_parser(
        "ablate", help="train presets x seeds for equal steps or equal time and tabulate held-out scores"
    )
    ablate.add_argument("--data", help="scene folder (default: the built-in procedural scene)")
    ablate.add_argument("--presets", default="ABCD", help="presets to train, e.g. ABCD or A,D (default ABCD)")
    ablate.add_argument("--seeds", default="0,1", help="seeds, comma-separated (default 0,1)")
    ablate.add_argument(
        "--model-override", action="append", default=[], metavar="NAME=VALUE",
        help="a ModelConfig setting for every run, e.g. se_per_point=true (repeatable)",
    )
    ablate.add_argument("--target-psnr", type=float, metavar="DB",
                        help="tabulate the training time to this validation PSNR (default: the lowest "
                        "best validation PSNR among the runs)")
    ablate.add_argument("--split", choices=("test", "val", "train"), help="held-out views scored (as eval)")
    ablate.add_argument("--max-images", type=int, help="score only the first N held-out views")
    for flag, options in TRAIN_OPTIONS.items():
        if flag not in ("--preset", "--seed"):
            ablate.add_argument(flag, default=None, **options)
    ablate.add_argument("--out", required=True, help="ablation folder: one run folder per preset and seed")
    ablate.add_argument("--resume", action="store_true",
                        help="continue the ablation in --out: skip finished runs, resume unfinished ones")
    _add_device_options(ablate)
    ablate.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_device_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", choices=("cpu", "cuda"), help="default: cuda when available")
    parser.add_argument("--backend", choices=BACKENDS, help="ops: compiled kernels or the PyTorch reference")
    parser.add_argument("--render-samples", type=int, metavar="N",
                        help="most samples shaded at once when rendering images: bounds the memory "
                        f"(default: {RENDER_SAMPLES['cpu']} on CPU, {RENDER_SAMPLES['cuda']} on CUDA)")


def _is_user_error(e: Exception) -> bool:
    from .data import DatasetError
    from .train import CheckpointError, NonFiniteError, OutputError

    if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
        return True  # disk full, quota, read-only: the user frees space or picks another --out
    return isinstance(
        e,
        (
            UserError,
            DatasetError,
            CheckpointError,
            NonFiniteError,
            OutputError,
            FileNotFoundError,
            PermissionError,
            ValueError,
        ),
    )
