"""The proposal sampler, for scenes an occupancy grid cannot prune (forward-facing in NDC, unbounded
360 captures): small proposal density networks, trained with an interval-overlap loss, resample
each ray in rounds so that the main field is evaluated at few samples near what it sees
(mip-NeRF 360's online distillation; nerfacc calls it ``PropNetEstimator``).

    uniform edges -> proposal 1 -> weights -> sample_pdf -> proposal 2 -> ... -> sample_pdf
    -> ``num_samples`` intervals for the main field

Positions along a ray are placed in a spacing coordinate ``s`` in [0, 1]: ``t`` linear in ``s``
(NDC, bounded) or ``1/t`` linear in ``s`` (``"disparity"``: unbounded scenes, needs ``near > 0``).
Sampling runs without gradient; the proposal networks get theirs from :func:`proposal_loss`, which
asks each round's weights to bound the main field's (detached) weights from above, at the steps
:func:`proposal_update_due` picks.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from ...ops import composite, sample_pdf
from ..volume import RayBundleResult, composite_samples, query_field

SPACINGS = ("linear", "disparity")
JITTERS = ("per_sample", "per_ray")
RESIDUALS = ("drop", "last")
INTERVALS = ("drawn", "between")
UPDATE_RAMP_STEPS = 1000
"""Steps over which :func:`proposal_update_due`'s interval grows from 1 to its final value."""


def proposal_update_due(step: int, every: int) -> bool:
    """Whether the proposal networks learn at ``step``: every step at first, then every ``every``
    steps from step :data:`UPDATE_RAMP_STEPS`, the interval growing linearly in between (nerfacc's
    ``get_proposal_requires_grad_fn`` schedule, decided from the step alone so a resumed run
    keeps it)."""
    interval = 1 + int(min(step / UPDATE_RAMP_STEPS, 1.0) * (every - 1))
    return step % interval == 0


@dataclass(frozen=True)
class ProposalOptions:
    """Attributes:
    samples_per_round: samples each proposal network is evaluated at, one entry per network.
    num_samples: samples per ray of the main field.
    spacing: ``"linear"`` or ``"disparity"`` (see the module docstring).
    weight_padding: added to every proposal weight before resampling, so that no part of the
        ray is ever given up entirely (0: none, the trainer's default).
    jitter: stratified positions ``u`` jittered all of a ray's by one offset (``"per_ray"``:
        equal steps in ``u``, as nerfacc's sampler; the default) or each by itself (``"per_sample"``).
    residual: what becomes of a ray's transmittance left after its last interval (1 - opacity)
        in each round and in the loss's target: ``"drop"`` it (a round's PDF is its weights
        normalised; the default) or add it to the last interval's weight (``"last"``: a CDF that
        ends at 1, so a ray its networks see as still transparent is sampled towards its far end
        too; nerfacc's estimator, whose CDF is 1 minus the exclusive transmittance, then 1).
    intervals: how a round's ``n`` intervals come from its PDF: ``"drawn"`` draws their ``n + 1``
        edges (the default), ``"between"`` draws ``n`` positions and puts the edges halfway between
        neighbours, the first and last half a spacing beyond, within the previous round's span
        (nerfacc's estimator): its edges reach the ray's first and last quantile, where drawn
        edges stop ~1/(n + 1) of the mass short of them.
    """

    samples_per_round: tuple[int, ...] = (128, 64)
    num_samples: int = 48
    spacing: str = "linear"
    weight_padding: float = 0.0
    jitter: str = "per_ray"
    residual: str = "drop"
    intervals: str = "drawn"

    def __post_init__(self) -> None:
        if not self.samples_per_round or any(n < 1 for n in self.samples_per_round):
            raise ValueError(f"samples_per_round must be positive counts, got {self.samples_per_round}")
        if self.num_samples < 1:
            raise ValueError(f"num_samples must be positive, got {self.num_samples}")
        if self.spacing not in SPACINGS:
            raise ValueError(f"spacing must be one of {SPACINGS}, got {self.spacing!r}")
        if not self.weight_padding >= 0:
            raise ValueError(f"weight_padding must be >= 0, got {self.weight_padding}")
        if self.jitter not in JITTERS:
            raise ValueError(f"jitter must be one of {JITTERS}, got {self.jitter!r}")
        if self.residual not in RESIDUALS:
            raise ValueError(f"residual must be one of {RESIDUALS}, got {self.residual!r}")
        if self.intervals not in INTERVALS:
            raise ValueError(f"intervals must be one of {INTERVALS}, got {self.intervals!r}")


