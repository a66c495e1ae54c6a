"""Training configuration: one flat dataclass, saved in every checkpoint and in ``config.json``."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from ..data import FORMATS
from ..render.image_renderer import RENDER_SAMPLES
from ..render.skipping import INTERVALS, JITTERS, RESIDUALS, MarchingOptions

PRESETS = ("A", "B", "C", "D")
PRECISIONS = ("bf16", "tf32", "fp32")
BACKENDS = ("auto", "kernel", "torch")
SAMPLERS = ("auto", "occupancy", "proposal", "hierarchical")
VAL_IMAGES = {"cuda": 3, "cpu": 1}  # views per validation, by device type


FORWARD_FACING_PROPOSAL_STEPS = 20_000
"""``steps`` where the config leaves it open, for the proposal sampler in a forward-facing (NDC) scene:
a capture of a few views is best on unseen ones after a shorter schedule (docs/training.md)."""
DEFAULT_STEPS = 50_000
"""``steps`` where the config leaves it open, elsewhere."""


def option(default: Any, help: str, **argparse_options: Any) -> Any:
    """A TrainConfig field that is also a ``train`` flag ``--name-with-dashes``: its help text and
    argparse options (choices, metavar) live in the field's metadata, so flags and fields cannot drift."""
    return field(default=default, metadata={"help": help, **argparse_options})


