"""Benchmark cases for composite (volume rendering), forward and forward+backward.

Sizes: CPU R=4096 rays x S=192 samples (64 coarse + 128 fine), CUDA R=65536 x 192; C=3, float32,
one shared background. The fwd+bwd case is a training step: the loss reads color, depth and
opacity; sigmas and rgbs get gradients (sample bounds come from the sampler and background is a
constant, so they need none; weights feed resampling detached, so they get no gradient either).
"""

from __future__ import annotations

import torch

from benchmarks.harness import Case, Variant
from mixer_nerf.ops.composite import composite
from mixer_nerf.ops.composite_reference import composite_reference

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


def nerfacc_composite(sigmas, rgbs, t_starts, t_ends, background):
    """The same outputs from nerfacc 0.5.3's batched API (a ``(R, S)`` torch path)."""
    import nerfacc

    weights, _, _ = nerfacc.render_weight_from_density(t_starts, t_ends, sigmas)
    color = nerfacc.accumulate_along_rays(weights, rgbs)
    opacity = nerfacc.accumulate_along_rays(weights, None)
    depth = nerfacc.accumulate_along_rays(weights, (0.5 * (t_starts + t_ends)).unsqueeze(-1))
    color = color + (1 - opacity) * background
    return color, depth.squeeze(-1), opacity.squeeze(-1), weights


def implementations(device: torch.device) -> dict:
    impls = {
        "kernel": lambda *a: tuple(composite(*a, backend="kernel", check_values=False)),
        "torch": lambda *a: tuple(composite(*a, backend="torch", check_values=False)),
    }
    if device.type == "cuda":
        impls["torch.compile"] = torch.compile(composite_reference)
        try:
            import nerfacc  # noqa: F401

            impls["nerfacc"] = nerfacc_composite
        except ImportError:
            pass
    return impls


def forward_case(size: str, inputs: dict, impls: dict) -> Case:
    args = list(inputs.values())

    def run(fn):
        with torch.no_grad():
            return fn(*args)

    R, S = inputs["sigmas"].shape
    item = inputs["sigmas"].element_size()
    reads = R * S * (3 + C) + C
    writes = R * C + 2 * R + R * S
    return Case(
        op="composite",
        mode="fwd",
        size=size,
        variants=[Variant(name, lambda fn=fn: run(fn)) for name, fn in impls.items()],
        truth=lambda: run(lambda *a: composite_reference(*[x.double() for x in a])),
        min_bytes=(reads + writes) * item,
    )


def training_case(size: str, inputs: dict, impls: dict) -> Case:
    R, S = inputs["sigmas"].shape
    gen = torch.Generator(device=inputs["sigmas"].device).manual_seed(1)
    upstream = [torch.randn(*shape, generator=gen, device=inputs["sigmas"].device) for shape in ((R, C), (R,), (R,))]

    def step(fn, dtype=None):
        cast = {k: v if dtype is None else v.to(dtype) for k, v in inputs.items()}
        leaves = [cast["sigmas"].detach().requires_grad_(), cast["rgbs"].detach().requires_grad_()]
        out = fn(*leaves, cast["t_starts"], cast["t_ends"], cast["background"])
        grads = torch.autograd.grad(out[:3], leaves, [u.to(out[0].dtype) for u in upstream])
        return (*[o.detach() for o in out], *grads)

    item = inputs["sigmas"].element_size()
    forward = R * S * (3 + C) + C + R * C + 2 * R + R * S
    # backward: read grad color/depth/opacity, sigmas, t_starts, t_ends, rgbs, background;
    # write grad sigmas and grad rgbs.
    backward = R * C + 2 * R + R * S * (3 + C) + C + R * S * (1 + C)
    return Case(
        op="composite",
        mode="fwd+bwd",
        size=size,
        variants=[Variant(name, lambda fn=fn: step(fn)) for name, fn in impls.items()],
        truth=lambda: step(composite_reference, torch.float64),
        min_bytes=(forward + backward) * item,
    )


def cases(device: torch.device) -> list[Case]:
    R, S = (65536, 192) if device.type == "cuda" else (4096, 192)
    inputs = make_inputs(R, S, device)
    impls = implementations(device)
    size = f"R={R} S={S} C={C}"
    return [forward_case(size, inputs, impls), training_case(size, inputs, impls)]
