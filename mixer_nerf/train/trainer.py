"""The training loop: random ray batches, coarse + fine MSE, Adam with a held then decaying rate,
periodic validation, atomic checkpoints, logs, a non-finite guard and a wall-clock budget."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F

from ..data import load_split
from ..metrics import psnr
from ..model.mlca import MLCA
from ..ops import use_kernel
from ..render import render_rays
from ..render.skipping import (
    distortion_loss,
    occlusion_loss,
    proposal_loss,
    proposal_update_due,
    render_rays_proposal,
    shade_samples,
)
from .checkpoint import capture_rng_state, load_checkpoint, restore_rng_state, save_checkpoint
from .config import TrainConfig
from .distributed import join, rank_seed, restore_rank_sampler
from .fixed_batch import FixedBatches, FixedCapacity
from .fields import model_config, model_config_to_dict, model_notes
from .graphed_steps import GraphedSteps
from .guard import NonFiniteError, NonFiniteGuard
from .logbook import CsvLog, TensorBoardLog, plot_curves
from .loss_spikes import LossSpikeWatch, SpikeRollback
from .marched_batches import MarchedBatches
from .memory import FLOAT_BYTES, check_fits
from .occupancy_batch import MarchedBatch, prepare_marched_batch
from .output import RunFiles, prepare_run_folder, write_text_atomic
from .precision import set_matmul_precision
from .sampler import RaySampler
from .sampling import image_renderer, make_fields, occupancy_sampler, recipe_notes, resolve_sampler
from .scenes import held_out_split, locate_scene, scene_info, scene_source

RESUMABLE_OVERRIDES = ("steps", "time_budget", "device", "backend", "data", "render_samples", "ckpt_every",
                       "log_every", "cuda_graphs", "spike_rollbacks", "progress")
"""Settings a resumed run may change: how long it trains (a longer ``steps`` stretches the
learning-rate schedule to the new end), where it runs, where its scene now is, how much a
render may hold at once, how often it saves and logs, and how often it may roll back a spike. Any other
setting that differs from the checkpoint is refused by name: the run continues as it began."""
CAPACITY_CHECK_EVERY = 100
"""Steps between checks of whether fixed-capacity batches outgrew their buffers (a host sync each)."""
DEVICE_SETTINGS = ("precision", "bf16_density_passes", "val_images")
"""Picked anew for the machine when a resumed run moves to another device type (unless typed)."""
REPICKED_SETTINGS = ("cuda_graphs",)
"""Picked anew at every resume (unless typed): how a step runs, not what it learns."""


def typed_overrides(cfg: TrainConfig) -> dict[str, Any]:
    """The settings of ``cfg`` (its ``out`` aside) that differ from the defaults: what a resumed
    run was told anew (an option left out keeps the checkpoint's value, its time budget included)."""
    default = TrainConfig()
    return {k: v for k, v in cfg.to_dict().items() if k != "out" and not _same(v, getattr(default, k))}


def resume_config(saved: TrainConfig, cfg: TrainConfig, ckpt: Any, step: int) -> TrainConfig:
    """The settings a resumed run continues with: the checkpoint's, with the ``RESUMABLE_OVERRIDES``
    ``cfg`` gives and its ``out``. ``data`` is left for :func:`locate_scene` to check.

    Raises:
        ValueError: naming each other setting of ``cfg`` that differs from the checkpoint's, or
            a ``steps`` short of the checkpoint's ``step``.
    """
    told = typed_overrides(cfg)
    if told.get("steps", step) < step:
        raise ValueError(f"{ckpt}: --steps {told['steps']} is short of the checkpoint's step {step}")
    moved = "device" in told and told["device"].split(":")[0] != (saved.device or "").split(":")[0]
    free = RESUMABLE_OVERRIDES + (DEVICE_SETTINGS if moved else ())
    refused = [f"{k} (checkpoint {getattr(saved, k)!r}, given {v!r})" for k, v in told.items()
               if k not in free and not _same(v, getattr(saved, k))]
    if refused:
        raise ValueError(f"{ckpt}: --resume continues the checkpoint's settings, but {', '.join(refused)} "
                         f"differ; only {', '.join(RESUMABLE_OVERRIDES[:-1])} may change (use another --out "
                         "for a new run)")
    if not moved and (saved.device or "").startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"{ckpt}: trained on {saved.device}, and torch sees no CUDA GPU here; "
                         "pass --device cpu to resume it on this machine")
    fresh = {k: told.get(k) for k in REPICKED_SETTINGS + (DEVICE_SETTINGS if moved else ())}
    kept = {k: v for k, v in told.items() if k in RESUMABLE_OVERRIDES and k != "data"}
    return TrainConfig(**{**saved.to_dict(), **fresh, **kept, "out": cfg.out})