class ProposalRound(NamedTuple):
    edges: torch.Tensor  # (R, n + 1) interval edges in s
    weights: torch.Tensor  # (R, n) the proposal network's weights (with gradient when training)


class ProposalSamples(NamedTuple):
    t_starts: torch.Tensor  # (R, N) intervals of the main field's samples
    t_ends: torch.Tensor  # (R, N)
    edges: torch.Tensor  # (R, N + 1) the same intervals' edges in s
    rounds: tuple[ProposalRound, ...]


class ProposalSampler(nn.Module):
    """``networks``: one density field per round (``net.density(x (R, n, 3)) -> (R, n)``); they
    are this module's parameters (and checkpoint with it)."""

    def __init__(self, networks: Sequence[nn.Module], options: ProposalOptions = ProposalOptions()) -> None:
        super().__init__()
        if len(networks) != len(options.samples_per_round):
            raise ValueError(f"{len(networks)} proposal networks for {len(options.samples_per_round)} rounds")
        self.networks = nn.ModuleList(networks)
        self.options = options

    def sample(
        self,
        rays_o: torch.Tensor,
        rays_d: torch.Tensor,
        near: float,
        far: float,
        *,
        stratified: bool,
        generator: torch.Generator | None = None,
        backend: str = "auto",
    ) -> ProposalSamples:
        """Intervals for the main field along rays ``(R, 3)`` in ``[near, far]`` (depths in units
        of ``|rays_d|``). The rounds' weights carry gradient to the networks if grad is enabled."""
        opts = self.options
        if opts.spacing == "disparity" and not near > 0:
            raise ValueError(f"disparity spacing needs near > 0, got {near}")
        if not near < far < float("inf"):
            raise ValueError(f"need near < far < inf, got near={near}, far={far}")
        num_rays = rays_o.shape[0]
        # made on the device: a tensor from a Python list is a host-to-device copy the host waits on
        edges = torch.linspace(0.0, 1.0, 2, device=rays_o.device, dtype=rays_o.dtype).expand(num_rays, 2)
        weights = torch.ones(num_rays, 1, device=rays_o.device, dtype=rays_o.dtype)
        norm = torch.linalg.vector_norm(rays_d, dim=-1, keepdim=True)
        rounds = []
        for net, n in zip(self.networks, opts.samples_per_round, strict=True):
            edges = self._intervals(edges, weights, n, stratified, generator, backend)
            t = self._to_t(edges, near, far)
            mids = 0.5 * (t[:, 1:] + t[:, :-1])
            sigma = net.density(rays_o[:, None, :] + mids[..., None] * rays_d[:, None, :]).float() * norm
            weights = self.target_weights(_weights(sigma, t[:, :-1], t[:, 1:], backend))
            rounds.append(ProposalRound(edges, weights))
        edges = self._intervals(edges, weights, opts.num_samples, stratified, generator, backend)
        t = self._to_t(edges, near, far)
        return ProposalSamples(t[:, :-1], t[:, 1:], edges, tuple(rounds))

    def target_weights(self, weights: torch.Tensor) -> torch.Tensor:
        """Volume-rendering weights ``(R, n)`` as this sampler's options resample them and as
        :func:`proposal_loss` takes the main field's: with ``residual="last"``, the last
        interval's weight takes the ray's remaining transmittance (differentiably)."""
        if self.options.residual == "drop":
            return weights
        remaining = (1 - weights.sum(-1, keepdim=True)).clamp_min(0)
        return torch.cat([weights[:, :-1], weights[:, -1:] + remaining], dim=-1)

    @torch.no_grad()
    def _intervals(self, edges, weights, n, stratified, generator, backend) -> torch.Tensor:
        """Edges ``(R, n + 1)`` of ``n`` intervals drawn from the PDF of ``weights`` on ``edges``."""
        if self.options.intervals == "drawn":
            return self._resample(edges, weights, n + 1, stratified, generator, backend)
        x = self._resample(edges, weights, n, stratified, generator, backend)
        lo, hi = edges[:, :1], edges[:, -1:]
        if n == 1:
            return torch.cat([lo, hi], dim=-1)
        first = torch.maximum(1.5 * x[:, :1] - 0.5 * x[:, 1:2], lo)
        last = torch.minimum(1.5 * x[:, -1:] - 0.5 * x[:, -2:-1], hi)
        return torch.cat([first, 0.5 * (x[:, 1:] + x[:, :-1]), last], dim=-1)

    def _resample(self, edges, weights, count, stratified, generator, backend) -> torch.Tensor:
        u = None
        if stratified and self.options.jitter == "per_ray":
            offset = torch.rand(edges.shape[0], 1, device=edges.device, dtype=torch.float32, generator=generator)
            u = (torch.arange(count, device=edges.device, dtype=torch.float32) + offset) / count
        return sample_pdf(edges.contiguous(), weights.detach().contiguous(), count, u=u,
                          deterministic=not stratified, weight_padding=self.options.weight_padding,
                          generator=generator, backend=backend, check_values=False)

    def _to_t(self, s: torch.Tensor, near: float, far: float) -> torch.Tensor:
        if self.options.spacing == "linear":
            return near + (far - near) * s
        return torch.reciprocal(1 / near + (1 / far - 1 / near) * s)


