"""Validation PSNR against training wall-clock time, one method per call (each call < 10 min).

    python -m benchmarks.time_to_quality --method nerfacc --data .data/lego_400 \
        --checkpoints 30,60,120,240 --label nerfacc

Methods:
  nerfacc   nerfacc 0.5.3's vanilla-MLP recipe through its public API (OccGridEstimator 128^3
            updated every 16 steps, render step sqrt(3)*3/1024, 65536 samples per step with a
            dynamic ray batch, smooth-L1 loss, Adam 5e-4 with step decay) around our preset-A MLP.
  nerfacc-proposal
            nerfacc 0.5.3's PropNetEstimator (its sampling, interval loss, update schedule and
            rendering) around our trainer's proposal-sampler run: the same main MLP, proposal
            networks, rays, optimizer settings and learning-rate schedule; only the estimator differs.
  ours      our trainer (``mixer_nerf.train``), any preset, every skip switchable.
The clock counts training only: it stops for validation, and JIT builds (nerfacc's and ours) and
data loading happen before it starts. Validation renders every view of the val split, and
``--train-views`` training views spread over the split (``train_psnr``: how far a run fits what it
sees beyond what it shows on held-out views).
Writes the run into ``<out>/<scene>_<device>.json`` (default
``benchmarks/results/time_to_quality/lego_h100.json`` for Lego on an H100), a list of runs in which it
replaces the run of its label or comes last, after every checkpoint (a run cut short keeps its
points); ``benchmarks.plot_time_to_quality`` plots and tabulates that file.
A curve longer than one call: ``--run-dir DIR`` (ours, nerfacc-proposal) keeps the run's state in
DIR, saved every ``--save-every`` training seconds and at each checkpoint; the same command again
resumes it there (same batches, the training clock going on). ``--stop-after S`` ends a call after S
seconds of training, saved, before a device call's limit would kill it; ``--stop-after +S`` after S
more than the run had when this call resumed it.
Ours and nerfacc-proposal end at the trainer's ``--steps`` (as ``mixer-nerf train``) if that comes first: the
last point is marked ``finished``, its final model standing for the checkpoints after it.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

from benchmarks.harness import RESULTS, device_tag, scene_tag
from benchmarks.skip_report import skip_report
from benchmarks.validation import validate
from mixer_nerf.ablation import parse_model_overrides
from mixer_nerf.cli_options import add_options
from mixer_nerf.data import detect_format, load_split
from mixer_nerf.render.skipping import JITTERS
from mixer_nerf.train.output import write_text_atomic
from mixer_nerf.train.trainer import TrainingClock

NERFACC_RECIPE_STEPS = 50_000  # nerfacc's occupancy recipe: its MultiStepLR milestones are fractions of it


@dataclass
class Method:
    """A method's training step, validation render, trainer (ours-based methods) and, for a run
    kept in ``--run-dir``, how to save and restore the state the trainer's checkpoint lacks."""

    step_fn: Callable[[int], dict | Callable[[], dict]]  # stats, or how to read them at a checkpoint
    render: Callable
    trainer: object = None
    save_extra: Callable[[Path], None] | None = None
    load_extra: Callable[[Path, int], None] | None = None