def check_sizes(cfg: TrainConfig, width: int, device: torch.device) -> None:
    """Refuse a batch or grid of a resolved ``cfg`` that cannot fit: a step holds at least one
    activation and its gradient of ``width`` floats per sample, the grid a float per cell."""
    per_ray = 2 * cfg.num_coarse + cfg.num_fine if cfg.sampler == "hierarchical" else 1
    check_fits(f"--batch-rays {cfg.batch_rays}", cfg.batch_rays * per_ray * width * 2 * FLOAT_BYTES, device)
    if cfg.sampler == "occupancy":
        check_fits(f"--grid-resolution {cfg.grid_resolution}", cfg.grid_resolution**3 * FLOAT_BYTES, device)


def _same(a: Any, b: Any) -> bool:
    """Equal settings, a tuple equal to the list it became in a file."""
    return json.dumps(a, sort_keys=True, default=str) == json.dumps(b, sort_keys=True, default=str)


def _why_not_graphable(cfg: TrainConfig, device: torch.device, several_processes: bool,
                       images: torch.device) -> str | None:
    """Why a step of this run cannot be replayed as a CUDA graph; None if it can."""
    if device.type != "cuda":
        return "it needs a CUDA device"
    if cfg.sampler not in ("proposal", "occupancy"):
        return f"only the proposal and occupancy samplers' steps can keep their shapes (this run's sampler: {cfg.sampler})"
    if several_processes:
        return "not with several processes"
    if images.type != "cuda":
        return "the training images do not fit on the GPU (a step would copy its pixels from the host)"
    return None


def replays_steps(cfg: TrainConfig, device: torch.device, several_processes: bool,
                  images: torch.device) -> tuple[bool, str | None]:
    """``cfg.cuda_graphs`` decided, and why a step cannot be replayed (None if it can): None is on
    wherever a step can be replayed; True where one cannot is refused, saying why."""
    why = _why_not_graphable(cfg, device, several_processes, images)
    if cfg.cuda_graphs and why:
        raise ValueError(f"--cuda-graphs: {why}")
    return (why is None if cfg.cuda_graphs is None else cfg.cuda_graphs), why


class TrainingClock:
    """Seconds spent training (validation and checkpointing excluded), across resumes."""

    def __init__(self, device: torch.device, elapsed: float = 0.0) -> None:
        self.device, self.elapsed, self._start = device, elapsed, None

    def start(self) -> None:
        self._sync()
        self._start = time.perf_counter()

    def pause(self) -> float:
        self._sync()
        if self._start is not None:
            self.elapsed += time.perf_counter() - self._start
            self._start = None
        return self.elapsed

    def now(self) -> float:
        """Host-side reading (no synchronisation): the GPU may lag it by the queued work."""
        return self.elapsed + (time.perf_counter() - self._start if self._start is not None else 0.0)

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)


def _seen_counter(index: int, doc: str) -> property:
    def get(self) -> int:
        return self._settled_counts()[index]

    def set(self, value: int) -> None:
        self._settled_counts()[index] = value

    return property(get, set, doc=doc)


