"""The ``mixer-nerf`` command line: train, eval, render, demo and ablate.

Errors a user can fix (missing or malformed data, unwritable output, bad checkpoints, a run that
went non-finite) print one line naming the file and exit with status 1; usage errors exit with 2.
Set ``MIXER_NERF_DEBUG=1`` to see the full traceback instead.
"""

from __future__ import annotations

import argparse
import errno
import gc
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .cli_options import DEVICE_FLAGS, add_options, train_options, typed_settings
from .train.config import DEMO_SETTINGS, TrainConfig

DEMO_OUT = "runs/demo"
DEMO_VIDEO_FRAMES = 40
VIDEO_PATHS = ("auto", "turntable", "spiral", "train", "test")
EVAL_VIEWS_CPU = 1  # a 400x400 view of preset D takes minutes on a CPU (docs/training.md#memory)


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
    add_options(evaluate, ["--render-samples"])

    render = commands.add_parser("render", help="render a video and depth maps along a camera path")
    render.add_argument("--ckpt", required=True, help="checkpoint file")
    render.add_argument("--frames", type=int, default=120, help="number of frames (default 120)")
    render.add_argument(
        "--path",
        type=_camera_path_arg,
        default="auto",
        metavar="{" + ",".join(VIDEO_PATHS) + "} or FILE.json",
        help="camera path: generated (default auto: spiral for forward-facing scenes, else turntable), the "
        "dataset's own train or test cameras, or a nerfstudio camera-path JSON file",
    )
    render.add_argument("--fps", type=int, default=30)
    render.add_argument("--scale", type=float, default=1.0, help="resolution relative to the training images")
    render.add_argument("--out", help="output folder (default: <checkpoint folder>/video)")
    _add_device_options(render)
    add_options(render, ["--render-samples"])

    demo = commands.add_parser(
        "demo", help="train, evaluate and render the built-in scene (a few CPU minutes)"
    )
    _add_train_options(demo, default_out=DEMO_OUT)
    demo.set_defaults(data=None)
    _add_prepare_parser(commands)
    _add_ablate_parser(commands)
    _add_export_parser(commands)
    commands.add_parser(
        "doctor", help="versions, GPU, which kernels run and why, a 10 s accuracy check of each op"
    )
    return parser


def _add_export_parser(commands: argparse._SubParsersAction) -> None:
    export = commands.add_parser(
        "export", help="a mesh, a point cloud or raw depth maps of a trained scene (mesh, points: .[export])"
    )
    kinds = export.add_subparsers(dest="what", metavar="WHAT", required=True)
    mesh = kinds.add_parser("mesh", help="marching cubes over the density in the occupancy grid's box")
    mesh.add_argument("--resolution", type=int, default=256, help="lattice points per axis (default 256)")
    mesh.add_argument("--threshold", type=float, default=10.0, help="density of the surface (default 10)")
    points = kinds.add_parser("points", help="coloured point cloud (PLY) from the depth of rendered views")
    points.add_argument("--min-opacity", type=float, default=0.5, help="pixels kept (default 0.5)")
    points.add_argument("--max-points", type=int, default=1_000_000, help="random subset (default 1,000,000)")
    depth = kinds.add_parser("depth", help="raw depth and opacity (NPY, EXR with OpenEXR) and depth previews")
    outs = ((mesh, "export/mesh.ply"), (points, "export/points.ply"), (depth, "depth_<path>"))
    for parser, default_out in outs:
        parser.add_argument("--ckpt", required=True, help="checkpoint file")
        parser.add_argument("--out", help=f"output (default: <checkpoint folder>/{default_out})")
        _add_device_options(parser)
    for parser, default_path, scale in ((points, "train", 0.5), (depth, "test", 1.0)):
        parser.add_argument("--path", type=_camera_path_arg, default=default_path,
                            help=f"cameras to render, as render --path (default {default_path})")
        parser.add_argument("--frames", type=int, default=30, help="frames of a generated path (default 30)")
        parser.add_argument("--scale", type=float, default=scale,
                            help=f"resolution relative to the training images (default {scale})")


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
    """TrainConfig defaults, then the demo settings when there is no scene folder, then the --config
    file, then what was typed. A resumed train takes no demo settings (its checkpoint holds them)."""
    from .train.config_file import read_config_file

    from_file = read_config_file(args.config) if getattr(args, "config", None) else {}
    data = args.data or from_file.get("data")
    resumed_run = args.command in ("train", "demo") and args.resume
    values: dict[str, Any] = {} if data or resumed_run else dict(DEMO_SETTINGS)
    values.update(from_file)
    values.update(typed_settings(args))
    values["data"] = data
    values["out"] = args.out or from_file.get("out") or (f"runs/{Path(data).name}" if data else DEMO_OUT)
    values["progress"] = not args.no_progress
    return TrainConfig(**values)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv  # --devices relaunches the same command under torchrun
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
        rank = f" (rank {os.environ['RANK']})" if "RANK" in os.environ else ""  # under torchrun
        print(f"mixer-nerf: error{rank}: {e}", file=sys.stderr)
        return 1