@dataclass
class TrainConfig:
    """Everything that defines a training run.

    ``None`` in ``precision``, ``device`` and ``bf16_density_passes`` means "pick for the machine"
    (see :meth:`resolved`): fp32 on CPU; on CUDA the sampler's recipe (bf16 autocast for the
    occupancy sampler, TF32 for the others: docs/training.md), bf16 density passes on CUDA, off on
    CPU. ``cuda_graphs=None`` is decided by the trainer, which knows the sampler, the processes and
    where the images went: on wherever a step can be replayed.
    Learning rate: a linear warm-up over ``lr_warmup`` steps, ``lr`` held for the first ``lr_hold``
    of the run, then an exponential decay to ``lr_final`` at its end. The run's end is ``steps`` or,
    with a ``time_budget``, whichever of the two comes first: the schedule follows the training
    clock, so a run given 2 minutes anneals within them. Learning-rate settings left at None come
    from the sampler's recipe (``SAMPLER_RECIPES``) once the sampler is decided.
    """

    data: str | None = None  # scene folder; None = the built-in procedural scene
    format: str = option("auto", "scene format (default: detected)", choices=FORMATS)
    downscale: float = option(1.0, "image downscale, any factor >= 1")
    val_holdout: int = option(
        0, "validate on every K-th training view (of a capture: of those not held out for test), which "
        "training then leaves out, so that nothing is tuned on the views reported: test, or a Blender "
        "scene's own val views when it ships no test split (default 0: validate on the val views, a "
        "capture's being its test views)",
        metavar="K")
    procedural_resolution: int = 100  # image size of the built-in scene
    procedural_views: int = 100  # its number of training views
    preset: str = option("D", "A NeRF, B +SE, C +MLCA, D Mixer-NeRF (default D)", choices=PRESETS)
    model_overrides: dict[str, Any] = field(default_factory=dict)  # passed to preset_config
    fine_network: bool = True  # a separate fine MLP, as in NeRF (False: the coarse one is reused)
    steps: int | None = option(
        None, f"training steps, also the length of the lr schedule (default {FORWARD_FACING_PROPOSAL_STEPS:,} for "
        f"the proposal sampler on forward-facing (NDC) scenes, {DEFAULT_STEPS:,} elsewhere)")
    batch_rays: int = option(4096, "rays per step")
    num_coarse: int = option(64, "coarse samples per ray")
    num_fine: int = option(128, "fine samples per ray (0: no fine pass)")
    # None: the sampler's recipe (SAMPLER_RECIPES), filled in once the sampler is known
    lr: float | None = option(None, "learning rate after the warm-up (default: occupancy sampler 4e-3, "
                              "hierarchical 5e-4), decaying exponentially to --lr-final")
    lr_final: float | None = option(None, "learning rate at the end of the run, --steps or --time-budget, "
                                    "whichever comes first (default: lr/10)")
    lr_warmup: int | None = option(
        None, "linear learning-rate warm-up (default: occupancy 200, hierarchical 0)", metavar="STEPS"
    )
    lr_hold: float | None = option(None, "fraction of the run at --lr before the decay to --lr-final starts "
                                   "(default: occupancy sampler 0.5, hierarchical 0)", metavar="FRACTION")
    adam_eps: float | None = option(
        None, "Adam's epsilon, added to the gradients' running RMS in each update's denominator: a larger "
        "value damps the steps of parameters whose gradients are small (default: proposal sampler 1e-8, "
        "the others 1e-15)", metavar="EPS")
    # Off by default: a remedy for loss spikes in long runs, not yet measured (docs/training.md).
    grad_clip: float | None = option(
        None, "scale the gradients of the trained networks (field and proposal networks) down so that "
        "their global norm is at most NORM before each optimizer step, against loss spikes in long runs "
        "(default: no clipping)", metavar="NORM")
    spike_rollbacks: int = option(
        3, "times a run may go back to its state of two log intervals before a loss spike (a logged colour "
        "loss over twice the median of the ten logged before it) and go on with new batches; 0: never",
        metavar="N")
    seed: int = option(0, "random seed")
    precision: str | None = option(
        None, "MLP precision (default on CUDA: bf16 for the occupancy sampler, tf32 for the others; "
        "fp32 on CPU)", choices=PRECISIONS
    )
    device: str | None = option(None, "default: cuda when available", choices=("cpu", "cuda"))
    backend: str = option("auto", "ops: compiled kernels or the PyTorch reference", choices=BACKENDS)
    out: str = "runs/default"
    val_every: int = option(2500, "validate every N steps")
    val_images: int | None = option(
        None, f"val views each validation renders (default: {VAL_IMAGES['cuda']} on CUDA, {VAL_IMAGES['cpu']} on CPU, "
        "where a full-size view of preset D takes minutes)", metavar="N")
    ckpt_every: int = option(1000, "checkpoint every N steps (a killed run loses at most N)")
    log_every: int = option(100, "log a training row (train_log.csv, TensorBoard) every N steps")
    # validation excluded; None: no limit
    time_budget: float | None = option(None, "stop after this much training time", metavar="SECONDS")
    chunk: int = 8192  # most rays per chunk when rendering whole images
    render_samples: int | None = option(
        None, "most samples shaded at once when rendering whole images: bounds their memory whatever the "
        f"rays hit (default: {RENDER_SAMPLES['cpu']} on CPU, {RENDER_SAMPLES['cuda']} on CUDA)", metavar="N")
    check_grads: bool = True  # the non-finite guard also checks every gradient
    # "occupancy": one marched pass over packed samples (mixer_nerf.render.skipping; no fine
    # network). "proposal": proposal networks pick proposal_samples intervals per ray (no fine
    # network). "hierarchical": NeRF's dense coarse + fine passes. "auto": sampling.resolve_sampler.
    sampler: str = option(
        "auto",
        "occupancy (skip empty space, occluded samples, missed rays), proposal (small density networks "
        "pick the samples), hierarchical (NeRF's dense coarse + fine), auto (occupancy for bounded "
        "scenes such as Blender's, proposal for forward-facing and unbounded ones)",
        choices=SAMPLERS,
    )
    grid_resolution: int = option(128, "occupancy grid cells per axis")
    grid_every: int = 16  # refresh the grid from the model's density every N steps
    grid_warmup: int = 256  # steps during which every cell counts as occupied
    grid_threshold: float = 0.01  # opacity of one marching step above which a cell is occupied
    step_size: float | None = None  # marching step; None: the box diagonal / 1000
    early_stop_eps: float = option(1e-4, "stop rays whose transmittance falls below this (0: never)")
    alpha_threshold: float = 0.0  # drop samples with a smaller alpha (0: keep them)
    target_samples: int | None = option(
        131072, "occupancy sampler: MLP samples per step (the ray batch adapts)"
    )
    # Marching never samples cells the grid marks empty; this keeps a render without the grid clean.
    # Off by default: it lowered val PSNR at 120 s and 240 s (docs/training.md).
    empty_space_weight: float = option(
        0.0, "occupancy sampler: weight of the loss that keeps density out of the cells the grid marks "
        "empty, applied at each grid refresh, for renders without the grid (default 0: off; e.g. 1e-2)")
    empty_space_points: int = 65536
    # bf16 whatever `precision` is: these passes only decide which samples to skip.
    bf16_density_passes: bool | None = option(
        None, "occupancy sampler: no-grad density passes (grid refreshes, early termination) in bf16 "
        "(default: on CUDA)")
    # proposal: samples of each proposal network's round, then of the main field
    proposal_rounds: tuple[int, ...] = (128, 64)
    proposal_samples: int = 48
    proposal_width: int = 128  # hidden width of each proposal network (2 layers)
    proposal_loss_weight: float = option(
        1.0, "proposal sampler: weight of the proposal networks' interval loss, summed over the main field's "
        "samples of a ray (nerfacc's estimator averages over them: 1/48 of this at 48 samples)", metavar="W")
    # The three proposal defaults below are nerfacc's recipe: a Fern screen found them 1.3 dB ahead
    # of updating every step with per-sample jitter (benchmarks/results/time_to_quality/README.md).
    proposal_update_every: int = option(
        6, "proposal sampler: train the proposal networks every N steps from step 1000 (the interval "
        "grows from 1 over the first 1000 steps); the other steps sample without their gradient "
        "(1: every step)")
    proposal_jitter: str = option(
        "per_ray", "proposal sampler: stratified training positions jittered with one offset per ray "
        "or per sample", choices=JITTERS)
    proposal_weight_padding: float = option(
        0.0, "proposal sampler: added to every proposal weight before resampling, so that no part of "
        "a ray is given up (default 0: none)")
    # drop: a Fern val screen gave "last" no gain (docs/skipping.md)
    proposal_residual: str = option(
        "drop", "proposal sampler: a ray's transmittance left after its last interval is dropped (each "
        "round's PDF is its weights normalised) or added to the last interval (nerfacc's estimator), "
        "in sampling and in the proposal loss", choices=RESIDUALS)
    proposal_intervals: str = option(
        "drawn", "proposal sampler: each round's interval edges are drawn from its PDF, or put halfway "
        "between drawn positions (nerfacc's estimator)", choices=INTERVALS)
    # Against floaters; off: on Fern's val split it did not help a 600 s run (docs/training.md).
    distortion_weight: float = option(
        0.0, "proposal sampler: weight of mip-NeRF 360's distortion loss on the main field's weights, "
        "which gathers each ray's weight into few short intervals (default 0: off; nerfacto uses 0.002)",
        metavar="W")
    # Off: at 20,000 steps on Fern's val split D ended higher without it (docs/training.md).
    occlusion_weight: float = option(
        0.0, "proposal sampler: weight of FreeNeRF's occlusion regularisation, the main field's weight "
        "in the first --occlusion-fraction of each ray (default 0: off; e.g. 0.01)", metavar="W")
    occlusion_fraction: float = option(
        0.1, "proposal sampler: the stretch of each ray, in the sampler's spacing coordinate s in [0, 1], "
        "that --occlusion-weight penalises", metavar="FRACTION")
    # Off until screened: a remedy for overfitting on few views (docs/training.md).
    frequency_anneal: float = option(
        0.0, "open the positions' encoding octave by octave over this fraction of the run, coarse to "
        "fine (Nerfies' window; FreeNeRF's frequency regularisation against overfitting on few views; "
        "default 0: every octave from the start)", metavar="FRACTION")
    density_noise: float = option(
        0.0, "standard deviation of the Gaussian noise added to the field's density pre-activation in "
        "training steps, NeRF's and mip-NeRF's regulariser against floaters on real captures (they use 1 "
        "on LLFF scenes; default 0: off)", metavar="STD")
    # Off: at 20,000 steps on Fern's val split D ended higher without it (docs/training.md).
    mlca_weight_decay: float = option(
        0.0, "decoupled weight decay of MLCA's token- and channel-mixing matrices (presets C and D): "
        "after each step they are scaled by 1 - lr * W, which pulls the mixing toward the identity, "
        "the NeRF it extends (default 0: off; e.g. 10)", metavar="W")
    cuda_graphs: bool | None = option(
        None, "proposal or occupancy sampler on a GPU: replay each training step as a CUDA graph, without "
        "the host work between its kernels; occupancy batches are padded to a fixed capacity (default: on "
        "where a step can be replayed: a GPU, one process, the training images on the GPU)")
    tensorboard: bool = option(
        False, "log losses, PSNR, learning rate, samples per ray, rays/s and validation renders to "
        "<out>/tensorboard (needs .[tensorboard])"
    )
    progress: bool = True  # progress bar on stderr

    def __post_init__(self) -> None:
        _one_of("format", self.format, FORMATS)
        _one_of("preset", self.preset, PRESETS)
        _one_of("backend", self.backend, BACKENDS)
        _one_of("sampler", self.sampler, SAMPLERS)
        if not self.empty_space_weight >= 0:
            raise ValueError(f"empty_space_weight must be >= 0, got {self.empty_space_weight}")
        self.marching()  # checks step_size, early_stop_eps, alpha_threshold
        if self.precision is not None:
            _one_of("precision", self.precision, PRECISIONS)
        if self.device is not None and self.device.split(":")[0] not in ("cpu", "cuda"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {self.device!r}")
        if self.steps is not None and self.steps < 1:
            raise ValueError(f"steps must be positive, got {self.steps}")
        for name in (
            "batch_rays",
            "num_coarse",
            "val_every",
            "ckpt_every",
            "grid_resolution",
            "grid_every",
            "empty_space_points",
            "log_every",
            "chunk",
            "procedural_resolution",
            "procedural_views",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not self.downscale >= 1:
            raise ValueError(f"downscale must be >= 1, got {self.downscale}")
        if not (isinstance(self.val_holdout, int) and self.val_holdout >= 0):
            raise ValueError(f"val_holdout must be an integer >= 0, got {self.val_holdout!r}")
        _finite_non_negative("mlca_weight_decay", self.mlca_weight_decay)
        _finite_non_negative("density_noise", self.density_noise)
        if not 0 <= self.frequency_anneal <= 1:
            raise ValueError(f"frequency_anneal must be in [0, 1], got {self.frequency_anneal}")
        if self.lr_hold is not None and not 0 <= self.lr_hold < 1:
            raise ValueError(f"lr_hold must be in [0, 1), got {self.lr_hold}")
        if self.lr_warmup is not None and self.lr_warmup < 0:
            raise ValueError(f"lr_warmup must be >= 0, got {self.lr_warmup}")
        if self.num_fine < 0:
            raise ValueError(f"num_fine must be >= 0, got {self.num_fine}")
        for name in ("lr", "lr_final"):
            if getattr(self, name) is not None and not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        self.proposal_rounds = tuple(int(n) for n in self.proposal_rounds)
        if not self.proposal_rounds or min(self.proposal_rounds) < 1 or self.proposal_samples < 1:
            raise ValueError(f"proposal_rounds and proposal_samples must be positive, got "
                             f"{self.proposal_rounds}, {self.proposal_samples}")
        if self.proposal_width < 1 or not self.proposal_loss_weight >= 0:
            raise ValueError("proposal_width must be positive and proposal_loss_weight >= 0")
        if self.proposal_update_every < 1:
            raise ValueError(f"proposal_update_every must be positive, got {self.proposal_update_every}")
        _one_of("proposal_jitter", self.proposal_jitter, JITTERS)
        _one_of("proposal_residual", self.proposal_residual, RESIDUALS)
        _one_of("proposal_intervals", self.proposal_intervals, INTERVALS)
        if not self.proposal_weight_padding >= 0:
            raise ValueError(f"proposal_weight_padding must be >= 0, got {self.proposal_weight_padding}")
        for name in PROPOSAL_REGULARISERS:
            weight = getattr(self, name)
            _finite_non_negative(name, weight)
            if weight > 0 and self.sampler not in ("auto", "proposal"):
                raise ValueError(f"{name} applies to the proposal sampler only, not to sampler {self.sampler!r}")
        if not 0 < self.occlusion_fraction < 1:
            raise ValueError(f"occlusion_fraction must be in (0, 1), got {self.occlusion_fraction}")
        if self.adam_eps is not None and not 0 < self.adam_eps < math.inf:
            raise ValueError(f"adam_eps must be positive and finite, got {self.adam_eps}")
        if self.grad_clip is not None and not 0 < self.grad_clip < math.inf:
            raise ValueError(f"grad_clip must be a positive, finite norm or None, got {self.grad_clip}")
        if not (isinstance(self.spike_rollbacks, int) and self.spike_rollbacks >= 0):
            raise ValueError(f"spike_rollbacks must be an integer >= 0, got {self.spike_rollbacks!r}")
        if self.time_budget is not None and not 0 < self.time_budget < math.inf:
            raise ValueError(f"time_budget must be a positive, finite number of seconds, got {self.time_budget}")
        for name in ("val_images", "render_samples", "target_samples"):  # None: chosen per machine
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")

    def resolved(self, cuda_available: bool) -> TrainConfig:
        """A copy with ``device``, ``bf16_density_passes`` and ``val_images`` chosen for this machine,
        and ``precision`` on a CPU (on CUDA :meth:`with_recipe` picks it by sampler)."""
        device = self.device or ("cuda" if cuda_available else "cpu")
        if device.startswith("cuda") and not cuda_available:
            raise ValueError("device 'cuda' was asked for but torch sees no CUDA GPU")
        on_cuda = device.startswith("cuda")
        precision = self.precision or (None if on_cuda else "fp32")
        bf16_passes = on_cuda if self.bf16_density_passes is None else self.bf16_density_passes
        val_images = self.val_images or VAL_IMAGES["cuda" if on_cuda else "cpu"]
        return dataclasses.replace(self, device=device, precision=precision, bf16_density_passes=bf16_passes,
                                   val_images=val_images)

    def with_recipe(self, sampler: str) -> TrainConfig:
        """A copy for ``sampler`` ("occupancy", "proposal" or "hierarchical") with the optimizer
        settings left at None taken from its recipe (``SAMPLER_RECIPES``), and on CUDA its precision."""
        recipe = SAMPLER_RECIPES[sampler]
        on_cuda = (self.device or "").startswith("cuda")
        lr = recipe["lr"] if self.lr is None else self.lr
        return dataclasses.replace(
            self,
            sampler=sampler,
            lr=lr,
            lr_final=lr * recipe["lr_decay"] if self.lr_final is None else self.lr_final,
            lr_warmup=recipe["lr_warmup"] if self.lr_warmup is None else self.lr_warmup,
            lr_hold=recipe["lr_hold"] if self.lr_hold is None else self.lr_hold,
            adam_eps=recipe["adam_eps"] if self.adam_eps is None else self.adam_eps,
            precision=self.precision or (recipe["precision"] if on_cuda else None),
        )

    def marching(self) -> MarchingOptions:
        """The occupancy sampler's marching step and skips."""
        return MarchingOptions(self.step_size, self.early_stop_eps, self.alpha_threshold)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        """Inverse of :meth:`to_dict`; unknown keys (from a newer version) are an error."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown training settings: {unknown}")
        return cls(**values)


# Losses on the proposal sampler's main field, each off at weight 0.
PROPOSAL_REGULARISERS = ("distortion_weight", "occlusion_weight")

SAMPLER_RECIPES: dict[str, dict[str, Any]] = {
    # Chosen by time-to-quality screens on Lego; eps 1e-15 is nerfacc's; bf16: 1.46x the steps of
    # TF32 in 240 s on Lego and a higher held-out PSNR (docs/training.md).
    "occupancy": {"lr": 4e-3, "lr_decay": 0.1, "lr_warmup": 200, "lr_hold": 0.5, "adam_eps": 1e-15,
                  "precision": "bf16"},
    # eps 1e-8: 1e-15 let a Fern run's loss spike for good during the 2e-3 hold (docs/training.md);
    # TF32: bf16 not yet measured on Fern
    "proposal": {"lr": 2e-3, "lr_decay": 0.1, "lr_warmup": 200, "lr_hold": 0.5, "adam_eps": 1e-8,
                 "precision": "tf32"},
    # NeRF's recipe for dense coarse + fine batches: 5e-4 decaying 10x over the whole run.
    "hierarchical": {"lr": 5e-4, "lr_decay": 0.1, "lr_warmup": 0, "lr_hold": 0.0, "adam_eps": 1e-15,
                     "precision": "tf32"},
}
"""Optimizer settings per sampler, for the fields a TrainConfig leaves at None, and the MLP's
precision on CUDA."""

DEMO_SETTINGS: dict[str, Any] = {
    "procedural_resolution": 40,
    "procedural_views": 50,
    "model_overrides": {
        "depth": 4,
        "width": 64,
        "skips": (2,),
        "view_width": 32,
        "pos_freqs": 8,
        "se_reduction": 8,
    },
    # At 40x40 pixels the occupancy sampler's fine marching step costs more samples per ray than
    # 16 + 16 hierarchical samples do.
    "sampler": "hierarchical",
    "steps": 1200,
    "batch_rays": 512,
    "num_coarse": 16,
    "num_fine": 16,
    "lr": 1e-3,
    "lr_final": 1e-4,
    "val_every": 300,
    "val_images": 2,
    "ckpt_every": 300,
    "log_every": 50,
}
"""Defaults for the built-in scene so that a run finishes in a few minutes on a 2-core CPU."""


def _finite_non_negative(name: str, value: float) -> None:
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")


def _one_of(name: str, value: Any, allowed: tuple) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