def _weights(sigma, t_starts, t_ends, backend) -> torch.Tensor:
    """Volume-rendering weights ``(R, n)`` of densities on intervals, differentiable in sigma."""
    dummy = sigma.new_zeros(*sigma.shape, 1)
    return composite(sigma, dummy, t_starts.contiguous(), t_ends.contiguous(), backend=backend,
                     check_values=False)[3]


def proposal_loss(rounds: Sequence[ProposalRound], edges: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360's interval-overlap loss: for each interval of the main field (``edges``
    ``(R, N + 1)`` in s, ``weights`` ``(R, N)``, detached here), the summed weight of the proposal
    intervals overlapping it must be at least its weight; the shortfall is penalised. Mean over
    rays, summed over rounds."""
    target = weights.detach()
    lo_t, hi_t = edges[:, :-1].contiguous(), edges[:, 1:].contiguous()
    total = weights.new_zeros(())
    for r in rounds:
        n = r.weights.shape[-1]
        cumulative = F.pad(torch.cumsum(r.weights, dim=-1), (1, 0))  # (R, n + 1)
        prop_edges = r.edges.contiguous()
        first = (torch.searchsorted(prop_edges, lo_t, right=True) - 1).clamp(0, n)
        last = torch.searchsorted(prop_edges, hi_t, right=False).clamp(0, n)
        outer = cumulative.gather(-1, last) - cumulative.gather(-1, first)
        shortfall = (target - outer).clamp_min(0)
        total = total + (shortfall.square() / (target + 1e-7)).sum(-1).mean()
    return total


def render_rays_proposal(
    field: nn.Module,
    proposal: ProposalSampler,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    near: float,
    far: float,
    *,
    stratified: bool = True,
    background: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
    backend: str = "auto",
    train_proposal: bool = True,
) -> tuple[RayBundleResult, ProposalSamples]:
    """Render rays ``(R, 3)`` through ``field`` at the intervals ``proposal`` picks (each sample at
    its interval's midpoint): the result (differentiable through the field) and the samples, whose
    rounds feed :func:`proposal_loss` (with gradient to the proposal networks only where
    ``train_proposal``)."""
    with torch.set_grad_enabled(train_proposal and torch.is_grad_enabled()):
        samples = proposal.sample(rays_o, rays_d, near, far, stratified=stratified, generator=generator,
                                  backend=backend)
    mids = 0.5 * (samples.t_starts + samples.t_ends)
    sigmas, rgbs = query_field(field, rays_o, rays_d, mids)
    bg = None if background is None else background.to(rays_o.dtype)
    return composite_samples(sigmas, rgbs, samples.t_starts, samples.t_ends, bg, backend), samples