def run_curve(step_fn: Callable[[int], dict | Callable[[], dict]], render: Callable, val,
              checkpoints: list[float], log: Callable, clock: TrainingClock,
              start: tuple[int, int] | None = None, save: Callable[[int], None] | None = None,
              save_every: float = math.inf, stop_after: float = math.inf,
              train: tuple[object, list[int]] | None = None,
              finished: Callable[[], bool] | None = None) -> int:
    """Train with ``step_fn(step)`` until the last checkpoint, validating at each one (``clock``
    pauses meanwhile; ``train``: a training split and the views of it scored as well) and logging
    the stats of the step before it (``step_fn``'s dict, or what the callable it returned reads
    then). Step 0 runs before the clock starts: it builds any JIT kernels (nerfacc's, ours) and
    warms up caches. ``start``: (step, checkpoints done) of a resumed run, which warms up by
    rendering one val view instead (no training state moves; nerfacc's kernels load there).
    ``save(step)`` runs, clock paused, every ``save_every`` training seconds, at each checkpoint and
    before a stop after ``stop_after`` seconds. ``finished()``, asked after every step (so no device
    sync in it), ends the run once True: one last point, ``"finished": True``, stands for every
    checkpoint left. Returns the checkpoints reached (all of them once finished)."""
    step, done = (1, 0) if start is None else start
    pending = sorted(checkpoints)[done:]
    if not pending:  # a complete (or finished) run resumed: nothing to train
        return done
    warm_up = time.perf_counter()
    if start is None:
        step_fn(0)
    else:
        validate(render, val, views=[0])
    print(f"warm-up {time.perf_counter() - warm_up:.1f} s, outside the clock", flush=True)
    next_save = clock.elapsed + save_every
    clock.start()
    while pending:
        stats = step_fn(step)
        step += 1
        # asked every step, not every 16th: the run stops at the trainer's step count exactly, as it does
        end = finished is not None and finished()
        if step % 16 and not end:
            continue
        now = clock.now()
        if end or now >= pending[0]:
            elapsed = clock.pause()
            point = {"seconds": round(elapsed, 2), "step": step, "val_psnr": validate(render, val)}
            if train is not None:
                point["train_psnr"] = validate(render, train[0], views=train[1])
            point.update(stats() if callable(stats) else stats)
            if end:
                point["finished"] = True
                done += len(pending)
                pending.clear()
            else:
                pending.pop(0)
                done += 1
            log(point)
        elif now >= min(next_save, stop_after):
            clock.pause()
        else:
            continue
        if save is not None:
            save(step)
            next_save = clock.elapsed + save_every
        if clock.elapsed >= stop_after:
            break
        if pending:
            clock.start()
    return done


