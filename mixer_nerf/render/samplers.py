"""Sampler stage: sample depths along rays, and the intervals each sample stands for.

Coarse samples are stratified: ``[near, far]`` is cut into S equal bins (in depth, or in
disparity ``1/t`` with ``lindisp``) and each sample is drawn uniformly in its bin (``stratified``)
or placed at the bin's centre (deterministic). Fine samples come from
:func:`mixer_nerf.ops.hierarchical_samples`, called by the renderer.

Intervals (``t_starts``, ``t_ends`` for compositing), two conventions:
  * ``last_delta=None`` (default), midpoint intervals: sample i stands for
    ``[(t_{i-1} + t_i) / 2, (t_i + t_{i+1}) / 2]``, the first starting at ``near`` and the last
    ending at ``far``. They tile ``[near, far]`` exactly, each sample sits inside its interval
    (midpoint quadrature of the rendering integral), and light that passes ``far`` shows the
    background. This is the right choice for a density that is never exactly zero (softplus): a
    last interval 1e10 long would turn the faintest density at the last sample into an opaque wall
    that hides the background.
  * ``last_delta=<float>``, NeRF's intervals: ``[t_i, t_{i+1}]`` with the last one ``last_delta``
    long (``1e10`` reproduces NeRF: everything behind the last sample is opaque).
"""

from __future__ import annotations

import torch


def stratified_depths(
    near: torch.Tensor,
    far: torch.Tensor,
    num_samples: int,
    stratified: bool = True,
    lindisp: bool = False,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """near, far ``(R, 1)`` -> sorted depths ``(R, num_samples)`` in ``[near, far]``, one per bin."""
    num_rays = near.shape[0]
    offsets = (
        torch.rand(num_rays, num_samples, generator=generator, device=near.device, dtype=near.dtype)
        if stratified
        else near.new_full((1, num_samples), 0.5)
    )
    fraction = (torch.arange(num_samples, device=near.device, dtype=near.dtype) + offsets) / num_samples
    # a + (b - a) f rounds monotonically in f (torch.lerp switches formulas at f = 1/2 and can
    # break sortedness by an ulp there).
    if lindisp:
        inv_near = torch.reciprocal(near)
        return torch.reciprocal(inv_near + (torch.reciprocal(far) - inv_near) * fraction)
    return near + (far - near) * fraction


def sample_intervals(
    depths: torch.Tensor, near: torch.Tensor, far: torch.Tensor, last_delta: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sorted depths ``(R, S)``, near/far ``(R, 1)`` -> ``t_starts, t_ends`` ``(R, S)`` (see module
    docstring for the two conventions)."""
    if last_delta is not None:
        return depths, torch.cat([depths[:, 1:], depths[:, -1:] + last_delta], dim=-1)
    mids = 0.5 * (depths[:, 1:] + depths[:, :-1])
    num_rays = depths.shape[0]
    t_starts = torch.cat([near.expand(num_rays, 1), mids], dim=-1)
    t_ends = torch.cat([mids, far.expand(num_rays, 1)], dim=-1)
    return t_starts, t_ends
