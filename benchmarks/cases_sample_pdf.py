"""Benchmark cases for sample_pdf and hierarchical_samples (NeRF's fine-pass sampling).

Sizes: 64 coarse samples and 128 fine ones per ray, R=4096 rays on CPU and R=65536 on CUDA,
float32. The PDF is NeRF's: bins are the 63 midpoints of the coarse depths, weights the 62
interior coarse weights (peaked, like compositing weights, every ray with some mass).

Cases:
  * hierarchical_samples fwd, positions u (R, N) given (stratified, drawn once outside the timed
    region): the fine pass's sampling + merge; byte floor z + weights + u read, merged written.
  * hierarchical_samples fwd, stratified positions drawn by each variant (the default call:
    our kernel draws them by Philox inside its one launch, the others by torch.rand): no error
    column, as every variant draws other positions (the u-given case measures the same math).
  * hierarchical_samples fwd, deterministic positions (i + 1/2) / N: the same positions nerfacc
    0.5.3's importance_sampling uses, so its error column is comparable (nerfacc samples, then
    torch.sort merges, as its users do).
  * sample_pdf fwd and fwd+bwd (gradients to bins and weights), deterministic positions.
  * sample_pdf_packed fwd and fwd+bwd: the same PDFs cut to ragged bin counts floor(63 x^2),
    x ~ U[0, 1) (0..62 bins, mean ~21, some rays without bins), deterministic positions. No
    nerfacc variant: its packed importance sampling takes another layout (per-edge flags).
  * sample_pdf and sample_pdf_packed fwd and fwd+bwd, stratified positions drawn by each variant
    (the default call, values checked: on CUDA our kernel draws the positions by Philox and checks
    the values inside its one launch, with no host sync but the packed op's sizing of shared
    memory; the others draw by torch.rand): no error column, as every variant draws other
    positions.
Our "kernel" variants run with check_values=False (the inputs are valid by construction), "ours,
values checked" with the default checks at the same positions; the reference variants take the
same u tensor the kernel sees.
"""

from __future__ import annotations

import torch

from benchmarks.harness import Case, Variant
from mixer_nerf.ops.hierarchical_samples import hierarchical_samples
from mixer_nerf.ops.hierarchical_samples_reference import hierarchical_samples_reference
from mixer_nerf.ops.sample_pdf import sample_pdf, sample_pdf_packed
from mixer_nerf.ops.sample_pdf_reference import sample_pdf_packed_reference, sample_pdf_reference

COARSE, FINE = 64, 128


def make_inputs(R: int, device: torch.device, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator(device=device).manual_seed(seed)
    strata = torch.linspace(0, 1, COARSE + 1, device=device)[:-1]
    z = 2.0 + 4.0 * (strata + torch.rand(R, COARSE, generator=gen, device=device) / COARSE)
    surface = 2.5 + 3.0 * torch.rand(R, 1, generator=gen, device=device)
    peak = torch.exp(-0.5 * ((z - surface) / 0.15) ** 2)
    weights = peak * torch.rand(R, COARSE, generator=gen, device=device) + 1e-3 * torch.rand(
        R, COARSE, generator=gen, device=device
    )
    strata_fine = torch.arange(FINE, device=device) / FINE
    u = strata_fine + torch.rand(R, FINE, generator=gen, device=device) / FINE
    return {"z": z.contiguous(), "weights": weights.contiguous(), "u": u.contiguous()}


def deterministic_u(device: torch.device, dtype=torch.float32) -> torch.Tensor:
    return (torch.arange(FINE, device=device, dtype=dtype) + 0.5) / FINE


def nerfacc_importance_samples(bins: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """nerfacc 0.5.3's batched importance sampling at its deterministic positions (i + 1/2) / N,
    from the normalised CDF that its users compute in PyTorch."""
    import nerfacc
    from nerfacc.data_specs import RayIntervals

    cdf = torch.cumsum(weights, dim=-1) / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], dim=-1)
    _, samples = nerfacc.importance_sampling(
        RayIntervals(vals=bins.contiguous()), cdf.contiguous(), FINE, False
    )
    return samples.vals


