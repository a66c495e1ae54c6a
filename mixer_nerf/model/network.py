"""The Mixer-NeRF field: NeRF's MLP on our positional encoding, with optional MLCA and SE blocks.

    x -> (x - center) / scale -> PE (10 octaves) -> [MLCA] -> trunk 8 x 256, ReLU, skip at 4
      -> [SE over the ray's samples] -> Linear 256 -> 1 + 256 -> sigma = softplus(raw - 1), feature
         (se_gates_density=False: sigma from the trunk's output before SE, the feature after it)
    d -> PE (4 octaves) -> [MLCA, unless mlca_directions=False] ---+
    feature -> Linear 256 -> 128  +  Linear (PE(d) width) -> 128  -+-> ReLU -> Linear 128 -> 3 -> sigmoid

Density activation and initialisation. With NeRF's ReLU density and PyTorch's default init, a run
on Lego collapsed to an all-background image: once the density pre-activation is negative
everywhere, ReLU passes no gradient and the field cannot recover. Here the density is
``softplus(raw + density_shift)`` (mip-NeRF's choice, shift -1): its gradient ``sigmoid(raw + shift)``
is never zero, so a field that has been pushed towards empty space still receives a signal
wherever the images need matter. The density row of the head starts at zero, so whatever the
seed the field starts as the same uniform fog of density softplus(-1) ~ 0.31 (a 4-unit Blender
ray is ~70% opaque): colour and density both get gradients from the first step, and the start
does not depend on a random per-network offset of the density (with a random density row the
initial mean density varied 3x between seeds). The trunk and view
layers use He (Kaiming-normal, fan-in) init with zero biases, which keeps ReLU activations at unit
scale through the 8 layers (PyTorch's default shrinks them ~2.4x per layer, leaving the heads
a nearly constant input); linear heads use Xavier init. ``density_activation="relu"`` keeps the
original recipe for comparison.

Layouts: dense samples ``x (R, S, 3)`` with ``d (R, S, 3)`` or per-ray ``(R, 1, 3)`` (an expanded
``(R, S, 3)`` view of a per-ray tensor is recognised by its zero stride and treated as per-ray, so
the view branch's direction term is computed once per ray), or packed ``x (N, 3)`` with ``d (N, 3)``
and, for the SE squeeze, optional CSR ``offsets (R+1,)`` (rows of a ray contiguous: the fused SE
ops) or ``ray_indices (N,)`` (rows in any order); without either every point is its own ray.
Packed samples with a layout may give ``ray_directions (R, 3)`` instead of ``d``: the view branch
then runs once per ray too (:mod:`mixer_nerf.model.ray_rows` spreads its rows to the samples).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..ops import linear, linear_relu, positional_encoding
from ..ops._checks import check_floating, check_offsets, check_same_device, check_tensor
from .config import ModelConfig
from .mlca import MLCA
from .ray_rows import spread_to_samples
from .squeeze_excitation import SqueezeExcitation


class MixerNeRF(nn.Module):
    """Radiance field ``f(x, d) -> (sigma, rgb)``; see the module docstring for the architecture."""

    # Packed samples' layout the renderers pass (mixer_nerf.render.skipping): SE squeezes per ray,
    # and the view branch runs once per ray on the rays' directions.
    packed_layout = ("ray_indices", "offsets", "ray_directions")

    def __init__(self, cfg: ModelConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg = cfg or ModelConfig()
        pos_tokens, dir_tokens = 1 + 2 * cfg.pos_freqs, 1 + 2 * cfg.dir_freqs
        trunk_tokens = pos_tokens + (dir_tokens if cfg.mlca_concat_direction else 0)
        self.position_mixer = _mixer(cfg, trunk_tokens, cfg.use_mlca)
        self.direction_mixer = _mixer(cfg, dir_tokens, cfg.use_mlca and cfg.mlca_directions)
        trunk_in = trunk_tokens * _channels(self.position_mixer)
        dir_in = dir_tokens * _channels(self.direction_mixer)

        widths = [trunk_in] + [cfg.width] * cfg.depth
        self.trunk = nn.ModuleList(
            nn.Linear(widths[i] + (trunk_in if i in cfg.skips else 0), cfg.width) for i in range(cfg.depth)
        )
        self.se = None
        if cfg.use_se:
            self.se = SqueezeExcitation(cfg.width, cfg.se_reduction, cfg.se_per_point, cfg.backend)
        self.head = nn.Linear(cfg.width, 1 + cfg.width)  # density pre-activation, then the feature
        self.view_feature = nn.Linear(cfg.width, cfg.view_width)
        self.view_direction = nn.Linear(dir_in, cfg.view_width, bias=False)
        self.rgb = nn.Linear(cfg.view_width, 3)
        for layer in (*self.trunk, self.view_feature, self.view_direction):
            _init_relu_layer(layer)
        for layer in (self.head, self.rgb):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
        with torch.no_grad():
            self.head.weight[0].zero_()  # every seed starts from density softplus(shift) everywhere
        self.register_buffer("scene_center", torch.tensor(cfg.scene_center, dtype=torch.float32))
        # The coarse-to-fine window over PE(x) (set_frequency_window): each column's octave (-1 for
        # x itself), and its weight, filled on the device so that moving the window never syncs.
        octave = torch.arange(cfg.pos_freqs, dtype=torch.float32).repeat_interleave(6)
        self.register_buffer("octave_of_column", torch.cat([torch.full((3,), -1.0), octave]), persistent=False)
        self.register_buffer("octave_weights", torch.ones_like(self.octave_of_column), persistent=False)
        self.frequency_window: float | None = None
        # NeRF's and mip-NeRF's LLFF regulariser, set by the trainer: N(0, density_noise^2) added to
        # the density pre-activation in training passes (``self.training``), drawn from noise_generator.
        self.density_noise = 0.0
        self.noise_generator: torch.Generator | None = None

    def forward(
        self,
        x: torch.Tensor,
        d: torch.Tensor,
        ray_indices: torch.Tensor | None = None,
        num_rays: int | None = None,
        offsets: torch.Tensor | None = None,
        ray_directions: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Density and colour at sample points.

        Args:
            x: positions ``(R, S, 3)``, or packed ``(N, 3)``.
            d: unit view directions ``(R, S, 3)`` or ``(R, 1, 3)``; ``(N, 3)`` when packed, or None
                with ``ray_directions``.
            ray_indices: packed layout only, ``(N,)`` int64 ray of each sample (SE's squeeze).
            num_rays: number of rays ``ray_indices`` index (default: its max + 1, a GPU sync;
                ``ray_directions``' length when given).
            offsets: packed layout only, ``(R+1,)`` int64 CSR offsets: ray r owns samples
                ``offsets[r]:offsets[r+1]`` (SE's squeeze by the fused ops; used instead of
                ``ray_indices`` when both are given). Values are not checked (a GPU sync).
            ray_directions: packed layout only, instead of ``d``: ``(R, 3)`` unit direction of each
                ray, with ``offsets`` or ``ray_indices``; the view branch then runs once per ray
                and is spread to the ray's samples.

        Returns:
            sigma ``x.shape[:-1]`` non-negative, rgb ``(*x.shape[:-1], 3)`` in [0, 1], in ``x``'s dtype
            (float32 under autocast, whose low precision stays inside the MLP).
        """
        d, num_rays = _check_inputs(x, d, ray_indices, offsets, ray_directions, num_rays)
        if d is None and ray_directions is None:
            raise ValueError("d is required (or ray_directions, for packed samples with a layout)")
        self._check_matches_parameters(x)
        direction, trunk_direction, spread = self._directions(x, d, ray_indices, offsets, ray_directions)
        trunk = self._trunk_features(x, trunk_direction)
        gated = self._gated(trunk, ray_indices, num_rays, offsets)
        feature, raw = self._head(gated)
        if not self.cfg.se_gates_density and gated is not trunk:
            raw = self._density_logit(trunk)
        sigma = self._activate_density(self._perturbed(raw), x.dtype)
        view_term = spread(self.view_direction(self.direction_mixer(direction)))  # per ray when d is
        hidden = torch.relu(self._linear(self.view_feature, feature) + view_term)
        rgb = torch.sigmoid(self._linear(self.rgb, hidden).to(x.dtype))
        return sigma, rgb

    def density(
        self,
        x: torch.Tensor,
        d: torch.Tensor | None = None,
        ray_indices: torch.Tensor | None = None,
        num_rays: int | None = None,
        offsets: torch.Tensor | None = None,
        ray_directions: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Only ``sigma`` (skips the colour branch), e.g. for occupancy-grid updates. ``d`` (or
        ``ray_directions``) is needed only when ``cfg.mlca_concat_direction`` makes the density
        view-dependent; the other arguments are those of :meth:`forward`."""
        d, num_rays = _check_inputs(x, d, ray_indices, offsets, ray_directions, num_rays)
        self._check_matches_parameters(x)
        trunk_direction = None
        if self.cfg.mlca_concat_direction:
            _, trunk_direction, _ = self._directions(x, d, ray_indices, offsets, ray_directions)
        features = self._trunk_features(x, trunk_direction)
        if self.cfg.se_gates_density:
            features = self._gated(features, ray_indices, num_rays, offsets)
        return self._activate_density(self._density_logit(features), x.dtype)

    def set_frequency_window(self, alpha: float | None) -> None:
        """Coarse-to-fine positional encoding of positions (Nerfies' window; FreeNeRF's frequency
        regularisation on few views): octave k of PE(x) is scaled by ``(1 - cos(pi c)) / 2`` with
        ``c = clamp(alpha - k, 0, 1)``, so ``alpha = 0`` leaves x alone and ``alpha >= pos_freqs``
        weights every octave 1. ``None``: the full encoding (the default, and what a loaded model
        uses). Directions are not windowed."""
        if alpha is None or alpha >= self.cfg.pos_freqs:
            if self.frequency_window is not None:
                self.octave_weights.fill_(1.0)
            self.frequency_window = None
            return
        if not (math.isfinite(alpha) and alpha >= 0):
            raise ValueError(f"alpha must be finite and >= 0, got {alpha}")
        with torch.no_grad():
            opened = (alpha - self.octave_of_column).clamp_(0, 1)
            self.octave_weights.copy_((1 - torch.cos(math.pi * opened)) / 2)
        self.frequency_window = float(alpha)

    def _check_matches_parameters(self, x: torch.Tensor) -> None:
        """x must live where the weights do, in their dtype unless autocast picks the matmul dtype."""
        weight = self.head.weight
        if x.device != weight.device:
            raise ValueError(f"x is on {x.device} but the model's parameters are on {weight.device}")
        if x.dtype != weight.dtype and not torch.is_autocast_enabled(x.device.type):
            raise TypeError(f"x has dtype {x.dtype} but the model's parameters are {weight.dtype} "
                            f"(convert one of them, or run under torch.autocast)")

    def _encode_direction(self, d: torch.Tensor) -> torch.Tensor:
        return positional_encoding(d, self.cfg.dir_freqs, scale=self.cfg.pe_scale, backend=self.cfg.backend)

    def _directions(self, x, d, ray_indices, offsets, ray_directions):
        """PE of the directions for the view branch, the same per sample for the trunk (Eq. 7 only;
        else None), and what takes the view branch's rows to the samples (per-ray rows of
        ``ray_directions`` spread, or nothing to do)."""
        if ray_directions is None:
            direction = None if d is None else self._encode_direction(d)
            return direction, direction if self.cfg.mlca_concat_direction else None, lambda rows: rows

        def spread(rows: torch.Tensor) -> torch.Tensor:
            return spread_to_samples(rows, x.shape[0], offsets, ray_indices)

        direction = self._encode_direction(ray_directions)
        return direction, spread(direction) if self.cfg.mlca_concat_direction else None, spread

    def _trunk_features(self, x: torch.Tensor, direction: torch.Tensor | None) -> torch.Tensor:
        """The trunk's output at ``x`` (before SE)."""
        cfg = self.cfg
        normalised = (x - self.scene_center.to(x.dtype)) / cfg.scene_scale
        encoded = positional_encoding(normalised, cfg.pos_freqs, scale=cfg.pe_scale, backend=cfg.backend)
        if self.frequency_window is not None:
            encoded = encoded * self.octave_weights.to(encoded.dtype)
        if cfg.mlca_concat_direction:
            if direction is None:
                raise ValueError("d is required when cfg.mlca_concat_direction (density depends on it)")
            encoded = torch.cat([encoded, direction.expand(*encoded.shape[:-1], -1)], dim=-1)
        encoded = self.position_mixer(encoded)
        if torch.is_autocast_enabled(encoded.device.type):
            # one cast for both uses (first layer, skip): each is a pass, and one more in the backward
            encoded = encoded.to(torch.get_autocast_dtype(encoded.device.type))
        h = encoded
        for i, layer in enumerate(self.trunk):
            if i in cfg.skips:
                h = torch.cat([encoded.to(h.dtype), h], dim=-1)
            h = linear_relu(h, layer.weight, layer.bias, backend=cfg.backend)
        return h

    def _gated(self, features: torch.Tensor, ray_indices: torch.Tensor | None, num_rays: int | None,
               offsets: torch.Tensor | None) -> torch.Tensor:
        """SE's gating of the trunk's ``features`` over each ray (``features`` itself without SE)."""
        return features if self.se is None else self.se(features, ray_indices, num_rays, offsets)

    def _density_logit(self, features: torch.Tensor) -> torch.Tensor:
        """The head's density row alone: ``(..., width) -> (...)``."""
        return F.linear(features, self.head.weight[:1], self.head.bias[:1])[..., 0]

    def _head(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The feature ``(..., width)`` and the density pre-activation ``(...)`` in one GEMM whose
        output rows are padded to a multiple of 8 values: cuBLAS's fast kernels need 16-byte aligned
        rows, which the head's 1 + width outputs (and the feature view into them) are not. Split, not
        sliced: the backward is then one cat, not a zero-filled copy per slice and their sum."""
        weight, bias, width = self.head.weight, self.head.bias, self.cfg.width
        pad = -(width + 1) % 8
        weight = torch.cat([weight[1:], weight[:1], weight.new_zeros(pad, weight.shape[1])])
        bias = torch.cat([bias[1:], bias[:1], bias.new_zeros(pad)])
        out = linear(features, weight, bias, backend=self.cfg.backend)
        feature, raw, _ = out.split([width, 1, pad], dim=-1)
        return feature, raw.squeeze(-1)

    def _linear(self, layer: nn.Linear, x: torch.Tensor) -> torch.Tensor:
        """``layer(x)`` with its bias gradient as a GEMV (ops.linear), not a column reduction."""
        return linear(x, layer.weight, layer.bias, backend=self.cfg.backend)

    def _perturbed(self, raw: torch.Tensor) -> torch.Tensor:
        """``raw`` with the training passes' density noise (float32 from there), else ``raw`` itself."""
        if not (self.training and self.density_noise > 0):
            return raw
        raw = raw.float()
        noise = torch.randn(raw.shape, device=raw.device, generator=self.noise_generator)
        return raw + self.density_noise * noise

    def _activate_density(self, raw: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        raw = raw.to(dtype)
        if self.cfg.density_activation == "relu":
            return torch.relu(raw)
        return F.softplus(raw + self.cfg.density_shift)


def _mixer(cfg: ModelConfig, num_tokens: int, mixes: bool) -> nn.Module:
    return MLCA(num_tokens, 3, cfg.mlca_channels, cfg.backend) if mixes else nn.Identity()


def _channels(mixer: nn.Module) -> int:
    """Values per token of a mixer's output: MLCA's channels, or the 3 coordinates it would lift."""
    return mixer.channels if isinstance(mixer, MLCA) else 3


def _init_relu_layer(layer: nn.Linear) -> None:
    nn.init.kaiming_normal_(layer.weight, nonlinearity="relu")
    if layer.bias is not None:
        nn.init.zeros_(layer.bias)


def _check_inputs(
    x: torch.Tensor,
    d: torch.Tensor | None,
    ray_indices: torch.Tensor | None,
    offsets: torch.Tensor | None,
    ray_directions: torch.Tensor | None = None,
    num_rays: int | None = None,
) -> tuple[torch.Tensor | None, int | None]:
    """Validate the layouts (ValueError/TypeError naming the argument); returns ``d``, with an
    expanded per-ray view ``(R, S, 3)`` (stride 0 along S) narrowed to ``(R, 1, 3)``, and the
    number of rays (``ray_directions``' length when given, else ``num_rays``)."""
    check_floating("x", x)
    if x.dim() not in (2, 3) or x.shape[-1] != 3:
        raise ValueError(f"x must have shape (R, S, 3) or (N, 3), got {tuple(x.shape)}")
    if ray_indices is not None:
        check_same_device(x=x, ray_indices=ray_indices)
        if x.dim() != 2:
            raise ValueError("ray_indices is only for packed samples x (N, 3)")
        if ray_indices.dtype not in (torch.int32, torch.int64) or ray_indices.shape != x.shape[:1]:
            raise ValueError(
                f"ray_indices must be an int64 tensor of shape {(x.shape[0],)}, "
                f"got {ray_indices.dtype} {tuple(ray_indices.shape)}"
            )
    if offsets is not None:
        check_tensor("offsets", offsets)
        check_same_device(x=x, offsets=offsets)
        if x.dim() != 2:
            raise ValueError("offsets is only for packed samples x (N, 3)")
        check_offsets("offsets", offsets, x.shape[0], check_values=False)
    if ray_directions is not None:
        _check_ray_directions(x, d, ray_indices, offsets, ray_directions, num_rays)
        num_rays = ray_directions.shape[0]
    if d is None:
        return None, num_rays
    check_floating("d", d)
    check_same_device(x=x, d=d)
    if x.dim() == 2:
        if d.shape != x.shape:
            raise ValueError(f"d must have shape {tuple(x.shape)} like x, got {tuple(d.shape)}")
        return d, num_rays
    R, S, _ = x.shape
    if d.dim() != 3 or d.shape[0] != R or d.shape[1] not in (1, S) or d.shape[2] != 3:
        raise ValueError(f"d must have shape {(R, S, 3)} or {(R, 1, 3)}, got {tuple(d.shape)}")
    return (d[:, :1] if d.shape[1] > 1 and d.stride(1) == 0 else d), num_rays


def _check_ray_directions(x, d, ray_indices, offsets, ray_directions, num_rays) -> None:
    """``ray_directions (R, 3)``: packed samples only, instead of ``d``, with a layout that maps
    samples to rays and R rays (offsets' R, or ``num_rays``)."""
    check_floating("ray_directions", ray_directions)
    check_same_device(x=x, ray_directions=ray_directions)
    if x.dim() != 2 or d is not None:
        raise ValueError("ray_directions is only for packed samples x (N, 3), instead of d (pass d=None)")
    if offsets is None and ray_indices is None:
        raise ValueError("ray_directions needs offsets or ray_indices (which samples belong to which ray)")
    rays = offsets.shape[0] - 1 if offsets is not None else num_rays
    if ray_directions.dim() != 2 or ray_directions.shape[1] != 3 or (
            rays is not None and ray_directions.shape[0] != rays):
        want = "(R, 3)" if rays is None else str((rays, 3))
        raise ValueError(f"ray_directions must have shape {want}, one row per ray, got {tuple(ray_directions.shape)}")
