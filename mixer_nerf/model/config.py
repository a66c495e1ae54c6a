"""Model configuration and the ablation presets A (NeRF), B (+SE), C (+MLCA), D (Mixer-NeRF)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

PRESETS = {
    "A": {"use_se": False, "use_mlca": False},  # NeRF
    "B": {"use_se": True, "use_mlca": False},  # NeRF + squeeze-and-excitation
    "C": {"use_se": False, "use_mlca": True},  # NeRF + MLCA
    "D": {"use_se": True, "use_mlca": True},  # Mixer-NeRF
}
DENSITY_ACTIVATIONS = ("softplus", "relu")


@dataclass
class ModelConfig:
    """Every knob of :class:`~mixer_nerf.model.MixerNeRF` (defaults: the paper's sizes, preset D).

    Plain data (ints, floats, bools, strings, a tuple): ``dataclasses.asdict(cfg)`` round-trips
    through JSON and ``ModelConfig(**d)``, so checkpoints can store it.
    """

    use_mlca: bool = True
    use_se: bool = True
    # NeRF backbone
    depth: int = 8  # trunk layers
    width: int = 256  # trunk width = feature width
    skips: tuple[int, ...] = (4,)  # trunk layers whose input is [encoded position, hidden]
    view_width: int = 128  # hidden width of the view-dependent colour branch
    # Positional encoding: positions are mapped by (x - scene_center) / scene_scale to about
    # [-1, 1]^3 first, so that with pe_scale = pi the lowest octave (period 2) does not alias.
    pos_freqs: int = 10
    dir_freqs: int = 4
    pe_scale: float = math.pi
    scene_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scene_scale: float = 1.5  # half-size of the scene box (Blender scenes: [-1.5, 1.5]^3)
    # MLCA (hybrid spatial feature learning)
    mlca_channels: int = 8  # channels each frequency-band token is lifted to (from 3 coordinates)
    mlca_concat_direction: bool = False  # paper's Eq. 7: mix PE(x) and PE(d) together in the trunk
    mlca_directions: bool = True  # an MLCA on PE(d) before the view branch (False: NeRF's PE(d) there)
    # Squeeze-and-excitation
    se_reduction: int = 16
    se_per_point: bool = False  # gate each sample by itself instead of by its ray's mean
    # The gate scales the features both heads read (the paper's); False: the colour branch's only,
    # so that the density is the point's alone, as the occupancy grid and the marching pre-pass see it.
    se_gates_density: bool = True
    # Density
    density_activation: str = "softplus"  # "relu" reproduces the original NeRF recipe
    density_shift: float = -1.0  # sigma = softplus(raw + density_shift)
    backend: str = "auto"  # the ops of positional encoding, MLCA and packed SE ("auto" | "kernel" | "torch")

    def __post_init__(self) -> None:
        self.skips = tuple(int(s) for s in self.skips)
        self.scene_center = tuple(float(c) for c in self.scene_center)
        for name in ("depth", "width", "view_width", "mlca_channels", "se_reduction"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("pos_freqs", "dir_freqs"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if any(not 0 < s < self.depth for s in self.skips):
            raise ValueError(f"skips must be trunk layer indices in [1, {self.depth - 1}], got {self.skips}")
        if len(self.scene_center) != 3:
            raise ValueError(f"scene_center must have 3 entries, got {self.scene_center}")
        if not (math.isfinite(self.scene_scale) and self.scene_scale > 0):
            raise ValueError(f"scene_scale must be positive and finite, got {self.scene_scale}")
        if self.mlca_channels < 3:
            raise ValueError(
                f"mlca_channels must be >= 3 (the coordinates it lifts), got {self.mlca_channels}"
            )
        if self.width // self.se_reduction < 1:
            raise ValueError(f"se_reduction {self.se_reduction} leaves no channels of width {self.width}")
        if self.density_activation not in DENSITY_ACTIVATIONS:
            raise ValueError(
                f"density_activation must be one of {DENSITY_ACTIVATIONS}, got {self.density_activation!r}"
            )

    @property
    def preset(self) -> str:
        """The preset letter of these MLCA/SE switches."""
        switches = {"use_se": self.use_se, "use_mlca": self.use_mlca}
        return next(name for name, preset in PRESETS.items() if preset == switches)


def preset_config(preset: str = "D", **overrides) -> ModelConfig:
    """The configuration of ablation preset ``"A"``, ``"B"``, ``"C"`` or ``"D"``, with overrides.

    Example: ``preset_config("D", width=128, scene_scale=1.0)``.
    """
    key = str(preset).upper()
    if key not in PRESETS:
        raise ValueError(f"preset must be one of {tuple(PRESETS)}, got {preset!r}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(ModelConfig)}
    if unknown:
        raise TypeError(f"unknown ModelConfig fields: {sorted(unknown)}")
    return ModelConfig(**{**PRESETS[key], **overrides})
