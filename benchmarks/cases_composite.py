"""Benchmark cases for composite and composite_packed (volume rendering), forward and
forward+backward.

Sizes: dense, CPU R=4096 rays x S=192 samples (64 coarse + 128 fine), CUDA R=65536 x 192; packed
(after occupancy-grid marching), the same R with ragged counts floor(65 u^2) in 0..64 (mean ~21,
N ~ 1.4M on CUDA; ~2% of rays empty). C=3, float32, one shared background. The fwd+bwd case is a
training step: the loss reads color, depth and opacity; sigmas and rgbs get gradients (sample
bounds come from the sampler and background is a constant, so they need none; weights feed
resampling detached, so they get no gradient either).
"""

from __future__ import annotations

import torch

from benchmarks.harness import Case, Variant
from mixer_nerf.ops.composite import composite, composite_packed
from mixer_nerf.ops.composite_reference import composite_packed_reference, composite_reference

C = 3


def make_inputs(R: int, S: int, device: torch.device, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator(device=device).manual_seed(seed)
    deltas = 0.005 + 0.02 * torch.rand(R, S, generator=gen, device=device)
    edges = torch.cat([torch.full((R, 1), 2.0, device=device), 2.0 + deltas.cumsum(1)], dim=1)
    return {
        "sigmas": 30 * torch.rand(R, S, generator=gen, device=device) ** 4,  # mostly thin, some opaque
        "rgbs": torch.rand(R, S, C, generator=gen, device=device),
        "t_starts": edges[:, :-1].contiguous(),
        "t_ends": edges[:, 1:].contiguous(),
        "background": torch.rand(C, generator=gen, device=device),
    }


def make_packed_inputs(R: int, device: torch.device, seed: int = 0) -> dict[str, torch.Tensor]:
    """The dense rays of make_inputs(R, 64) keeping a ragged prefix of each: ray r keeps its first
    floor(65 u_r^2) samples."""
    dense = make_inputs(R, 64, device, seed)
    gen = torch.Generator(device=device).manual_seed(seed + 1)
    counts = (65 * torch.rand(R, generator=gen, device=device) ** 2).long().clamp_max(64)
    keep = torch.arange(64, device=device) < counts[:, None]
    packed = {k: v[keep].contiguous() for k, v in dense.items() if k != "background"}
    packed["offsets"] = torch.nn.functional.pad(counts.cumsum(0), (1, 0))
    packed["background"] = dense["background"]
    return packed


def nerfacc_composite(sigmas, rgbs, t_starts, t_ends, background):
    """The same outputs from nerfacc 0.5.3's batched API (a ``(R, S)`` torch path)."""
    import nerfacc

    weights, _, _ = nerfacc.render_weight_from_density(t_starts, t_ends, sigmas)
    color = nerfacc.accumulate_along_rays(weights, rgbs)
    opacity = nerfacc.accumulate_along_rays(weights, None)
    depth = nerfacc.accumulate_along_rays(weights, (0.5 * (t_starts + t_ends)).unsqueeze(-1))
    color = color + (1 - opacity) * background
    return color, depth.squeeze(-1), opacity.squeeze(-1), weights


def nerfacc_composite_packed(sigmas, rgbs, t_starts, t_ends, offsets, background):
    """The same outputs from nerfacc 0.5.3's packed API (``ray_indices``)."""
    import nerfacc

    n_rays = offsets.numel() - 1
    ray_indices = torch.repeat_interleave(
        torch.arange(n_rays, device=offsets.device), offsets.diff(), output_size=sigmas.numel()
    )
    weights, _, _ = nerfacc.render_weight_from_density(
        t_starts, t_ends, sigmas, ray_indices=ray_indices, n_rays=n_rays
    )
    color = nerfacc.accumulate_along_rays(weights, rgbs, ray_indices, n_rays)
    opacity = nerfacc.accumulate_along_rays(weights, None, ray_indices, n_rays)
    depth = nerfacc.accumulate_along_rays(weights, (0.5 * (t_starts + t_ends))[:, None], ray_indices, n_rays)
    color = color + (1 - opacity) * background
    return color, depth.squeeze(-1), opacity.squeeze(-1), weights


def _implementations(op, reference, peer, device: torch.device) -> dict:
    impls = {
        "kernel": lambda *a: tuple(op(*a, backend="kernel", check_values=False)),
        "ours, defaults": lambda *a: tuple(op(*a)),  # what a user calls: values checked
        "torch": lambda *a: tuple(op(*a, backend="torch", check_values=False)),
    }
    if device.type == "cuda":
        impls["torch.compile"] = torch.compile(reference)
        try:
            import nerfacc  # noqa: F401

            impls["nerfacc"] = peer
        except ImportError:
            pass
    return impls


def implementations(device: torch.device) -> dict:
    return _implementations(composite, composite_reference, nerfacc_composite, device)


def packed_implementations(device: torch.device) -> dict:
    return _implementations(composite_packed, composite_packed_reference, nerfacc_composite_packed, device)


def _layout(inputs: dict) -> tuple[int, int, int]:
    """(rays R, samples N, bytes of offsets) of dense or packed inputs."""
    sigmas, offsets = inputs["sigmas"], inputs.get("offsets")
    if offsets is None:
        return sigmas.shape[0], sigmas.numel(), 0
    return offsets.numel() - 1, sigmas.numel(), offsets.numel() * offsets.element_size()


def _cast(inputs: dict, dtype) -> dict:
    return {k: v.to(dtype) if dtype is not None and v.is_floating_point() else v for k, v in inputs.items()}


def forward_case(op: str, size: str, inputs: dict, impls: dict, reference) -> Case:
    def run(fn, dtype=None):
        with torch.no_grad():
            return fn(*_cast(inputs, dtype).values())

    R, N, offset_bytes = _layout(inputs)
    reads = N * (3 + C) + C
    writes = R * C + 2 * R + N
    return Case(
        op=op,
        mode="fwd",
        size=size,
        variants=[Variant(name, lambda fn=fn: run(fn)) for name, fn in impls.items()],
        truth=lambda: run(reference, torch.float64),
        min_bytes=(reads + writes) * inputs["sigmas"].element_size() + offset_bytes,
    )


def training_case(op: str, size: str, inputs: dict, impls: dict, reference) -> Case:
    R, N, offset_bytes = _layout(inputs)
    device = inputs["sigmas"].device
    gen = torch.Generator(device=device).manual_seed(1)
    upstream = [torch.randn(*shape, generator=gen, device=device) for shape in ((R, C), (R,), (R,))]

    def step(fn, dtype=None):
        cast = _cast(inputs, dtype)
        leaves = [cast.pop("sigmas").detach().requires_grad_(), cast.pop("rgbs").detach().requires_grad_()]
        out = fn(*leaves, *cast.values())  # t_starts, t_ends, [offsets,] background
        grads = torch.autograd.grad(out[:3], leaves, [u.to(out[0].dtype) for u in upstream])
        return (*[o.detach() for o in out], *grads)

    forward = N * (3 + C) + C + R * C + 2 * R + N
    # backward: read grad color/depth/opacity, sigmas, t_starts, t_ends, rgbs, background (and the
    # offsets again); write grad sigmas and grad rgbs.
    backward = R * C + 2 * R + N * (3 + C) + C + N * (1 + C)
    return Case(
        op=op,
        mode="fwd+bwd",
        size=size,
        variants=[Variant(name, lambda fn=fn: step(fn)) for name, fn in impls.items()],
        truth=lambda: step(reference, torch.float64),
        min_bytes=(forward + backward) * inputs["sigmas"].element_size() + 2 * offset_bytes,
    )


def cases(device: torch.device) -> list[Case]:
    R, S = (65536, 192) if device.type == "cuda" else (4096, 192)
    dense, impls = make_inputs(R, S, device), implementations(device)
    packed, packed_impls = make_packed_inputs(R, device), packed_implementations(device)
    dense_size = f"R={R} S={S} C={C}"
    packed_size = f"R={R} N={packed['sigmas'].numel()} (0..64 per ray) C={C}"
    return [
        forward_case("composite", dense_size, dense, impls, composite_reference),
        training_case("composite", dense_size, dense, impls, composite_reference),
        forward_case("composite_packed", packed_size, packed, packed_impls, composite_packed_reference),
        training_case("composite_packed", packed_size, packed, packed_impls, composite_packed_reference),
    ]