class Trainer:
    """One training run in ``cfg.out``.

    Args:
        cfg: the run's settings. With ``resume=True`` they are read from the checkpoint in
            ``cfg.out`` instead, except those in ``RESUMABLE_OVERRIDES`` (see :func:`resume_config`).
        resume: continue from ``cfg.out/checkpoint.pt`` bit-for-bit (same batches, same samples;
            on another device type, new random batches).
        log: where one-line messages go (``print`` by default).
        overwrite: remove an earlier run's files from ``cfg.out`` and start over.

    The run folder is locked (``run.lock``) from here until :meth:`fit` returns or raises.

    Raises:
        OutputError, CheckpointError, DatasetError (and MissingFileError): naming the file;
        ValueError: a resumed run was given settings it cannot change.
    """

    def __init__(
        self, cfg: TrainConfig, resume: bool = False, log: Callable[[str], None] = print, overwrite: bool = False
    ) -> None:
        self.log = log
        owner = int(os.environ.get("RANK", "0")) == 0  # under torchrun rank 0 holds the folder for all
        self.files, self.lock = prepare_run_folder(cfg.out, resume, overwrite) if owner else (RunFiles(Path(cfg.out)), None)
        try:
            self._start(cfg, resume)
        except BaseException:
            self._release_folder()  # a run that could not start leaves the folder to the next one
            raise

    def _start(self, cfg: TrainConfig, resume: bool) -> None:
        """Everything else ``__init__`` does, once the folder is ours."""
        state = None
        if resume:
            state = load_checkpoint(self.files.checkpoint)
            data = cfg.data
            saved = TrainConfig.from_dict(state["train_config"])
            cfg = resume_config(saved, cfg, self.files.checkpoint, int(state["step"]))
            folder, fmt = locate_scene(cfg, state["scene"], data, self.files.checkpoint)
        else:
            folder, fmt = scene_source(cfg)
        if cfg.data is not None:  # the checkpoint names the scene wherever it is read from
            cfg = dataclasses.replace(cfg, data=str(folder.resolve()))
        self.cfg = cfg = cfg.resolved(torch.cuda.is_available())
        self.ranks = join(cfg.device)  # None: one process (no torchrun)
        self.rank = 0 if self.ranks is None else self.ranks.rank
        self._shared_time = (-1, 0.0)  # (step, rank 0's clock then)
        if self.rank:
            self.log = lambda _: None  # rank 0 speaks and writes for all
        self.device = torch.device(cfg.device)
        tensorboard = cfg.tensorboard and not self.rank  # rank 0 writes for all
        self.tensorboard = TensorBoardLog(self.files.root / "tensorboard") if tensorboard else None

        self.train_scene = load_split(folder, fmt, "train", cfg.downscale, cfg.val_holdout).to(self.device)
        val_scene, self.val_split = held_out_split(folder, fmt, "val", cfg.downscale, cfg.val_holdout)
        self.val_scene = val_scene.to(self.device)
        self.cfg = cfg = resolve_sampler(cfg, self.train_scene.bbox, self.train_scene.ndc)
        set_matmul_precision(cfg.precision)  # the sampler's recipe picks it on CUDA
        graphs, why = replays_steps(cfg, self.device, self.ranks is not None, self.train_scene.images.device)
        if self.device.type == "cuda" and cfg.cuda_graphs is None:
            self.log("  note: " + ("steps replay as CUDA graphs (--no-cuda-graphs: eager steps)" if graphs
                                   else f"eager steps, no CUDA graphs: {why}"))
        self.cfg = cfg = dataclasses.replace(cfg, cuda_graphs=graphs)
        self.scene = scene_info(self.train_scene, folder, fmt, cfg)
        self.background = self.train_scene.background.to(self.device, torch.float32)

        torch.manual_seed(cfg.seed)  # model initialisation
        self.model_cfg = model_config(cfg.preset, cfg.model_overrides, self.train_scene.bbox, cfg.backend,
                                      ndc=self.train_scene.ndc)
        check_sizes(cfg, self.model_cfg.width, self.device)
        for note in model_notes(self.model_cfg) + recipe_notes(cfg):
            self.log(f"  note: {note}")
        self.fields = make_fields(cfg, self.model_cfg, self.train_scene.bbox)
        self.fields.to(self.device)
        self.coarse_field, self.fine_field = self.fields.runners(cfg.precision, self.device)
        # The no-grad density passes that decide what to skip (grid refreshes, early termination).
        self.density_field = (
            self.fields.runners("bf16", self.device)[0] if cfg.bf16_density_passes else self.coarse_field
        )
        self.params = [p for p in self.fields.parameters() if p.requires_grad]
        self.param_names = [n for n, p in self.fields.named_parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(
            self.params, lr=cfg.lr, eps=cfg.adam_eps, fused=self.device.type == "cuda"
        )
        self.decayed = [w for m in self.fields.modules() if isinstance(m, MLCA) for w in m.mixing_weights()]
        if cfg.mlca_weight_decay > 0 and not self.decayed:
            self.log(f"  note: --mlca-weight-decay does nothing in preset {cfg.preset}, which has no MLCA")
        near, far = self.train_scene.near, self.train_scene.far
        self.renderer = image_renderer(cfg, self.fields, near, far, self.background, step=lambda: self.step)
        self.sampler = RaySampler(self.train_scene, cfg.batch_rays, rank_seed(cfg.seed, self.rank))
        for field in self.fields.mlps():  # a replayed step draws from the generator its graph registers
            field.density_noise, field.noise_generator = cfg.density_noise, self.sampler.generator
        self.batches = self.occupancy = None
        if self.fields.grid is not None:
            self.occupancy = occupancy = occupancy_sampler(cfg, self.fields.grid, self.ranks and self.ranks.cell_share())
            if occupancy.budget is not None:
                self.sampler.batch_rays = occupancy.budget.first_rays(cfg.batch_rays)
            self.empty_points = cfg.empty_space_points if cfg.empty_space_weight > 0 else 0
            self.batches = MarchedBatches(
                lambda step: prepare_marched_batch(step, self.sampler, occupancy, self.density_field, near, far,
                                                   self.empty_points, cfg.backend),
                self.sampler)
            # The empty-space loss is the optical depth of a box diagonal through the mean density.
            self.box_diagonal = float((self.fields.grid.aabb[1] - self.fields.grid.aabb[0]).norm())
        # A first-use JIT build of the kernels (a minute or more) happens here, not on the training clock.
        use_kernel(cfg.backend, self.device)
        self.guard = NonFiniteGuard(self.param_names, self.device)
        self.spikes = LossSpikeWatch()
        self.rollback = SpikeRollback(self.params, self.optimizer, cfg.spike_rollbacks)
        self.check_every = 1 if self.device.type == "cpu" else min(cfg.log_every, 50)
        self.train_log, self.val_log = CsvLog(self.files.train_log), CsvLog(self.files.val_log)
        self.step, self.clock = 0, TrainingClock(self.device)
        self._seen, self.fixed = [0, 0, 0], None  # rays, samples and marched samples: the *_seen counters
        if state is not None:
            self._load_state(state)
        self.graphs = None
        if cfg.cuda_graphs:
            # Replayed steps read the learning rate from the device (a tensor the host refills each
            # step) and Adam keeps its step counts there: both set here, after the checkpoint's
            # groups are loaded, whatever those held.
            for group in self.optimizer.param_groups:
                group["lr"], group["capturable"] = torch.tensor(float(group["lr"]), device=self.device), True
            self._step_counter = torch.tensor(self.step, device=self.device)  # the step a replay is at
            if self.batches is None:
                self.graphs = GraphedSteps(self._graphed_step, self.params, self.sampler.generator)
        if not self.rank:
            write_text_atomic(self.files.config, json.dumps(
                {"train": cfg.to_dict(), "model": model_config_to_dict(self.model_cfg)}, indent=1))

    rays_seen = _seen_counter(0, "Rays trained on so far.")
    samples_seen = _seen_counter(1, "Samples the field was trained at so far.")
    marched_seen = _seen_counter(2, "Samples marching gave so far (before early termination).")

    def _settled_counts(self) -> list[int]:
        """The counters, with what fixed-capacity batches counted on the device folded in (a sync:
        read them at logs and checkpoints, not every step)."""
        if self.fixed is not None:
            pending = self.fixed.seen.tolist()
            self.fixed.seen.zero_()
            self._seen = [a + b for a, b in zip(self._seen, pending)]
        return self._seen

    # -- one step ---------------------------------------------------------------------------

    def train_step(self) -> dict[str, torch.Tensor]:
        """One optimisation step on a fresh random batch. Returns device scalars (no sync):
        ``loss`` (coarse + fine MSE, or the marched pass's MSE) and ``mse`` (of the final colours)."""
        cfg = self.cfg
        progress = self._progress()
        lr = self.learning_rate(progress)
        self._open_frequency_window(progress)
        for group in self.optimizer.param_groups:
            if cfg.cuda_graphs:
                group["lr"].fill_(lr)
            else:
                group["lr"] = lr
        if self.batches is not None and cfg.cuda_graphs:
            stats = self._fixed_capacity_step()
        elif self.batches is not None:
            stats = self._learn(self._marched_losses(self.batches.take(self.step)), self.step + 1)
        elif self.fields.proposal is not None:
            update = proposal_update_due(self.step, cfg.proposal_update_every)
            if self.graphs is not None:
                stats = self.graphs(update)
            else:
                stats = self._learn(self._proposal_losses(*self.sampler.sample(), update), self.step + 1)
            self.rays_seen += self.sampler.batch_rays
            self.samples_seen += self.sampler.batch_rays * cfg.proposal_samples
        else:
            rays_o, rays_d, target = self.sampler.sample()
            self.rays_seen += rays_o.shape[0]
            stats = self._learn(self._hierarchical_losses(rays_o, rays_d, target), self.step + 1)
        self.step += 1
        return stats

    def _graphed_step(self, update: bool) -> dict[str, torch.Tensor]:
        """The proposal path's step as :class:`GraphedSteps` replays it: all on the device, the
        step number included."""
        self._step_counter.add_(1)
        rays_o, rays_d, target = self.sampler.sample()
        return self._learn(self._proposal_losses(rays_o, rays_d, target, update), self._step_counter)

    def _fixed_capacity_step(self) -> dict[str, torch.Tensor]:
        """The occupancy path's step with ``--cuda-graphs``: batches of fixed capacity
        (:class:`FixedBatches`), drawn and trained in one replayed graph with no host sync (one
        graph for plain steps, one for grid refreshes). Eager steps until the grid's warm-up is
        over and the batch size has settled (the capacities come from the last of them)."""
        occupancy, step = self.occupancy, self.step
        self._step_counter.add_(1)
        if self.fixed is None:
            batch = self.batches.take(step)
            settled = step >= 2 * occupancy.refresh.warmup
            stats = self._learn(self._marched_losses(batch), self._step_counter, prefetch=not settled)
            if settled:
                self.fixed = FixedBatches(self.sampler, occupancy, FixedCapacity.for_batch(batch, occupancy.budget),
                                          self.sampler.batch_rays, self.train_scene.near, self.train_scene.far,
                                          self.empty_points, self.cfg.backend)
                self._capture_fixed_step(step)
            return stats
        if step % CAPACITY_CHECK_EVERY == 0 and self.fixed.grow():
            self._capture_fixed_step(step)
        return self.graphs("refresh" if occupancy.is_refresh_step(step) else "fixed")

    def _capture_fixed_step(self, step: int) -> None:
        """A new graph for the fixed-capacity step (captured at its first call), for new shapes."""
        self.graphs = GraphedSteps(self._fixed_body, self.params, self.sampler.generator)
        rays, marched, kept = self.fixed.capacity
        self.log(f"  step {step}: batches of up to {rays} rays, {marched} marched and {kept} kept samples")

    def _fixed_body(self, kind: str) -> dict[str, torch.Tensor]:
        """One step on a :class:`FixedBatches` batch, as :class:`GraphedSteps` replays it: kind
        "fixed", or "refresh" (the grid's refresh first, then a step with the empty-space loss)."""
        if kind == "refresh":
            self.occupancy.update(self.step, self.density_field, self.sampler.generator)
        b = self.fixed.draw(self.density_field, empty_space=kind == "refresh")
        color, *_ = shade_samples(self.coarse_field, b.rays_o, b.rays_d, b.samples, self.background, self.cfg.backend)
        losses = {"loss_coarse": b.mse(color)}
        if b.empty_points is not None:
            losses["loss_empty"] = self._empty_space_loss(b.empty_points, b.empty_mask)
        return self._learn(losses, self._step_counter, prefetch=False)

    def _learn(self, losses: dict[str, torch.Tensor], step: int | torch.Tensor,
               prefetch: bool = True) -> dict[str, torch.Tensor]:
        """Backward and optimizer step of ``losses`` at ``step`` (1-based, the host's or the device's);
        ``prefetch``: prepare the occupancy path's next batch after the backward pass."""
        cfg = self.cfg
        loss = sum(losses.values())
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.guard.observe_losses(step, **losses)
        mean = self.ranks and self.ranks.start_gradient_mean(self.params)  # overlaps the prefetch
        if self.batches is not None and prefetch:
            # Overlaps the backward pass; reads the weights before the update. The host's number of the
            # next step, whatever ``step`` is: a device counter would not match take()'s.
            self.batches.prefetch(self.step + 1)
        if mean:
            mean.finish()
        if cfg.check_grads:
            self.guard.observe_grads(step, [p.grad for p in self.params])
        if cfg.grad_clip is not None:
            # After the ranks' mean and the guard (it names the bad parameter); scaled on the device, no sync
            torch.nn.utils.clip_grad_norm_(self.params, cfg.grad_clip, foreach=True)
        self.optimizer.step()
        if cfg.mlca_weight_decay > 0:
            self._decay_mixing()
        return {"loss": loss.detach(), "mse": losses.get("loss_fine", losses["loss_coarse"]).detach()}

    def _hierarchical_losses(self, rays_o, rays_d, target) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        out = render_rays(
            self.coarse_field,
            rays_o,
            rays_d,
            self.train_scene.near,
            self.train_scene.far,
            num_coarse=cfg.num_coarse,
            num_fine=cfg.num_fine,
            fine_field=self.fine_field,
            stratified=True,
            background=self.background,
            backend=cfg.backend,
            generator=self.sampler.generator,
            check_field=self.device.type == "cpu",  # a GPU sync per pass; the guard catches what follows
        )
        self.samples_seen += rays_o.shape[0] * (
            cfg.num_coarse + (cfg.num_coarse + cfg.num_fine) * (out.fine is not None)
        )
        losses = {"loss_coarse": F.mse_loss(out.coarse.color, target)}
        if out.fine is not None:
            losses["loss_fine"] = F.mse_loss(out.fine.color, target)
        return losses

    def _proposal_losses(self, rays_o, rays_d, target, update: bool) -> dict[str, torch.Tensor]:
        """``update``: the proposal networks learn at this step. Host state is left alone (the
        step may be a CUDA graph's capture)."""
        cfg = self.cfg
        out, samples = render_rays_proposal(
            self.coarse_field, self.fields.proposal, rays_o, rays_d, self.train_scene.near, self.train_scene.far,
            stratified=True, background=self.background, generator=self.sampler.generator, backend=cfg.backend,
            train_proposal=update)
        weights = self.fields.proposal.target_weights(out.weights)
        loss = proposal_loss(samples.rounds, samples.edges, weights) if update else out.color.new_zeros(())
        losses = {"loss_coarse": F.mse_loss(out.color, target),
                  "loss_proposal": cfg.proposal_loss_weight * loss}
        if cfg.distortion_weight > 0:  # the edges are in s (no gradient): only the main field's weights learn
            losses["loss_distortion"] = cfg.distortion_weight * distortion_loss(out.weights, samples.edges)
        if cfg.occlusion_weight > 0:
            losses["loss_occlusion"] = cfg.occlusion_weight * occlusion_loss(
                out.weights, samples.edges, cfg.occlusion_fraction)
        return losses

    def _count_batch(self, batch: MarchedBatch) -> None:
        self.rays_seen += batch.rays_o.shape[0]
        self.samples_seen += batch.samples.t_starts.shape[0]
        self.marched_seen += batch.num_marched

    def _marched_losses(self, batch: MarchedBatch) -> dict[str, torch.Tensor]:
        cfg = self.cfg
        self._count_batch(batch)
        color, *_ = shade_samples(
            self.coarse_field, batch.rays_o, batch.rays_d, batch.samples, self.background, cfg.backend
        )
        losses = {"loss_coarse": F.mse_loss(color, batch.target)}
        if batch.empty_points is not None:
            losses["loss_empty"] = self._empty_space_loss(batch.empty_points, batch.empty_mask)
        return losses

    def _empty_space_loss(self, points: torch.Tensor, empty: torch.Tensor) -> torch.Tensor:
        """The optical depth of a box diagonal through the mean density at ``points`` (P, 3) that
        lie in cells the grid marks ``empty`` (P,)."""
        sigma = self.coarse_field.density(points)
        return self.cfg.empty_space_weight * (sigma * empty).mean() * self.box_diagonal

    def _progress(self) -> float:
        """How far the run is: the step over ``cfg.steps`` or, with a time budget, the training time
        over the budget when that is further along (so schedules end within the budget)."""
        progress = self.step / self.cfg.steps
        if self.cfg.time_budget is not None:
            progress = max(progress, self._training_time() / self.cfg.time_budget)
        return progress

    @torch.no_grad()
    def _decay_mixing(self) -> None:
        """AdamW's decoupled decay on MLCA's mixing matrices, at the step's learning rate (a device
        tensor in replayed steps)."""
        scale = 1 - self.optimizer.param_groups[0]["lr"] * self.cfg.mlca_weight_decay
        for weight in self.decayed:
            weight.mul_(scale)

    def learning_rate(self, progress: float | None = None) -> float:
        """The learning rate of the coming step at ``progress`` (default: the run's, :meth:`_progress`):
        a linear warm-up over ``cfg.lr_warmup`` steps, ``cfg.lr`` for the first ``cfg.lr_hold`` of the
        run, then an exponential decay to ``cfg.lr_final`` at its end."""
        cfg = self.cfg
        progress = self._progress() if progress is None else progress
        decay = min(1.0, max(0.0, (progress - cfg.lr_hold) / (1.0 - cfg.lr_hold)))
        warmup = min(1.0, (self.step + 1) / cfg.lr_warmup) if cfg.lr_warmup else 1.0
        return cfg.lr * warmup * (cfg.lr_final / cfg.lr) ** decay

    def _open_frequency_window(self, progress: float) -> None:
        """With ``cfg.frequency_anneal``: the fields' octaves of PE(x) open linearly in the run's
        ``progress``, all of them from that fraction of the run on."""
        fraction = self.cfg.frequency_anneal
        if not fraction:
            return
        alpha = self.model_cfg.pos_freqs * progress / fraction
        for field in self.fields.mlps():
            field.set_frequency_window(alpha)

    def render_rgb(self, rays_o: torch.Tensor, rays_d: torch.Tensor) -> torch.Tensor:
        """Final colours (R, 3) of arbitrary rays with the current fields (deterministic samples)."""
        return self.renderer(rays_o, rays_d).color

    def validate(self) -> float:
        """Mean PSNR over ``cfg.val_images`` evenly spaced views of the validation split."""
        scene, n = self.val_scene, min(self.cfg.val_images, len(self.val_scene))
        views = torch.linspace(0, len(scene) - 1, n).round().long().tolist()
        scores = []
        for i in views:
            rays_o, rays_d = scene.rays_for_image(i)
            rgb = self.render_rgb(rays_o.float(), rays_d.float()).reshape(scene.H, scene.W, 3)
            scores.append(psnr(rgb.clamp(0, 1), scene.image(i)).item())
            if self.tensorboard is not None:
                self.tensorboard.image(self.step, f"validation/view_{i}", rgb)
        return sum(scores) / len(scores)

    # -- the loop ---------------------------------------------------------------------------

    def fit(self) -> dict[str, Any]:
        """Train until ``cfg.steps`` or ``cfg.time_budget``; returns the summary (also written to
        ``summary.json``).

        Raises:
            NonFiniteError: a loss or gradient went NaN/Inf. The checkpoint on disk is the last
                good one; logs, plot and summary (status "non-finite") are written first.
        """
        from tqdm import tqdm

        cfg = self.cfg
        bar = tqdm(
            total=cfg.steps,
            initial=self.step,
            disable=not cfg.progress or self.rank > 0,
            unit="step",
            dynamic_ncols=True,
            leave=False,
        )
        status = "finished"
        mark_rays, mark_time = self.rays_seen, self.clock.elapsed
        self.clock.start()
        try:
            while self.step < cfg.steps:
                if cfg.time_budget is not None and self._training_time() >= cfg.time_budget:
                    status = "time budget reached"
                    break
                stats = self.train_step()
                bar.update(1)
                if self.step % self.check_every == 0:
                    self.guard.raise_if_bad()
                if self.step % cfg.log_every == 0:
                    now = self.clock.pause()
                    spike = self._log_train(
                        stats, rays_per_s=(self.rays_seen - mark_rays) / max(now - mark_time, 1e-9), bar=bar
                    )
                    mark_rays, mark_time = self.rays_seen, now
                    self.clock.start()
                    self._after_log(spike)  # keeping and restoring state is training, on its clock
                if self.step % cfg.val_every == 0:
                    self._paused(self._log_validation)
                if self.step % cfg.ckpt_every == 0:
                    self._paused(self.save)
            self.clock.pause()
            self.guard.raise_if_bad()
            if self.step % cfg.ckpt_every != 0:
                self.save()
            if self.step % cfg.val_every != 0:
                self._log_validation()
        except NonFiniteError as e:
            self.clock.pause()
            status = f"non-finite: {e}"
            self._finish(status)
            raise
        except BaseException:
            self._release_folder()  # a killed or failed run leaves the folder to the next one
            raise
        finally:
            bar.close()
        summary = self._finish(status)
        self._release_folder()
        return summary

    def save(self) -> None:
        """Atomically write the full training state to ``checkpoint.pt`` (after the guard check)."""
        self.guard.raise_if_bad()
        if self.batches is not None:
            self.batches.discard()  # a resumed run prepares its first batch with these weights
        if self.fixed is not None:
            self.sampler.batch_rays = int(self.fixed.num_rays)  # a resumed run starts eagerly with it
        rank_samplers = self.ranks and self.ranks.gather_objects(self.sampler.generator.get_state())
        if self.rank:
            return
        save_checkpoint(
            self.files.checkpoint,
            {
                "step": self.step,
                "elapsed": self.clock.elapsed,
                "train_config": self.cfg.to_dict(),
                "model_config": model_config_to_dict(self.model_cfg),
                "scene": self.scene,
                "model": self.fields.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "rng": capture_rng_state(self.sampler.generator),
                "rank_samplers": rank_samplers or [],  # each rank's own rays (several processes)
                # The occupancy sampler adapts the batch size; the counters feed samples_per_ray.
                "progress": {
                    "batch_rays": self.sampler.batch_rays,
                    "rays_seen": self.rays_seen,
                    "samples_seen": self.samples_seen,
                    "marched_seen": self.marched_seen,
                    "spike_rollbacks": self.rollback.used,
                },
            },
        )

    # -- internals --------------------------------------------------------------------------

    def _load_state(self, state: dict[str, Any]) -> None:
        self.fields.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.step = int(state["step"])
        trained_on = str(state["train_config"].get("device") or "cpu").split(":")[0]
        same_device = trained_on == self.device.type  # a generator's state is one device type's
        restore_rng_state(state["rng"], self.sampler.generator if same_device and not self.rank else None)
        if self.rank:
            restore_rank_sampler(self.sampler.generator, state.get("rank_samplers", []) if same_device else [],
                                 self.rank, self.cfg.seed, self.step)
        elif not same_device:
            self.sampler.generator.manual_seed(rank_seed(self.cfg.seed, 0, self.step))
            self.log(f"moved from {trained_on} to {self.device.type}: from step {self.step} on, the random "
                     "batches differ from an uninterrupted run's")
        progress = state.get("progress", {})
        self.sampler.batch_rays = int(progress.get("batch_rays", self.sampler.batch_rays))
        self.rays_seen = int(progress.get("rays_seen", 0))
        self.samples_seen = int(progress.get("samples_seen", 0))
        self.marched_seen = int(progress.get("marched_seen", 0))
        self.rollback.used = min(int(progress.get("spike_rollbacks", 0)), self.rollback.limit)
        self.clock = TrainingClock(self.device, float(state["elapsed"]))
        # Rows a killed run logged after its last checkpoint describe steps that will be redone.
        if not self.rank:
            self.train_log.truncate_after(self.step)
            self.val_log.truncate_after(self.step)
        self.log(f"resumed {self.files.checkpoint} at step {self.step}")

    def _training_time(self) -> float:
        """The training clock; with several ranks rank 0's, read once a step (one broadcast), so
        that they all decide alike."""
        if self.ranks is None:
            return self.clock.now()
        if self._shared_time[0] != self.step:
            self._shared_time = (self.step, self.ranks.decide(self.clock.now()))
        return self._shared_time[1]

    def _release_folder(self) -> None:
        if self.lock is not None:
            self.lock.release()

    def _paused(self, action: Callable[[], Any]) -> None:
        """Run ``action`` with the training clock paused."""
        self.clock.pause()
        action()
        self.clock.start()

    def _log_train(self, stats: dict[str, torch.Tensor], rays_per_s: float, bar: Any) -> str | None:
        """Writes the step's row; returns the spike note of its colour loss (None: no spike, or a rank > 0)."""
        if self.rank:
            return None
        loss, mse = stats["loss"].item(), stats["mse"].item()
        row = {
            "step": self.step,
            "seconds": round(self.clock.elapsed, 3),
            "lr": float(self.optimizer.param_groups[0]["lr"]),
            "loss": loss,
            "psnr": -10.0 * math.log10(max(mse, 1e-30)),
            "rays_per_s": round(rays_per_s, 1),
            "samples_per_ray": round(self.samples_seen / max(self.rays_seen, 1), 2),
            "grad_norm": self._grad_norm(),
        }
        self.train_log.append(row)
        if self.tensorboard is not None:
            scalars = {f"train/{k}": v for k, v in row.items() if k not in ("step", "seconds")}
            self.tensorboard.scalars(self.step, scalars)
        bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{row['psnr']:.2f}", rays_s=f"{rays_per_s:,.0f}")
        # The colour loss, not the total: a regulariser added at some logged steps is no spike.
        return self.spikes.observe(self.step, mse)

    def _after_log(self, spike: str | None) -> None:
        """At a logged step: keep the trained state for a later rollback or, at a spike, say it and
        go back to the state kept before it (every rank alike: rank 0 read the loss)."""
        if spike is not None:
            self.log(f"  note: {spike}")
        if not self.rollback.limit:  # nothing to go back to: no rank needs rank 0's reading
            return
        spiked = spike is not None
        if self.ranks is not None:
            spiked = bool(self.ranks.decide(float(spiked)))
        if not spiked:
            self.rollback.keep(self.step)
            return
        back_to = self.rollback.restore()
        if back_to is not None:
            self.log(f"  note: back to the fields and optimiser of step {back_to}, on with new batches "
                     f"(rollback {self.rollback.used} of {self.rollback.limit}; --spike-rollbacks)")
        elif not self.rollback.left:
            self.log(f"  note: no rollback left ({self.rollback.limit} used; --spike-rollbacks)")
        else:
            self.log("  note: no state kept yet to go back to (one is kept at each logged step)")

    @torch.no_grad()
    def _grad_norm(self) -> float:
        """Global norm of the last step's gradients (after ``grad_clip``): what a clip bound is chosen
        against. Read only at log steps, which synchronise anyway."""
        grads = [p.grad for p in self.params if p.grad is not None]
        return float(torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads)))) if grads else 0.0

    def _log_validation(self) -> None:
        if self.rank:
            return  # the others wait for rank 0 at their next collective
        value = self.validate()
        self.val_log.append({"step": self.step, "seconds": round(self.clock.elapsed, 3), "psnr": value})
        if self.tensorboard is not None:
            self.tensorboard.scalars(self.step, {"validation/psnr": value})
        self.log(f"step {self.step}: validation PSNR {value:.2f} dB ({self.val_split} split)")

    def _finish(self, status: str) -> dict[str, Any]:
        if self.rank:
            return {"status": status, "step": self.step, "rank": self.rank}
        val = self.val_log.rows()
        summary = {
            "status": status,
            "step": self.step,
            "train_seconds": round(self.clock.elapsed, 3),
            "val_psnr": float(val[-1]["psnr"]) if val else None,
            "checkpoint": str(self.files.checkpoint) if self.files.checkpoint.exists() else None,
            "curves": str(plot_curves(self.train_log, self.val_log, self.files.curves) or ""),
            "device": str(self.device),
            "processes": 1 if self.ranks is None else self.ranks.world_size,
            "precision": self.cfg.precision,
            "spike_rollbacks": self.rollback.used,
        }
        write_text_atomic(self.files.summary, json.dumps(summary, indent=1))
        if self.tensorboard is not None:
            self.tensorboard.close()
        return summary