def nerfacc_method(args, train, val, device) -> Method:
    import nerfacc

    from mixer_nerf.model import MixerNeRF, preset_config

    aabb = torch.tensor([-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], device=device)
    step_size = (aabb[3:] - aabb[:3]).max().item() * math.sqrt(3) / 1024
    estimator = nerfacc.OccGridEstimator(roi_aabb=aabb, resolution=128, levels=1).to(device)
    field = MixerNeRF(preset_config("A")).to(device)
    # Our MLP starts from one uniform density everywhere; nerfacc's grid keeps cells whose opacity
    # exceeds the grid mean, so a uniform field would leave every cell empty and never train. Give
    # the peer a random density row, as nerfacc's own MLP has.
    torch.nn.init.xavier_uniform_(field.head.weight[:1])
    optimizer = torch.optim.Adam(field.parameters(), lr=5e-4, eps=1e-15)
    steps = args.nominal_steps or NERFACC_RECIPE_STEPS
    scheduler = torch.optim.lr_scheduler.MultiStepLR(
        optimizer, milestones=[steps // 2, steps * 3 // 4, steps * 5 // 6, steps * 9 // 10], gamma=0.33)
    rays_o_all, rays_d_all, rgb_all = (t.to(device) for t in train.all_rays())
    target_samples, state = 1 << 16, {"num_rays": 1024}
    white = torch.ones(3, device=device)

    def fields(rays_o, rays_d):
        def sigma_fn(t_starts, t_ends, ray_indices):
            x = rays_o[ray_indices] + rays_d[ray_indices] * ((t_starts + t_ends) / 2)[:, None]
            return field(x, F.normalize(rays_d[ray_indices], dim=-1))[0]

        def rgb_sigma_fn(t_starts, t_ends, ray_indices):
            x = rays_o[ray_indices] + rays_d[ray_indices] * ((t_starts + t_ends) / 2)[:, None]
            sigma, rgb = field(x, F.normalize(rays_d[ray_indices], dim=-1))
            return rgb, sigma

        return sigma_fn, rgb_sigma_fn

    def render(rays_o, rays_d, background=white, stratified=False):
        sigma_fn, rgb_sigma_fn = fields(rays_o, rays_d)
        ray_indices, t_starts, t_ends = estimator.sampling(
            rays_o, rays_d, sigma_fn=sigma_fn, render_step_size=step_size, stratified=stratified)
        rgb, opacity, _, _ = nerfacc.rendering(
            t_starts, t_ends, ray_indices, n_rays=len(rays_o), rgb_sigma_fn=rgb_sigma_fn, render_bkgd=background)
        return rgb, opacity, len(t_starts)

    def step_fn(step: int) -> dict:
        field.train()
        estimator.train()
        estimator.update_every_n_steps(
            step=step, occ_eval_fn=lambda x: field.density(x)[:, None] * step_size, occ_thre=1e-2)
        idx = torch.randint(0, len(rays_o_all), (state["num_rays"],), device=device)
        # Our loader composites on white (no alpha kept), so both methods train on white.
        target = rgb_all[idx]
        rgb, opacity, n_samples = render(rays_o_all[idx], rays_d_all[idx], white, stratified=True)
        if n_samples == 0:
            return {}
        state["num_rays"] = min(int(state["num_rays"] * target_samples / n_samples), 1 << 16)
        alive = opacity.squeeze(-1) > 0
        loss = F.smooth_l1_loss(rgb[alive], target[alive])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        scheduler.step()
        return {"samples_per_step": n_samples, "samples_per_ray": n_samples / len(idx), "rays": len(idx)}

    def render_val(rays_o, rays_d):
        field.eval()
        estimator.eval()
        return render(rays_o, rays_d)[0]

    return Method(step_fn, render_val)


def nerfacc_proposal_method(args, train, val, device) -> Method:
    import nerfacc
    from nerfacc.estimators.prop_net import get_proposal_requires_grad_fn

    from mixer_nerf.render.volume import query_field

    args.sampler = "proposal"
    # only ours' fields, sampler and schedule are used: nothing to replay
    trainer = ours_method(argparse.Namespace(**{**vars(args), "cuda_graphs": False}), train, val, device).trainer
    cfg, fields = trainer.cfg, trainer.fields
    networks = list(fields.proposal.networks)
    proposal_params = [p for net in networks for p in net.parameters()]
    main_params = [p for p in fields.parameters() if all(p is not q for q in proposal_params)]
    optimizer = torch.optim.Adam(main_params, lr=cfg.lr, eps=cfg.adam_eps)
    estimator = nerfacc.PropNetEstimator(torch.optim.Adam(proposal_params, lr=cfg.lr, eps=cfg.adam_eps)).to(device)
    near, far = trainer.train_scene.near, trainer.train_scene.far
    # nerfacc's "uniform" is our linear spacing (bounded and NDC scenes), "lindisp" our disparity.
    spacing = "uniform" if fields.proposal.options.spacing == "linear" else "lindisp"
    requires_grad_at = get_proposal_requires_grad_fn()

    def render(rays_o, rays_d, stratified=False, requires_grad=False):
        norm = torch.linalg.vector_norm(rays_d, dim=-1, keepdim=True)

        def density_fn(net):
            def sigma_fn(t_starts, t_ends):
                mids = 0.5 * (t_starts + t_ends)
                return net.density(rays_o[:, None, :] + mids[..., None] * rays_d[:, None, :]).float() * norm
            return sigma_fn

        def rgb_sigma_fn(t_starts, t_ends, ray_indices):
            sigma, rgb = query_field(trainer.coarse_field, rays_o, rays_d, 0.5 * (t_starts + t_ends))
            return rgb, sigma

        t_starts, t_ends = estimator.sampling(
            [density_fn(net) for net in networks], list(cfg.proposal_rounds), cfg.proposal_samples,
            n_rays=len(rays_o), near_plane=near, far_plane=far, sampling_type=spacing,
            stratified=stratified, requires_grad=requires_grad)
        rgb, _, _, extras = nerfacc.rendering(t_starts, t_ends, rgb_sigma_fn=rgb_sigma_fn,
                                              render_bkgd=trainer.background)
        return rgb, extras["trans"], t_starts.numel()

    def step_fn(step: int) -> dict:
        fields.train()
        lr = trainer.learning_rate()
        for group in (*optimizer.param_groups, *estimator.optimizer.param_groups):
            group["lr"] = lr
        rays_o, rays_d, target = trainer.sampler.sample()
        requires_grad = requires_grad_at(step)
        rgb, trans, n_samples = render(rays_o, rays_d, stratified=True, requires_grad=requires_grad)
        loss = F.mse_loss(rgb, target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        estimator.update_every_n_steps(trans, requires_grad, loss_scaler=1.0)
        trainer.step += 1  # drives the shared learning-rate schedule
        return {"samples_per_step": n_samples, "samples_per_ray": n_samples / len(rays_o), "rays": len(rays_o),
                "lr": lr}

    def render_val(rays_o, rays_d):
        fields.eval()
        with torch.no_grad():
            return render(rays_o, rays_d)[0]

    def save_extra(run_dir: Path) -> None:  # the trainer's checkpoint holds the fields, not these
        partial = run_dir / "nerfacc_state.pt.partial"
        torch.save({"optimizer": optimizer.state_dict(), "estimator": estimator.optimizer.state_dict()}, partial)
        partial.replace(run_dir / "nerfacc_state.pt")

    def load_extra(run_dir: Path, step: int) -> None:
        state = torch.load(run_dir / "nerfacc_state.pt", map_location=device)
        optimizer.load_state_dict(state["optimizer"])
        estimator.optimizer.load_state_dict(state["estimator"])
        for past in range(step):  # nerfacc's schedule keeps its count in a closure: replay it
            requires_grad_at(past)

    return Method(step_fn, render_val, trainer, save_extra, load_extra)


TRAINER_OPTIONS = (
    "target_samples", "batch_rays", "precision", "lr", "lr_final", "lr_warmup", "lr_hold", "bf16_density_passes",
    "adam_eps", "early_stop_eps", "empty_space_weight", "grid_warmup", "grid_every", "grid_threshold", "step_size",
    "proposal_width", "proposal_samples", "proposal_loss_weight", "proposal_update_every", "proposal_jitter",
    "proposal_weight_padding", "val_holdout", "grad_clip", "distortion_weight", "proposal_residual",
    "proposal_intervals", "cuda_graphs", "frequency_anneal", "density_noise", "mlca_weight_decay", "occlusion_weight",
    "occlusion_fraction")
"""Options of ours passed to TrainConfig only when given: unset, they keep the trainer's defaults."""


def ours_method(args, train, val, device) -> Method:
    import tempfile

    from mixer_nerf.train import TrainConfig, Trainer

    cfg = TrainConfig(
        data=args.data, preset=args.preset, sampler=args.sampler,
        device=str(device), seed=args.seed, val_every=10**9, ckpt_every=10**9, log_every=10**9,
        # as `mixer-nerf train --time-budget`: the run and its schedule end at the last checkpoint or
        # at the trainer's --steps (or --nominal-steps), whichever comes first
        **({"steps": args.nominal_steps} if args.nominal_steps else {}),
        time_budget=max(float(c) for c in args.checkpoints.split(",")),
        progress=False, out=args.run_dir or tempfile.mkdtemp(prefix="ttq_"), backend=args.backend,
        model_overrides=parse_model_overrides(args.model_override),
        # the options left unset keep the trainer's defaults
        **{k: getattr(args, k) for k in TRAINER_OPTIONS if getattr(args, k) is not None})
    resume = args.run_dir is not None and (Path(args.run_dir) / "checkpoint.pt").is_file()
    trainer = Trainer(cfg, resume=resume, overwrite=args.run_dir is not None and not resume, log=lambda _: None)

    last = {"step": trainer.step, "rays": trainer.rays_seen, "samples": trainer.samples_seen}

    def stats() -> dict:
        """Per-step averages since the last checkpoint: read only there, as replayed steps count
        their samples on the device."""
        steps = max(trainer.step - last["step"], 1)
        rays, samples = trainer.rays_seen, trainer.samples_seen
        point = {"samples_per_ray": samples / max(rays, 1), "samples_per_step": (samples - last["samples"]) / steps,
                 "rays": (rays - last["rays"]) / steps, "marched_per_ray": trainer.marched_seen / max(rays, 1),
                 "lr": float(trainer.optimizer.param_groups[0]["lr"])}
        last.update(step=trainer.step, rays=rays, samples=samples)
        return point

    def step_fn(step: int) -> Callable[[], dict]:
        trainer.fields.train()
        trainer.train_step()
        return stats

    return Method(step_fn, trainer.render_rgb, trainer)


METHODS = {"nerfacc": nerfacc_method, "nerfacc-proposal": nerfacc_proposal_method, "ours": ours_method}


def save_runs(path: Path, records: list[dict]) -> None:
    """Write each of ``records`` into the list of runs in ``path``: in place of the run of its
    label, else last."""
    runs = json.loads(path.read_text()) if path.exists() else []
    for record in records:
        labels = [run["label"] for run in runs]
        if record["label"] in labels:
            runs[labels.index(record["label"])] = record
        else:
            runs.append(record)
    path.write_text(json.dumps(runs, indent=1))


def _stop_after(text: str) -> tuple[float, bool]:
    """``--stop-after``: (seconds, whether they count from where the run resumes)."""
    try:
        seconds = float(text.removeprefix("+"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected S or +S (seconds), got {text!r}") from None
    if not seconds > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, got {text!r}")
    return seconds, text.startswith("+")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", choices=sorted(METHODS), required=True)
    parser.add_argument("--label", default=None)
    parser.add_argument("--data", default=".data/lego_400")
    parser.add_argument("--checkpoints", default="30,60,120,240")
    parser.add_argument("--nominal-steps", type=int, default=None,
                        help=f"schedule length in steps (default: nerfacc's occupancy recipe "
                             f"{NERFACC_RECIPE_STEPS}; ours and nerfacc-proposal: the trainer's --steps, the "
                             "run and its schedule ending there or at the last checkpoint, whichever comes "
                             "first)")
    parser.add_argument("--out", default=str(RESULTS / "time_to_quality"))
    parser.add_argument("--record-from", default=None, metavar="DIR",
                        help="where --out has no file for this scene and device yet, start it from DIR's "
                             "(the record's runs, this run's label replaced in it): only that file is copied")
    parser.add_argument("--scene", default=None,
                        help="scene name in the result file's name (default: the --data folder's name up to "
                             "its first '_', e.g. lego for .data/lego_400)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train-views", type=int, default=3,
                        help="training views (spread over the split) scored at each checkpoint too, as "
                             "train_psnr (0: none)")
    parser.add_argument("--device", default="cuda", help="cuda, or cpu for a smoke run")
    parser.add_argument("--preset", default="D", help="ours: model preset")
    parser.add_argument("--sampler", default="auto",
                        help="ours: auto (as `mixer-nerf train` picks per scene) | occupancy | proposal | "
                             "hierarchical")
    parser.add_argument("--target-samples", type=int, help="ours: MLP samples per step (default: the trainer's)")
    parser.add_argument("--batch-rays", type=int, default=None,
                        help="ours, hierarchical and proposal samplers: rays per step (default: the trainer's)")
    parser.add_argument("--precision",
                        help="ours: bf16 | tf32 | fp32 (default: the trainer's, the sampler's recipe on CUDA)")
    parser.add_argument("--lr", type=float, default=None, help="ours: learning rate (default: the sampler's recipe)")
    parser.add_argument("--lr-final", type=float, default=None,
                        help="ours: learning rate at the last checkpoint (the trainer's time budget) "
                             "or --nominal-steps, whichever comes first (exponential decay; default: the recipe)")
    parser.add_argument("--lr-hold", type=float, default=None,
                        help="ours: fraction of the run at --lr before the decay starts (default: the recipe)")
    parser.add_argument("--lr-warmup", type=int, default=None,
                        help="ours: steps of linear lr warm-up (default: the sampler's recipe)")
    parser.add_argument("--bf16-density-passes", action=argparse.BooleanOptionalAction, default=None,
                        help="ours, occupancy sampler: grid refreshes and the early-termination pre-pass in bf16 "
                             "(default: the trainer's, on CUDA)")
    parser.add_argument("--proposal-width", type=int, help="ours, proposal sampler: proposal networks' width")
    parser.add_argument("--proposal-samples", type=int, help="ours, proposal sampler: main-field samples per ray")
    parser.add_argument("--proposal-update-every", type=int,
                        help="ours, proposal sampler: train the proposal networks every N steps past step 1000")
    parser.add_argument("--proposal-jitter", choices=JITTERS,
                        help="ours, proposal sampler: stratified jitter per sample or one offset per ray")
    parser.add_argument("--proposal-weight-padding", type=float,
                        help="ours, proposal sampler: added to each proposal weight before resampling")
    # as `mixer-nerf train` has them (help and types from TrainConfig); unset, the trainer's defaults
    add_options(parser, ("--distortion-weight", "--adam-eps", "--val-holdout", "--grad-clip", "--proposal-residual",
                         "--proposal-intervals", "--proposal-loss-weight", "--cuda-graphs", "--frequency-anneal",
                         "--density-noise", "--mlca-weight-decay", "--occlusion-weight", "--occlusion-fraction"))
    parser.add_argument("--early-stop-eps", type=float,
                        help="ours, occupancy sampler: early ray termination (0: off; default: the trainer's)")
    parser.add_argument("--empty-space-weight", type=float,
                        help="ours, occupancy sampler: weight of the empty-space density loss (0: off; "
                             "default: the trainer's)")
    parser.add_argument("--grid-warmup", type=int,
                        help="ours, occupancy sampler: steps of a fully occupied grid (a huge value: "
                             "no empty-space skipping, box clipping only; default: the trainer's)")
    parser.add_argument("--grid-every", type=int, default=None,
                        help="ours, occupancy sampler: refresh the grid every N steps (default: the trainer's)")
    parser.add_argument("--grid-threshold", type=float, default=None,
                        help="ours, occupancy sampler: opacity of one marching step above which a cell is "
                             "occupied (default: the trainer's)")
    parser.add_argument("--step-size", type=float, default=None,
                        help="ours, occupancy sampler: marching step (default: the box diagonal / 1000)")
    parser.add_argument("--backend", default="auto", help="ours: auto | kernel | torch (the pure-PyTorch path)")
    parser.add_argument("--skip-report", action="store_true",
                        help="ours, occupancy sampler: after training, time one val render under each skip")
    parser.add_argument("--model-override", action="append", default=[], metavar="NAME=VALUE",
                        help="ours: a ModelConfig setting, e.g. se_per_point=true (repeatable)")
    parser.add_argument("--run-dir", help="ours, nerfacc-proposal: keep the run's state here and resume it "
                        "from there (a curve longer than one call)")
    parser.add_argument("--save-every", type=float, default=60.0,
                        help="with --run-dir: training seconds between saves (default 60)")
    parser.add_argument("--stop-after", type=_stop_after, default=(math.inf, False), metavar="S|+S",
                        help="with --run-dir: end this call after S seconds of training (+S: S more than "
                             "the run had when this call resumed it), saved")
    args = parser.parse_args()
    if args.skip_report and (args.method != "ours" or args.sampler not in ("auto", "occupancy")):
        parser.error("--skip-report needs --method ours and the occupancy sampler")
    if args.run_dir is not None and args.method == "nerfacc":
        parser.error("--run-dir needs --method ours or nerfacc-proposal")
    if args.grad_clip is not None and args.method != "ours":
        parser.error("--grad-clip needs --method ours (nerfacc's estimator steps its own optimizer)")
    if args.stop_after[0] != math.inf and args.run_dir is None:
        parser.error("--stop-after needs --run-dir (a stopped run is resumed from there)")

    torch.manual_seed(args.seed)
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True
    device = torch.device(args.device)
    # as the trainer loads them: a val split held out of a capture's training views is refused for Blender
    fmt, holdout = detect_format(args.data), args.val_holdout or 0
    train = load_split(args.data, fmt, "train", val_holdout=holdout).to(device)
    val = load_split(args.data, fmt, "val", val_holdout=holdout).to(device)
    checkpoints = [float(c) for c in args.checkpoints.split(",")]
    label = args.label or args.method

    method = METHODS[args.method](args, train, val, device)
    trainer = method.trainer
    if args.skip_report and trainer.cfg.sampler != "occupancy":
        parser.error(f"--skip-report needs the occupancy sampler; 'auto' picked {trainer.cfg.sampler!r} "
                     "for this scene")

    scene = args.scene or scene_tag(args.data)
    path = Path(args.out) / f"{scene}_{device_tag(device)}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    record_file = None if args.record_from is None else Path(args.record_from) / path.name
    if record_file is not None and record_file.is_file() and not path.exists():
        path.write_text(record_file.read_text())
    record = {"label": label, "method": args.method, "data": args.data, "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
              "val_views": len(val), "curve": []}

    def log(point: dict) -> None:  # the file after every checkpoint: a run cut short keeps its points
        print(label, json.dumps(point), flush=True)
        record["curve"].append(point)
        save_runs(path, [record])

    start, save = None, None
    if args.run_dir is not None:
        run_dir = Path(args.run_dir)
        state_path = run_dir / "ttq_state.json"
        if (run_dir / "checkpoint.pt").is_file():
            state = json.loads(state_path.read_text())
            if state["trainer_step"] != trainer.step:
                raise SystemExit(f"{run_dir}: its checkpoint (step {trainer.step}) and {state_path.name} "
                                 f"(step {state['trainer_step']}) disagree: the run was killed while saving")
            record["curve"] = state["curve"]
            # a finished run's last point stands for every checkpoint: it trains no further
            finished_run = bool(state["curve"]) and state["curve"][-1].get("finished", False)
            start = (state["step"], len(checkpoints) if finished_run else len(state["curve"]))
            if method.load_extra is not None:
                method.load_extra(run_dir, trainer.step)
            print(label, f"resumed at {trainer.clock.elapsed:.1f} s of training", flush=True)

        def save(step: int) -> None:
            if method.save_extra is not None:
                method.save_extra(run_dir)
            trainer.save()
            write_text_atomic(state_path, json.dumps({"step": step, "trainer_step": trainer.step,
                                                      "curve": record["curve"]}))

    clock = trainer.clock if trainer is not None else TrainingClock(device)
    stop_after, relative = args.stop_after
    if relative:
        stop_after += clock.elapsed
    views = torch.linspace(0, len(train) - 1, min(args.train_views, len(train))).round().long().tolist()
    # as `mixer-nerf train`: a run on our trainer's schedule stops at its --steps (nerfacc's recipe has no trainer)
    finished = None if trainer is None else (lambda: trainer.step >= trainer.cfg.steps)
    done = run_curve(method.step_fn, method.render, val, checkpoints, log=log, clock=clock, start=start, save=save,
                     save_every=args.save_every if save else math.inf, stop_after=stop_after,
                     train=(train, views) if views else None, finished=finished)
    if done < len(checkpoints):
        print(label, f"stopped at {clock.elapsed:.1f} s of training; the same command resumes it", flush=True)
    elif args.skip_report:
        record["skip_report"] = skip_report(trainer, val)
        print(label, json.dumps(record["skip_report"]), flush=True)
        save_runs(path, [record])


if __name__ == "__main__":
    main()