def nerfacc_hierarchical(z: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    fine = nerfacc_importance_samples(0.5 * (z[:, 1:] + z[:, :-1]), weights[:, 1:-1])
    return torch.sort(torch.cat([z, fine], dim=-1), dim=-1).values


def has_nerfacc(device: torch.device) -> bool:
    if device.type != "cuda":
        return False
    try:
        import nerfacc  # noqa: F401
    except ImportError:
        return False
    return True


def hierarchical_case(size: str, inputs: dict, device: torch.device, deterministic: bool) -> Case:
    z, weights = inputs["z"], inputs["weights"]
    u = deterministic_u(device) if deterministic else inputs["u"]
    variants = [
        Variant(
            "kernel",
            lambda: hierarchical_samples(z, weights, FINE, u=u, backend="kernel", check_values=False),
        ),
        Variant(  # what a user calls: values checked
            "ours, defaults",
            lambda: hierarchical_samples(z, weights, FINE, deterministic=True) if deterministic
            else hierarchical_samples(z, weights, FINE, u=u),
        ),
        Variant("torch", lambda: hierarchical_samples_reference(z, weights, u)),
    ]
    if device.type == "cuda":
        compiled = torch.compile(hierarchical_samples_reference)
        variants.append(Variant("torch.compile", lambda: compiled(z, weights, u)))
    if deterministic and has_nerfacc(device):
        variants.append(Variant("nerfacc", lambda: nerfacc_hierarchical(z, weights)))
    R = z.shape[0]
    u_bytes = u.numel() * u.element_size()
    return Case(
        op="hierarchical_samples",
        mode="fwd",
        size=f"{size} u={'(N,) deterministic' if deterministic else '(R, N) given'}",
        variants=variants,
        truth=lambda: hierarchical_samples_reference(z.double(), weights.double(), u.double()),
        min_bytes=(2 * R * COARSE + R * (COARSE + FINE)) * z.element_size() + u_bytes,
    )


def stratified_u(R: int, device: torch.device) -> torch.Tensor:
    """NeRF's stratified fine positions, drawn afresh as a caller without a kernel would."""
    return (torch.arange(FINE, device=device) + torch.rand(R, FINE, device=device)) / FINE


def hierarchical_stratified_case(size: str, inputs: dict, device: torch.device) -> Case:
    z, weights = inputs["z"], inputs["weights"]
    R = z.shape[0]

    def drawn():
        return hierarchical_samples_reference(z, weights, stratified_u(R, device))

    variants = [
        Variant("kernel", lambda: hierarchical_samples(z, weights, FINE, backend="kernel", check_values=False)),
        Variant("ours, defaults", lambda: hierarchical_samples(z, weights, FINE)),
        Variant("torch", drawn),
    ]
    if device.type == "cuda":
        variants.append(Variant("torch.compile", torch.compile(drawn)))
    return Case(
        op="hierarchical_samples",
        mode="fwd",
        size=f"{size} stratified, drawn (default)",
        variants=variants,
        truth=None,
        min_bytes=(2 * R * COARSE + R * (COARSE + FINE)) * z.element_size(),
    )


def pdf_of(inputs: dict) -> tuple[torch.Tensor, torch.Tensor]:
    z = inputs["z"]
    return (0.5 * (z[:, 1:] + z[:, :-1])).contiguous(), inputs["weights"][:, 1:-1].contiguous()


def packed_pdf_of(inputs: dict, device: torch.device, seed: int = 2):
    """pdf_of's rays keeping their first floor(63 x^2) bins: bins (N + R,), weights (N,), offsets."""
    bins, weights = pdf_of(inputs)
    R, B = weights.shape
    gen = torch.Generator(device=device).manual_seed(seed)
    counts = (B + 1) * torch.rand(R, generator=gen, device=device) ** 2
    counts = counts.long().clamp_max(B)
    slots = torch.arange(B + 1, device=device)
    packed_bins = bins[slots <= counts[:, None]].contiguous()
    packed_weights = weights[slots[:-1] < counts[:, None]].contiguous()
    return packed_bins, packed_weights, torch.nn.functional.pad(counts.cumsum(0), (1, 0))


def pdf_cases(op: str, size: str, bins, weights, impls: dict, reference, device, nerfacc=None) -> list[Case]:
    """fwd and fwd+bwd cases of ``impls[name](bins, weights, u)`` at the deterministic positions;
    ``reference`` gives the float64 truth (None: no truth, for variants that draw their own
    positions), ``nerfacc`` an optional forward-only peer."""
    u = deterministic_u(device)
    R = impls["torch"](bins, weights, u).shape[0]
    item = bins.element_size()

    def forward(fn, dtype=None):
        with torch.no_grad():
            cast = [x if dtype is None else x.to(dtype) for x in (bins, weights, u)]
            return fn(*cast)

    fwd_bytes = (bins.numel() + weights.numel() + R * FINE) * item
    fwd_variants = [Variant(name, lambda fn=fn: forward(fn)) for name, fn in impls.items()]
    if nerfacc is not None:
        fwd_variants.append(Variant("nerfacc", nerfacc))
    gen = torch.Generator(device=device).manual_seed(1)
    upstream = torch.randn(R, FINE, generator=gen, device=device)

    def step(fn, dtype=None):
        leaves = [x.detach().to(dtype or x.dtype).requires_grad_() for x in (bins, weights)]
        out = fn(*leaves, u.to(dtype or u.dtype))
        grads = torch.autograd.grad(out, leaves, upstream.to(out.dtype))
        return (out.detach(), *grads)

    # backward: read grad_samples, bins, weights; write grad_bins, grad_weights
    bwd_bytes = (R * FINE + 2 * (bins.numel() + weights.numel())) * item
    has_truth = reference is not None
    return [
        Case(op, "fwd", size, fwd_variants, (lambda: forward(reference, torch.float64)) if has_truth else None,
             fwd_bytes),
        Case(
            op,
            "fwd+bwd",
            size,
            [Variant(name, lambda fn=fn: step(fn)) for name, fn in impls.items()],
            (lambda: step(reference, torch.float64)) if has_truth else None,
            fwd_bytes + bwd_bytes,
        ),
    ]


def pdf_default_cases(op: str, size: str, bins, weights, ours, reference, device) -> list[Case]:
    """:func:`pdf_cases` of what a user calls, ``ours(bins, weights)`` (stratified positions drawn
    by the op, values checked), beside ``reference(bins, weights, u)`` with positions drawn as a
    caller without the op would; no error column (each variant draws other positions)."""
    R = weights.shape[0] if weights.dim() == 2 else bins.shape[0] - weights.shape[0]
    impls = {"ours, defaults": lambda b, w, _: ours(b, w),
             "torch": lambda b, w, _: reference(b, w, stratified_u(R, device))}
    if device.type == "cuda":
        impls["torch.compile"] = torch.compile(impls["torch"])
    return pdf_cases(op, f"{size} stratified, drawn (default)", bins, weights, impls, None, device)


def sample_pdf_cases(size: str, inputs: dict, device: torch.device) -> list[Case]:
    bins, weights = pdf_of(inputs)
    impls = {
        "kernel": lambda b, w, uu: sample_pdf(b, w, FINE, u=uu, backend="kernel", check_values=False),
        "ours, values checked": lambda b, w, uu: sample_pdf(b, w, FINE, u=uu),
        "torch": sample_pdf_reference,
    }
    if device.type == "cuda":
        impls["torch.compile"] = torch.compile(sample_pdf_reference)
    nerfacc = (lambda: nerfacc_importance_samples(bins, weights)) if has_nerfacc(device) else None
    return [
        *pdf_cases("sample_pdf", size, bins, weights, impls, sample_pdf_reference, device, nerfacc),
        *pdf_default_cases("sample_pdf", size, bins, weights, lambda b, w: sample_pdf(b, w, FINE),
                           sample_pdf_reference, device),
    ]


def sample_pdf_packed_cases(inputs: dict, device: torch.device) -> list[Case]:
    bins, weights, offsets = packed_pdf_of(inputs, device)

    def reference(b, w, uu):
        return sample_pdf_packed_reference(b, w, offsets, uu)

    impls = {
        "kernel": lambda b, w, uu: sample_pdf_packed(
            b, w, offsets, FINE, u=uu, backend="kernel", check_values=False
        ),
        "ours, values checked": lambda b, w, uu: sample_pdf_packed(b, w, offsets, FINE, u=uu),
        "torch": reference,
    }
    if device.type == "cuda":
        impls["torch.compile"] = torch.compile(reference)
    size = f"R={offsets.numel() - 1} bins={weights.numel()} (0..{COARSE - 2} per ray) N={FINE}"
    return [
        *pdf_cases("sample_pdf_packed", size, bins, weights, impls, reference, device),
        *pdf_default_cases("sample_pdf_packed", size, bins, weights,
                           lambda b, w: sample_pdf_packed(b, w, offsets, FINE), reference, device),
    ]


def cases(device: torch.device) -> list[Case]:
    R = 65536 if device.type == "cuda" else 4096
    inputs = make_inputs(R, device)
    size = f"R={R} S={COARSE} N={FINE}"
    return [
        hierarchical_stratified_case(size, inputs, device),
        hierarchical_case(size, inputs, device, deterministic=False),
        hierarchical_case(size, inputs, device, deterministic=True),
        *sample_pdf_cases(size, inputs, device),
        *sample_pdf_packed_cases(inputs, device),
    ]