def run_train(args: argparse.Namespace) -> int:
    cfg = train_config_from_args(args)
    if args.devices is not None and _relaunched(args, cfg):
        return 0
    rank = int(os.environ.get("RANK", "0"))
    if cfg.data is None and not args.resume and rank == 0:
        chosen = {k: getattr(cfg, k) for k in DEMO_SETTINGS}
        print(
            "no --data: training on the built-in procedural scene with CPU-friendly settings:\n  "
            + ", ".join(f"{k}={v}" for k, v in chosen.items())
        )
    summary = _train(cfg, args.resume, args.overwrite)
    if rank:
        return 0  # rank 0 evaluates and reports
    ckpt = Path(summary["checkpoint"])
    views = eval_views(args.eval_views, summary["device"], builtin=cfg.data is None)
    held_out = None if views == 0 else _evaluate(ckpt, device=cfg.device, backend=cfg.backend, max_images=views)
    if held_out is not None and args.eval_views is None and views is not None:
        held_out["notes"].append(f"a CPU scores {views} held-out view by default after training; "
                                 f"--eval-views all, or `mixer-nerf eval --ckpt {ckpt}`, scores every view")
    video = (
        _render(ckpt, DEMO_VIDEO_FRAMES, device=cfg.device, backend=cfg.backend)
        if cfg.data is None
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

    from .ablation import AblationPlan, parse_model_overrides, parse_presets, parse_seeds
    from .ablation.runner import report
    from .ablation.workers import parse_gpus

    gpus = None if args.gpus is None else parse_gpus(args.gpus)
    if args.max_images is not None and args.max_images < 1:
        raise UserError(f"--max-images must be positive, got {args.max_images}")
    if args.report:
        if gpus is not None or args.runs is not None:
            raise UserError("--report trains nothing: drop --gpus")
        base, presets, seeds, lpips = _saved_ablation(args)
    else:
        if args.steps is None and args.time_budget is None:
            raise UserError("give --steps N (equal steps) or --time-budget SECONDS (equal training time)")
        base, lpips = train_config_from_args(args), True
        presets = "ABCD" if args.presets is None else args.presets
        seeds = "0,1" if args.seeds is None else args.seeds
    overrides = {**base.model_overrides, **parse_model_overrides(args.model_override)}
    plan = AblationPlan(
        base=dataclasses.replace(base, model_overrides=overrides), presets=parse_presets(presets),
        seeds=parse_seeds(seeds), out=Path(args.out), target_psnr=args.target_psnr, split=args.split,
        max_images=args.max_images, lpips=lpips and not args.no_lpips,
    )
    if args.report:
        table = report(plan)  # refuses a typed setting that differs from the saved plan's
    else:
        table = _train_ablation(args, plan, gpus)
        if table is None:
            return 0
    print(f"table: {Path(args.out) / 'ablation.md'}")
    for row in table["presets"]:
        psnr = "-" if row["psnr_mean"] is None else f"{row['psnr_mean']:.2f} dB"
        scored = sum(r["preset"] == row["preset"] and r["psnr"] is not None for r in table["runs"])
        print(f"  preset {row['preset']} ({row['model']}): held-out PSNR {psnr} "
              f"over {scored} of {row['seeds']} run(s)")
    return 0


def _saved_ablation(args: argparse.Namespace) -> tuple[TrainConfig, str, str, bool]:
    """--report's settings, presets, seeds and LPIPS: those of the plan saved in --out, with what
    was typed on top."""
    from .ablation.plan import PLAN_FILE, saved_plan

    saved = saved_plan(Path(args.out))
    if saved is None:
        raise UserError(f"{args.out}: no ablation to report ({PLAN_FILE} missing)")
    settings = dict(saved["settings"])
    lpips = settings.pop("lpips", True)
    values = {**settings, **typed_settings(args), "out": args.out, "progress": False}
    if args.data:
        values["data"] = args.data
    presets = ",".join(saved["presets"]) if args.presets is None else args.presets
    seeds = ",".join(str(seed) for seed in saved["seeds"]) if args.seeds is None else args.seeds
    return TrainConfig.from_dict(values), presets, seeds, lpips


def _train_ablation(args: argparse.Namespace, plan: Any, gpus: list[int] | None) -> dict[str, Any] | None:
    """Train and score ``plan``'s runs (a ``--runs`` worker: its share only, returning None) and
    return the table."""
    from .ablation import run_ablation
    from .ablation.runner import check_lpips, run_each
    from .ablation.workers import parse_runs, train_on_gpus

    check_lpips(plan)  # every mode (plain, --gpus, a worker's --runs), before a folder is claimed
    if args.runs is not None:  # a worker of --gpus: its share of the runs; the caller writes the table
        plan.claim_folder(resume=True)
        run_each(plan, parse_runs(args.runs, plan), print)
        return None
    if gpus is not None:
        plan.claim_folder(args.resume)
        train_on_gpus(plan, _without_option(args.argv, "--gpus"), gpus)
    return run_ablation(plan, resume=args.resume or gpus is not None)


def _without_option(argv: Sequence[str], flag: str) -> list[str]:
    """``argv`` without ``flag VALUE`` or ``flag=VALUE``."""
    kept, skip = [], False
    for item in argv:
        if skip:
            skip = False
        elif item == flag:
            skip = True
        elif not item.startswith(flag + "="):
            kept.append(item)
    return kept


def run_export(args: argparse.Namespace) -> int:
    from .export import export_depth, export_mesh, export_points

    device = {"device": args.device, "backend": args.backend}
    default = Path(args.ckpt).parent / "export" / f"{'mesh' if args.what == 'mesh' else 'points'}.ply"
    if args.what == "mesh":
        r = export_mesh(args.ckpt, args.out or default, args.resolution, args.threshold, **device)
        print(f"mesh: {r['mesh']} ({r['vertices']} vertices, {r['faces']} faces, "
              f"{'watertight' if r['watertight'] else 'not watertight'})")
    elif args.what == "points":
        r = export_points(
            args.ckpt, args.out or default, args.path, args.frames, args.scale, args.min_opacity,
            args.max_points, **device,
        )  # fmt: skip
        print(f"points: {r['points']} ({r['count']} points from {r['views']} views)")
    else:
        r = export_depth(args.ckpt, args.out, args.path, args.frames, args.scale, **device)
        print(f"depth: {r['out']} ({r['views']} views: depth_NNNN.npy, opacity_NNNN.npy, depth_NNNN.png"
              f"{', depth_NNNN.exr' if r['exr'] else '; no EXR writer (pip install OpenEXR)'})")
        return 0
    box = f", scene box {_box(r['scene_box'])}" if "scene_box" in r else ""
    print(f"  bounds {_box(r['bounds'])}{box}")
    return 0


def _box(bounds: list[list[float]]) -> str:
    return " to ".join("(" + ", ".join(f"{v:.3f}" for v in corner) + ")" for corner in bounds)


def run_doctor(args: argparse.Namespace) -> int:
    from .doctor import run_doctor as doctor

    return doctor()


COMMANDS = {"train": run_train, "eval": run_eval, "render": run_render, "demo": run_train,
            "prepare": run_prepare, "ablate": run_ablate, "export": run_export, "doctor": run_doctor}


def _relaunched(args: argparse.Namespace, cfg: TrainConfig) -> bool:
    """Run this same command under torchrun on ``--devices`` processes, unless it is one of them
    already or N is 1 (False: train here).

    Raises:
        UserError: N is not positive, not torchrun's number of processes, or more than the GPUs.
    """
    import torch

    from .train.distributed import NO_MULTICAST, launched_ranks

    n, world = args.devices, launched_ranks()
    if n < 1:
        raise UserError(f"--devices must be positive, got {n}")
    if "TORCHELASTIC_RUN_ID" in os.environ or world > 1:
        if n != world:
            raise UserError(f"--devices {n} under torchrun with {world} processes: leave --devices out there")
        return False
    if n == 1:
        return False
    device = cfg.resolved(torch.cuda.is_available()).device
    if device.startswith("cuda") and n > torch.cuda.device_count():
        raise UserError(f"--devices {n} but this machine has {torch.cuda.device_count()} GPU(s)")
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import parse_args, run

    for name, value in NO_MULTICAST.items():
        os.environ.setdefault(name, value)
    try:
        run(parse_args(["--standalone", f"--nproc-per-node={n}", "--module", "mixer_nerf", *args.argv]))
    except ChildFailedError as e:
        rank, failure = e.get_first_failure()
        raise UserError(f"training process {rank} of {n} failed (exit code {failure.exitcode}); "
                        "its error is printed above and the others were stopped") from e
    return True


def _train(cfg: TrainConfig, resume: bool, overwrite: bool) -> dict[str, Any]:
    from .train import Trainer
    from .train.distributed import leave

    trainer = Trainer(cfg, resume=resume, overwrite=overwrite)
    c = trainer.cfg
    if not trainer.rank:
        print(f"training {c.steps} steps on {c.device} ({c.precision}, backend {c.backend}), preset {c.preset}, "
              f"{sampling_summary(c)} -> {trainer.files.root}")
    summary, rank = trainer.fit(), trainer.rank
    leave()  # every rank, before rank 0 evaluates alone
    # The trainer's GPU memory (CUDA graph pools among it) sits in reference cycles: freed for the evaluation.
    del trainer
    gc.collect()
    if rank:
        return summary
    print(f"training {summary['status']} at step {summary['step']} after {summary['train_seconds']:.1f} s")
    return summary


def sampling_summary(c: TrainConfig) -> str:
    """What a step of a resolved config shades, in words."""
    if c.sampler == "occupancy":
        return f"occupancy-grid sampling, ~{c.target_samples} samples per step"
    if c.sampler == "proposal":
        rounds = " + ".join(str(n) for n in c.proposal_rounds)
        return f"{c.batch_rays} rays x {c.proposal_samples} samples (proposal rounds {rounds})"
    return f"{c.batch_rays} rays x ({c.num_coarse} + {c.num_fine}) samples"


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
    parser.add_argument(
        "--config", metavar="FILE",
        help="settings from a run's config.json or a JSON/TOML table of them; typed flags override it",
    )  # fmt: skip
    add_options(parser, train_options())
    parser.add_argument("--out", help=f"run folder (default: {default_out})")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint "
                        "(a new --steps extends it; --device moves it; other settings must match)")
    parser.add_argument("--overwrite", action="store_true", help="delete the run in --out and start over")
    parser.add_argument("--eval-views", type=_eval_views, metavar="N|all|none",
                        help=f"held-out views scored after training (default: all on a GPU, {EVAL_VIEWS_CPU} on "
                        "a CPU; none: skip)")
    parser.add_argument("--devices", type=int, metavar="N",
                        help="train on N processes under torchrun: one per GPU, or CPU processes with "
                        "--device cpu (docs/distributed.md)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def eval_views(typed: int | str | None, device: str, builtin: bool = False) -> int | None:
    """The held-out views scored after training (None: all) for ``--eval-views`` as parsed (None:
    not given) on ``device``: all on a GPU or of the tiny built-in scene, else ``EVAL_VIEWS_CPU``."""
    if typed is None:
        return EVAL_VIEWS_CPU if device.startswith("cpu") and not builtin else None
    return None if typed == "all" else typed


def _eval_views(text: str) -> int | str:
    """``--eval-views``: a positive count, "all" or "none" (0)."""
    if text in ("all", "none"):
        return 0 if text == "none" else text
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a positive number of views, 'all' or 'none', got {text!r}")
    return int(text)


def _add_ablate_parser(commands: Any) -> None:
    ablate = commands.add_parser(
        "ablate", help="train presets x seeds for equal steps or equal time and tabulate held-out scores"
    )
    ablate.add_argument("--data", help="scene folder (default: the built-in procedural scene)")
    ablate.add_argument("--presets", help="presets to train, e.g. ABCD or A,D (default ABCD; --report: the ablation's)")
    ablate.add_argument("--seeds", help="seeds, comma-separated (default 0,1; --report: the ablation's)")
    ablate.add_argument(
        "--model-override", action="append", default=[], metavar="NAME=VALUE",
        help="a ModelConfig setting for every run, e.g. se_per_point=true (repeatable)",
    )
    ablate.add_argument("--target-psnr", type=float, metavar="DB",
                        help="tabulate the training time to this validation PSNR (default: the lowest "
                        "best validation PSNR among the runs)")
    ablate.add_argument("--split", choices=("test", "val", "train"), help="held-out views scored (as eval)")
    ablate.add_argument("--max-images", type=int, help="score only the first N held-out views")
    add_options(ablate, [flag for flag in train_options() if flag not in ("--preset", "--seed")])
    ablate.add_argument("--out", required=True, help="ablation folder: one run folder per preset and seed")
    ablate.add_argument("--resume", action="store_true",
                        help="continue the ablation in --out: skip finished runs, resume unfinished ones")
    ablate.add_argument("--no-progress", action="store_true", help="no progress bar")
    ablate.add_argument("--no-lpips", action="store_true",
                        help="score the runs without LPIPS (without it, ablate refuses to start where "
                        "LPIPS's weights are not installed)")
    ablate.add_argument("--gpus", metavar="LIST",
                        help="train the runs in one process per GPU, e.g. 0,1 (each sees only its GPU; "
                        "logs in --out/worker_gpu<N>.log), then write the table")
    ablate.add_argument("--report", action="store_true",
                        help="train and score nothing: write the table from the runs in --out as they are "
                        "(unfinished runs as rows without scores, runs not started left out), with the "
                        "settings the ablation was started with (no other flag needed)")
    ablate.add_argument("--runs", help=argparse.SUPPRESS)  # a --gpus worker's share: PRESET:SEED,...


def _add_device_options(parser: argparse.ArgumentParser) -> None:
    add_options(parser, DEVICE_FLAGS)


def _camera_path_arg(value: str) -> str:
    if value in VIDEO_PATHS or value.endswith(".json"):
        return value
    raise argparse.ArgumentTypeError(f"expected one of {', '.join(VIDEO_PATHS)} or a .json camera-path file, "
                                     f"got {value!r}")


def _is_user_error(e: Exception) -> bool:
    from .data import DatasetError
    from .export import ExportError
    from .train import CheckpointError, NonFiniteError, OutputError
    from .train.distributed import DistributedError

    if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
        return True  # disk full, quota, read-only: the user frees space or picks another --out
    return isinstance(
        e,
        (
            UserError,
            DatasetError,
            ExportError,
            CheckpointError,
            NonFiniteError,
            OutputError,
            DistributedError,
            FileNotFoundError,
            PermissionError,
            ValueError,
        ),
    )
