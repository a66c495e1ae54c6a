"""Error budget of the fused ops: how far each output and gradient is from a float64 truth, for
float32, float16 and bfloat16 inputs, over typical and stress input distributions, next to the
reference path (``backend="torch"``) in the same dtype, and for compositing next to the classic NeRF
formulation ``alpha = 1 - exp(-tau)``, ``T = cumprod(1 - alpha + 1e-10)``.

    python -m benchmarks.error_budget                 # CPU kernels, < 1 minute on 2 cores
    python -m benchmarks.error_budget --device cuda   # CUDA kernels (larger batches)

Writes ``benchmarks/results/error_budget/<device>.md`` and ``.json`` (device ``cpu``, ``h100``, ...)
and prints the table.

Error metric: element-wise relative error ``|y - t| / max(|t|, tiny)``, with ``tiny`` the smallest
normal number of the output dtype (values below it count as zero), except for sample positions,
whose error is relative to the ray's largest |edge| (a sample at 0 on [-1e4, 1e4] is as accurate as
one at 1e4). "max" and "median" are over every element of the distribution; "inf" marks a
non-finite value where the truth is finite. The truth takes the low-precision *inputs* exactly
(upcast to float64), so the errors are those of the computation, not of rounding the inputs.
Gradients are taken for one random upstream gradient (the same for every variant). Values beyond
float16's range are clamped to it before casting (a float16 input cannot be 1e10).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import platform
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from benchmarks.harness import RESULTS, device_tag
from mixer_nerf.ops import composite, hierarchical_samples, positional_encoding, sample_pdf
from mixer_nerf.ops.hierarchical_samples_reference import hierarchical_samples_reference
from mixer_nerf.ops.sample_pdf_reference import sample_pdf_reference

DTYPES = (torch.float32, torch.float16, torch.bfloat16)


@dataclass
class Row:
    op: str
    distribution: str
    quantity: str
    dtype: str
    errors: dict[str, tuple[float, float]]  # variant -> (max, median) relative error


# ---------------------------------------------------------------------------------------------
# Error metric


def relative_errors(
    value: torch.Tensor, truth: torch.Tensor, unit: torch.Tensor | float | None = None
) -> torch.Tensor:
    """Element-wise ``|value - truth| / max(|truth|, floor)``, the floor being half an ulp (of
    value's dtype) of ``unit``: by default the largest |truth| of the row (ray, point), so that
    errors below the resolution of the row's largest entry are not magnified, and at least the
    dtype's smallest normal number. inf where value is non-finite and truth finite; truths that
    are non-finite or beyond the dtype's range (unrepresentable) are left out."""
    info = torch.finfo(value.dtype)
    value, truth = value.double(), truth.double()
    if unit is None:
        unit = truth.abs().amax(dim=-1, keepdim=True) if truth.dim() > 1 else truth.abs()
    floor = torch.clamp(
        torch.as_tensor(unit, dtype=torch.float64, device=truth.device) * info.eps / 2, min=info.tiny
    )
    error = (value - truth).abs() / torch.maximum(truth.abs(), floor)
    error = torch.where(torch.isfinite(value), error, torch.full_like(error, math.inf))
    return error[torch.isfinite(truth) & (truth.abs() <= info.max)]


def position_errors(value: torch.Tensor, truth: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
    """Errors of sample positions relative to the ray's largest |edge| (a sample near 0 on
    [-1e4, 1e4] is as accurate as one near 1e4)."""
    scale = bins.double().abs().amax(dim=1, keepdim=True).clamp_min(torch.finfo(value.dtype).tiny)
    error = (value.double() - truth).abs() / scale
    return torch.where(torch.isfinite(value.double()), error, torch.full_like(error, math.inf)).flatten()


def summarise(errors: torch.Tensor) -> tuple[float, float]:
    if errors.numel() == 0:
        return (0.0, 0.0)
    return float(errors.max()), float(errors.float().median())


# ---------------------------------------------------------------------------------------------
# Input distributions (float64, generated once per distribution; cast per dtype)


def log_uniform(gen: torch.Generator, shape, lo: float, hi: float, device) -> torch.Tensor:
    u = torch.rand(shape, generator=gen, dtype=torch.float64).to(device)
    return 10.0 ** (lo + (hi - lo) * u)


def rand(gen, shape, device) -> torch.Tensor:
    return torch.rand(shape, generator=gen, dtype=torch.float64).to(device)


def zero_some(gen, x: torch.Tensor, fraction: float) -> torch.Tensor:
    return x * (rand(gen, x.shape, x.device) >= fraction)


def cast(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """To ``dtype``, clamping to its finite range; returned as float64 holding exactly those values."""
    limit = torch.finfo(dtype).max
    return x.clamp(-limit, limit).to(dtype).double()


def composite_inputs(name: str, R: int, S: int, gen, device) -> tuple[torch.Tensor, ...]:
    """sigmas, rgbs, t_starts, t_ends, background (3,) of one distribution, float64."""
    if name == "typical":  # a trained NeRF: densities 0.01..100 on [2, 6], jittered intervals
        sigmas = log_uniform(gen, (R, S), -2, 2, device)
        deltas = 4.0 / S * (0.5 + rand(gen, (R, S), device))
    elif name == "thin":  # fog: optical thickness 1e-9..1e-4 per sample
        sigmas = log_uniform(gen, (R, S), -8, -3, device)
        deltas = 4.0 / S * (0.5 + rand(gen, (R, S), device))
    elif name == "dense":  # opaque surfaces and NeRF's 1e10 last interval
        sigmas = log_uniform(gen, (R, S), 2, 10, device)
        deltas = log_uniform(gen, (R, S), -4, -1, device)
        deltas[:, -1] = 1e10
    else:  # "extreme": densities and interval lengths 0 or 1e-10..1e10
        sigmas = zero_some(gen, log_uniform(gen, (R, S), -10, 10, device), 0.2)
        deltas = zero_some(gen, log_uniform(gen, (R, S), -10, 10, device), 0.1)
    t_starts = 2.0 + torch.cumsum(deltas, dim=1) - deltas
    return sigmas, rand(gen, (R, S, 3), device), t_starts, t_starts + deltas, rand(gen, (3,), device)


def pdf_inputs(name: str, R: int, B: int, N: int, gen, device) -> tuple[torch.Tensor, ...]:
    """bins (R, B+1), weights (R, B) and sorted positions u (R, N), float64."""
    if name == "typical":  # coarse weights of a trained NeRF on [2, 6]
        widths = 4.0 / B * (0.5 + rand(gen, (R, B), device))
        weights = zero_some(gen, log_uniform(gen, (R, B), -4, 0, device), 0.3)
        start = torch.full((R, 1), 2.0, dtype=torch.float64, device=device)
    else:  # "extreme": duplicated edges, weights 1e-30..1e30 per ray, all-zero and one-hot rays
        widths = zero_some(gen, log_uniform(gen, (R, B), -6, 3, device), 0.3)
        scale = log_uniform(gen, (R, 1), -30, 30, device)
        weights = zero_some(gen, scale * log_uniform(gen, (R, B), -3, 3, device), 0.3)
        kind = rand(gen, (R, 1), device)
        one_hot = torch.zeros_like(weights).scatter_(
            1, torch.randint(B, (R, 1), generator=gen).to(device), 1.0
        )
        weights = torch.where(kind < 0.1, torch.zeros_like(weights), weights)
        weights = torch.where((kind >= 0.1) & (kind < 0.2), one_hot * scale, weights)
        start = (rand(gen, (R, 1), device) * 2 - 1) * 1e4
    bins = torch.cat([start, start + torch.cumsum(widths, dim=1)], dim=1)
    u = torch.sort(rand(gen, (R, N), device), dim=1).values
    return bins, weights, u


def encoding_inputs(name: str, P: int, gen, device) -> tuple[torch.Tensor, int]:
    """points (P, 3) and the number of octaves."""
    if name == "typical":  # NeRF positions in [-1, 1], 10 octaves
        return rand(gen, (P, 3), device) * 2 - 1, 10
    return (rand(gen, (P, 3), device) * 2 - 1) * 1e4, 16  # "high": |x| up to 1e4, 16 octaves


# ---------------------------------------------------------------------------------------------
# Truths and the classic formulation


def straight_through(value: torch.Tensor, carrier: torch.Tensor) -> torch.Tensor:
    return value.detach() + (carrier - carrier.detach())


def composite_truth(sigmas, rgbs, t_starts, t_ends, background):
    """The reference's formulas in float64, with alpha's gradient taken from exp(-tau) itself:
    autograd of expm1 forms it as expm1(-tau) + 1, exactly 0 beyond tau ~ 37 in float64."""
    tau = sigmas * (t_ends - t_starts)
    alpha = straight_through(-torch.expm1(-tau), -torch.exp(-tau))
    optical_depth = torch.cumsum(tau, dim=1)
    before = torch.cat([torch.zeros_like(tau[:, :1]), optical_depth[:, :-1]], dim=1)
    weights = torch.exp(-before) * alpha
    color = (weights[..., None] * rgbs).sum(dim=1) + torch.exp(-optical_depth[:, -1:]) * background
    depth = (weights * 0.5 * (t_starts + t_ends)).sum(dim=1)
    return color, depth, weights.sum(dim=1), weights


def composite_classic(sigmas, rgbs, t_starts, t_ends, background):
    """The original NeRF code's compositing (in float32 for low-precision inputs, like ours)."""
    dtype = sigmas.dtype
    compute = torch.promote_types(dtype, torch.float32)
    sigmas, rgbs, t_starts, t_ends, background = (
        x.to(compute) for x in (sigmas, rgbs, t_starts, t_ends, background)
    )
    alpha = 1.0 - torch.exp(-sigmas * (t_ends - t_starts))
    kept = torch.cumprod(1.0 - alpha + 1e-10, dim=1)
    transmittance = torch.cat([torch.ones_like(kept[:, :1]), kept[:, :-1]], dim=1)
    weights = alpha * transmittance
    opacity = weights.sum(dim=1)
    color = (weights[..., None] * rgbs).sum(dim=1) + (1.0 - opacity)[:, None] * background
    depth = (weights * 0.5 * (t_starts + t_ends)).sum(dim=1)
    return tuple(x.to(dtype) for x in (color, depth, opacity, weights))


def encoding_truth(x: torch.Tensor, num_freqs: int) -> tuple[torch.Tensor, torch.Tensor]:
    """float64 [x, sin(pi 2^k x), cos(pi 2^k x)...] and its derivative blocks. 2^k x is exact in
    float64 for inputs of <= 24 significant bits and is reduced exactly to a quarter turn n / 2
    plus r in [-1/4, 1/4], so sin(pi r), cos(pi r) carry ~1e-16 relative error and exact zeros
    (sin(pi) is 0 here, not float64's 1.2e-16)."""
    values, slopes = [x], [torch.ones_like(x)]
    for k in range(num_freqs):
        y = x * 2.0**k
        quarter = torch.round(2 * y)
        r = math.pi * (y - quarter / 2)
        s, c = torch.sin(r), torch.cos(r)
        q = torch.remainder(quarter, 4)
        sin = torch.where(q == 0, s, torch.where(q == 1, c, torch.where(q == 2, -s, -c)))
        cos = torch.where(q == 0, c, torch.where(q == 1, -s, torch.where(q == 2, -c, s)))
        values += [sin, cos]
        slopes += [math.pi * 2.0**k * cos, -math.pi * 2.0**k * sin]
    return torch.cat(values, dim=-1), torch.cat(slopes, dim=-1)


# ---------------------------------------------------------------------------------------------
# Measurements, one op at a time


def forward_and_grads(fn: Callable, inputs: list[torch.Tensor], upstream: list[torch.Tensor], wrt: list[int]):
    """Outputs of ``fn(*inputs)`` and the gradients of <outputs, upstream> w.r.t. ``inputs[wrt]``,
    as one flat list (outputs first)."""
    leaves = [x.detach().clone().requires_grad_(i in wrt) for i, x in enumerate(inputs)]
    outputs = fn(*leaves)
    outputs = (outputs,) if isinstance(outputs, torch.Tensor) else tuple(outputs)
    cotangents = [g.to(o.dtype) for o, g in zip(outputs, upstream, strict=True)]
    grads = torch.autograd.grad(outputs, [leaves[i] for i in wrt], cotangents)
    return [o.detach() for o in outputs] + list(grads)


def compare(
    op: str,
    dist: str,
    dtype: torch.dtype,
    quantities: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]],
    truth: list[torch.Tensor],
    results: dict[str, list[torch.Tensor]],
) -> list[Row]:
    """One row per quantity (name -> error function, in the order of the result lists)."""
    return [
        Row(
            op,
            dist,
            name,
            str(dtype).removeprefix("torch."),
            {variant: summarise(metric(values[k], truth[k])) for variant, values in results.items()},
        )
        for k, (name, metric) in enumerate(quantities.items())
    ]


def measure_composite(R: int, S: int, device, gen) -> list[Row]:
    quantities = dict.fromkeys(
        ("color", "depth", "opacity", "weights", "d sigmas", "d t_ends"), relative_errors
    )
    variants = {
        "kernel": functools.partial(composite, backend="kernel"),
        "reference": functools.partial(composite, backend="torch"),
        "classic NeRF": composite_classic,
    }
    rows = []
    for dist in ("typical", "thin", "dense", "extreme"):
        inputs = composite_inputs(dist, R, S, gen, device)
        shapes = ((R, 3), (R,), (R,), (R, S))
        upstream = [torch.randn(shape, generator=gen, dtype=torch.float64).to(device) for shape in shapes]
        for dtype in DTYPES:
            exact, cotangents = [cast(x, dtype) for x in inputs], [cast(g, dtype) for g in upstream]
            truth = forward_and_grads(composite_truth, exact, cotangents, [0, 3])
            low = [x.to(dtype) for x in exact]
            results = {name: forward_and_grads(fn, low, cotangents, [0, 3]) for name, fn in variants.items()}
            rows += compare("composite", dist, dtype, quantities, truth, results)
    return rows


def measure_sampling(R: int, B: int, N: int, device, gen) -> list[Row]:
    """sample_pdf (samples and gradients) and hierarchical_samples (the merged depths)."""
    rows = []
    for dist in ("typical", "extreme"):
        bins64, weights64, u64 = pdf_inputs(dist, R, B, N, gen, device)
        upstream = torch.randn((R, N), generator=gen, dtype=torch.float64).to(device)
        u = u64.float()  # the positions the kernels take for low-precision inputs
        for dtype in DTYPES:
            bins, weights = cast(bins64, dtype), cast(weights64, dtype)
            on_edges = functools.partial(position_errors, bins=bins)
            quantities = {"samples": on_edges, "d bins": relative_errors, "d weights": relative_errors}
            truth = forward_and_grads(
                functools.partial(sample_pdf_reference, u=u.double()),
                [bins, weights],
                [cast(upstream, dtype)],
                [0, 1],
            )
            results = {
                name: forward_and_grads(
                    functools.partial(sample_pdf, num_samples=N, u=u, backend=backend),
                    [bins.to(dtype), weights.to(dtype)],
                    [cast(upstream, dtype)],
                    [0, 1],
                )
                for name, backend in (("kernel", "kernel"), ("reference", "torch"))
            }
            rows += compare("sample_pdf", dist, dtype, quantities, truth, results)
            # The bins as coarse depths (R, B+1), with one more weight.
            z, w = bins, torch.cat([weights, weights[:, :1]], dim=1)
            truth = [hierarchical_samples_reference(z, w, u.double())]
            results = {
                name: [hierarchical_samples(z.to(dtype), w.to(dtype), N, u=u, backend=backend)]
                for name, backend in (("kernel", "kernel"), ("reference", "torch"))
            }
            rows += compare("hierarchical_samples", dist, dtype, {"merged depths": on_edges}, truth, results)
    return rows


def measure_positional_encoding(P: int, device, gen) -> list[Row]:
    # sin/cos lie in [-1, 1]: their errors below half an ulp of 1 count absolutely.
    quantities = {"encoding": functools.partial(relative_errors, unit=1.0), "d x": relative_errors}
    rows = []
    for dist in ("typical", "high"):
        x64, num_freqs = encoding_inputs(dist, P, gen, device)
        upstream = torch.randn((P, 3 * (1 + 2 * num_freqs)), generator=gen, dtype=torch.float64).to(device)
        for dtype in DTYPES:
            x, cotangent = cast(x64, dtype), cast(upstream, dtype)
            encoding, slopes = encoding_truth(x, num_freqs)
            truth = [encoding, (cotangent * slopes).unflatten(-1, (-1, 3)).sum(dim=-2)]
            results = {
                name: forward_and_grads(
                    functools.partial(positional_encoding, num_freqs=num_freqs, backend=backend),
                    [x.to(dtype)],
                    [cotangent],
                    [0],
                )
                for name, backend in (("kernel", "kernel"), ("reference", "torch"))
            }
            rows += compare("positional_encoding", dist, dtype, quantities, truth, results)
    return rows


# ---------------------------------------------------------------------------------------------
# Report


VARIANTS = ("kernel", "reference", "classic NeRF")
DISTRIBUTIONS = {
    "typical": "the op's everyday inputs (see the code)",
    "thin": "optical thickness 1e-9..1e-4 per sample (fog)",
    "dense": "densities 1e2..1e10, last interval 1e10",
    "extreme": "values 0 or 1e-10..1e10 (composite), 1e-30..1e30 weights with duplicated edges (sampling)",
    "high": "|x| up to 1e4, 16 octaves",
}


NOTES = (
    "Reading the table: medians show the typical error; maxima are set by the worst-conditioned",
    "element, where the *input* precision already bounds what any method can get (e.g. the depth",
    "gradient of a sample at t ~ 4e7, where float32 has an ulp of 4, or gradients near float32's",
    "underflow, ~1e-36). Compare a variant's maximum with the kernel's in the same row: a gap of",
    "orders of magnitude is a formulation breaking, not rounding.",
)


def fmt(value: float) -> str:
    return "inf" if math.isinf(value) else f"{value:.1e}"


def markdown(rows: list[Row], header: dict) -> str:
    lines = [
        f"# Error budget ({header['device']})",
        "",
        f"{header['torch']} on {header['machine']}; sizes {header['sizes']}; {header['seconds']:.0f} s.",
        "Relative error against a float64 truth (see `benchmarks/error_budget.py`): max / median over",
        "all elements; `inf`: non-finite where the truth is finite. Low-precision inputs are computed",
        "in float32 by the kernels and by the reference path (composite, sampling); the reference",
        "positional encoding computes in the input dtype. Distributions:",
        "",
    ]
    lines += [f"- **{name}**: {text}" for name, text in DISTRIBUTIONS.items()]
    lines += ["", *NOTES]
    for op in dict.fromkeys(r.op for r in rows):
        op_rows = [r for r in rows if r.op == op]
        variants = [v for v in VARIANTS if v in op_rows[0].errors]
        lines += [
            "",
            f"## {op}",
            "",
            "| distribution | quantity | dtype | "
            + " | ".join(f"{v} max | {v} median" for v in variants)
            + " |",
        ]
        lines.append("|" + "---|" * (3 + 2 * len(variants)))
        for r in op_rows:
            cells = " | ".join(f"{fmt(r.errors[v][0])} | {fmt(r.errors[v][1])}" for v in variants)
            lines.append(f"| {r.distribution} | {r.quantity} | {r.dtype} | {cells} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--out", type=Path, default=RESULTS / "error_budget")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    big = device.type == "cuda"
    sizes = {
        "rays": 65536 if big else 4096,
        "samples": 192 if big else 64,
        "pdf_bins": 63,
        "pdf_samples": 128,
        "points": 1 << 20 if big else 1 << 16,
    }
    gen = torch.Generator().manual_seed(args.seed)  # on the CPU: the same inputs on every device
    start = time.perf_counter()
    rows = measure_composite(sizes["rays"], sizes["samples"], device, gen)
    rows += measure_sampling(sizes["rays"], sizes["pdf_bins"], sizes["pdf_samples"], device, gen)
    rows += measure_positional_encoding(sizes["points"], device, gen)
    header = {
        "device": torch.cuda.get_device_name(device)
        if big
        else f"CPU ({platform.processor() or platform.machine()})",
        "torch": f"torch {torch.__version__}",
        "machine": platform.node(),
        "sizes": ", ".join(f"{k}={v}" for k, v in sizes.items()),
        "seconds": time.perf_counter() - start,
    }
    table = markdown(rows, header)
    args.out.mkdir(parents=True, exist_ok=True)
    tag = device_tag(device)
    (args.out / f"{tag}.md").write_text(table)
    (args.out / f"{tag}.json").write_text(
        json.dumps({"header": header, "rows": [asdict(r) for r in rows]}, indent=1)
    )
    print(table)


if __name__ == "__main__":
    main()
