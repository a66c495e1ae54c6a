"""Tests of segment_mean and ray_scale (SE on packed rows): CPU/CUDA kernels against the reference."""

from __future__ import annotations

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.ops import ray_scale, segment_mean
from cuda_poison import poison_allocator

needs_kernels = pytest.mark.skipif(not _extension.available(), reason="mixer_nerf kernels not built")
on_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")

F64_REL = 1e-12  # float64 kernel vs float64 reference: the same sums in another order
F32_REL = 1e-5  # float32 sums of up to ~1500 rows, errors relative to the tensor's largest value
HALF_REL = {torch.float16: 2e-3, torch.bfloat16: 1e-2}  # one rounding of each output


LAYOUTS = {
    "one ray, one row": [1],
    "one ray": [9],
    "one empty ray": [0],
    "all empty": [0, 0, 0],
    "no rays": [],
    "ragged": [3, 0, 7, 1, 0, 12, 33],
    "long rays": [1500, 0, 3, 1030],
    "many": "random",
}


def counts_named(name, gen):
    if LAYOUTS[name] == "random":
        return torch.randint(0, 41, (60,), generator=gen)
    return torch.tensor(LAYOUTS[name], dtype=torch.int64)


def offsets_of(counts):
    return torch.nn.functional.pad(torch.as_tensor(counts, dtype=torch.int64).cumsum(0), (1, 0))


def make_inputs(counts, C, gen, dtype=torch.float64, device="cpu"):
    """values/features (N, C), scale (R, C), offsets (R+1,) for rays of ``counts`` rows."""
    offsets = offsets_of(counts)
    N, R = int(offsets[-1]), offsets.numel() - 1
    rows = torch.randn(N, C, generator=gen, dtype=torch.float64)
    scale = torch.rand(R, C, generator=gen, dtype=torch.float64)
    return rows.to(device, dtype), scale.to(device, dtype), offsets.to(device)


def run(rows, scale, offsets, upstream_mean, upstream_scaled, **kwargs):
    """Outputs of both ops and the gradients of sum(out * upstream) w.r.t. rows and scale."""
    rows, scale = rows.detach().clone().requires_grad_(), scale.detach().clone().requires_grad_()
    mean = segment_mean(rows, offsets, **kwargs)
    scaled = ray_scale(rows, scale, offsets, **kwargs)
    (grad_mean,) = torch.autograd.grad(mean, rows, upstream_mean)
    grad_rows, grad_scale = torch.autograd.grad(scaled, (rows, scale), upstream_scaled)
    return [mean, scaled], [grad_mean, grad_rows, grad_scale]


def truth(rows, scale, offsets, upstream_mean, upstream_scaled):
    """The float64 reference on the CPU."""
    f64 = [t.detach().to("cpu", torch.float64) for t in (rows, scale, upstream_mean, upstream_scaled)]
    return run(f64[0], f64[1], offsets.cpu(), f64[2], f64[3], backend="torch")


def magnitudes(rows, scale, offsets, upstream_mean, upstream_scaled):
    """The float64 truth of the same sums over |terms|: what each output's rounding error scales
    with. A mean of cancelling rows is small, yet its float32 error is that of the |rows| sum."""
    return truth(*(t.abs() for t in (rows, scale)), offsets, *(t.abs() for t in (upstream_mean, upstream_scaled)))


def random_upstream(rows, scale, gen):
    """Upstream gradients of segment_mean (R, C) and ray_scale (N, C)."""
    return [
        torch.randn(t.shape, generator=gen, dtype=torch.float64).to(t.device, t.dtype) for t in (scale, rows)
    ]


def assert_close(got, want, rel, what="", magnitude=None):
    """max |got - want| <= rel * max |magnitude| per tensor (magnitude: ``magnitudes()``'s, else
    ``want``), and got finite, of want's shape."""
    for k, (g, w, m) in enumerate(zip(got, want, magnitude or want, strict=True)):
        g, w = g.detach().to("cpu", torch.float64), w.detach().to("cpu", torch.float64)
        assert g.shape == w.shape, f"{what}[{k}]: shape {tuple(g.shape)} != {tuple(w.shape)}"
        assert torch.isfinite(g).all(), f"{what}[{k}]: non-finite values"
        if w.numel():
            err, scale = (g - w).abs().max().item(), m.detach().abs().max().item()
            assert err <= rel * scale, f"{what}[{k}]: max err {err:.3e} vs scale {scale:.3e}"


# ---------------------------------------------------------------------------------------------
# CPU kernels


@needs_kernels
@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("C", [1, 16, 256])
def test_cpu_kernels_match_reference(gen, layout, C):
    rows, scale, offsets = make_inputs(counts_named(layout, gen), C, gen)
    upstream = random_upstream(rows, scale, gen)
    want_out, want_grads = truth(rows, scale, offsets, *upstream)
    size_out, size_grads = magnitudes(rows, scale, offsets, *upstream)
    for dtype, rel in ((torch.float64, F64_REL), (torch.float32, F32_REL)):
        cast = [t.to(dtype) for t in (rows, scale, *upstream)]
        out, grads = run(cast[0], cast[1], offsets, *cast[2:], backend="kernel")
        assert all(t.dtype == dtype for t in out + grads)
        assert_close(out, want_out, rel, f"{dtype} outputs", size_out)
        assert_close(grads, want_grads, rel, f"{dtype} grads", size_grads)


@needs_kernels
def test_cpu_empty_rays_get_zero_mean_and_zero_scale_gradient(gen):
    rows, scale, offsets = make_inputs([0, 4, 0, 2, 0], 5, gen)
    empty = torch.tensor([True, False, True, False, True])
    out, grads = run(rows, scale, offsets, *random_upstream(rows, scale, gen), backend="kernel")
    assert not out[0][empty].any() and not grads[2][empty].any()


@needs_kernels
def test_cpu_gradcheck(gen):
    rows, scale, offsets = make_inputs([2, 0, 5, 1], 3, gen)
    rows, scale = rows.requires_grad_(), scale.requires_grad_()
    assert torch.autograd.gradcheck(lambda v: segment_mean(v, offsets, backend="kernel"), (rows,))
    assert torch.autograd.gradcheck(lambda f, s: ray_scale(f, s, offsets, backend="kernel"), (rows, scale))


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_cpu_half_precision(gen, dtype):
    """Half/bfloat16 rows sum in float32: one rounding of each output away from the float64 truth
    of the same (rounded) inputs. A product is one rounding of the exact one, as torch's own."""
    rows, scale, offsets = make_inputs(counts_named("many", gen), 16, gen, dtype)
    upstream = random_upstream(rows, scale, gen)
    out, grads = run(rows, scale, offsets, *upstream, backend="kernel")
    assert all(t.dtype == dtype for t in out + grads)
    want_out, want_grads = truth(rows, scale, offsets, *upstream)
    size_out, size_grads = magnitudes(rows, scale, offsets, *upstream)
    assert_close(out, want_out, HALF_REL[dtype], "outputs", size_out)
    assert_close(grads, want_grads, HALF_REL[dtype], "grads", size_grads)
    assert torch.equal(out[1], ray_scale(rows, scale, offsets, backend="torch"))
    ray = torch.repeat_interleave(torch.arange(offsets.numel() - 1), offsets.diff())
    assert torch.equal(out[1], rows * scale[ray])


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_cpu_large_magnitudes_and_cancellation(gen, dtype):
    """Rows of magnitudes 1e-30..1e30 with random signs (sums cancel): each result within the
    bound of a float32 recursive sum, n * 2^-24 * sum |terms| (of the float64 truth's own terms),
    where a float16/bfloat16 accumulator or an unscaled float32 one would lose it all."""
    counts = torch.tensor([1500, 1, 0, 37, 2, 1030])
    offsets = offsets_of(counts)
    N, R, C = int(offsets[-1]), counts.numel(), 8
    sign = torch.randint(0, 2, (N, C), generator=gen) * 2 - 1
    rows = (sign * 10 ** (60 * torch.rand(N, C, generator=gen, dtype=torch.float64) - 30)).to(dtype)
    scale = (10 ** (8 * torch.rand(R, C, generator=gen, dtype=torch.float64) - 4)).to(dtype)
    upstream = [torch.randn(R, C, generator=gen).to(dtype), torch.randn(N, C, generator=gen).to(dtype)]
    out, grads = run(rows, scale, offsets, *upstream, backend="kernel")
    want_out, want_grads = truth(rows, scale, offsets, *upstream)
    n = counts.double()[:, None]
    u = 2.0**-24  # float32's unit roundoff
    abs_sum = segment_mean(rows.double().abs(), offsets, backend="torch") * n
    terms = (upstream[1].double() * rows.double()).abs()
    abs_terms = segment_mean(terms, offsets, backend="torch") * n
    rounding = torch.finfo(dtype).eps  # the final roundings (division, cast to dtype), with margin
    for got, want, bound in (
        (out[0], want_out[0], u * abs_sum),  # the sum's error over n
        (grads[2], want_grads[2], n * u * abs_terms),
        (out[1], want_out[1], 0.0),  # products: one rounding
        (grads[1], want_grads[1], 0.0),
    ):
        err = (got.double() - want).abs()
        assert torch.isfinite(got).all()
        assert (err <= bound + rounding * want.abs()).all(), f"worst excess {(err - bound).max().item():.3e}"


@needs_kernels
def test_cpu_non_contiguous_inputs(gen):
    rows, scale, offsets = make_inputs([3, 0, 5], 4, gen)
    rows_nc, scale_nc = rows.t().contiguous().t(), scale.t().contiguous().t()
    assert not rows_nc.is_contiguous()
    want = segment_mean(rows, offsets, backend="torch")
    torch.testing.assert_close(segment_mean(rows_nc, offsets, backend="kernel"), want)
    torch.testing.assert_close(
        ray_scale(rows_nc, scale_nc, offsets, backend="kernel"),
        ray_scale(rows, scale, offsets, backend="torch"),
    )


@needs_kernels
def test_cpu_unchecked_bad_offsets_stay_in_bounds(gen):
    """check_values=False skips the offsets' value checks; the kernels clamp them into [0, N]
    instead of reading or writing outside the arrays (a ray past N is empty)."""
    rows, scale, _ = make_inputs([3, 2], 3, gen)
    for bad in ([0, 100, 5], [-7, 2, 5], [0, 4, 2], [3, 1, 0]):
        offsets = torch.tensor(bad)
        upstream = random_upstream(rows, scale, gen)
        out, _ = run(rows, scale, offsets, *upstream, backend="kernel", check_values=False)
        assert torch.isfinite(out[0]).all()


def test_segment_mean_is_the_mean_of_each_rays_rows():
    values = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    offsets = torch.tensor([0, 2, 2, 3])
    want = torch.tensor([[2.0, 3.0], [0.0, 0.0], [5.0, 6.0]])
    for backend in ["torch"] + (["kernel"] if _extension.available() else []):
        torch.testing.assert_close(segment_mean(values, offsets, backend=backend), want)
        scale = torch.tensor([[1.0, 2.0], [7.0, 7.0], [0.5, -1.0]])
        scaled = ray_scale(values, scale, offsets, backend=backend)
        torch.testing.assert_close(scaled, torch.tensor([[1.0, 4.0], [3.0, 8.0], [2.5, -6.0]]))


# ---------------------------------------------------------------------------------------------
# Validation: clear errors before any kernel runs


def valid_args():
    """values/features (6, 3), scale (3, 3), offsets for 3 rays of 0, 4 and 2 rows."""
    return {"rows": torch.rand(6, 3), "scale": torch.rand(3, 3), "offsets": torch.tensor([0, 0, 4, 6])}


BAD = [
    ("rows", torch.rand(6), ValueError, "values|features"),
    ("rows", torch.rand(6, 3, 1), ValueError, "values|features"),
    ("rows", torch.rand(6, 0), ValueError, "values|features"),
    ("rows", torch.ones(6, 3, dtype=torch.int64), TypeError, "values|features"),
    ("rows", [[1.0, 2.0, 3.0]], TypeError, "values|features"),
    ("rows", torch.rand(5, 3), ValueError, "offsets"),
    ("rows", torch.rand(6, 3, device="meta"), ValueError, "offsets on cpu"),
    ("offsets", torch.tensor([0, 0, 4, 6], dtype=torch.int32), TypeError, "offsets"),
    ("offsets", torch.tensor([0.0, 0.0, 4.0, 6.0]), TypeError, "offsets"),
    ("offsets", [0, 0, 4, 6], TypeError, "offsets"),
    ("offsets", torch.tensor([[0, 0, 4, 6]]), ValueError, "offsets"),
    ("offsets", torch.zeros(0, dtype=torch.int64), ValueError, "offsets"),
    ("offsets", torch.tensor([0, 0, 4, 5]), ValueError, "offsets"),
    ("offsets", torch.tensor([1, 1, 4, 6]), ValueError, "offsets"),
    ("offsets", torch.tensor([0, 5, 4, 6]), ValueError, "offsets"),
    ("offsets", torch.tensor([0, 0, 4, 6], device="meta"), ValueError, "offsets on meta"),
]
BAD_SCALE = [
    ("scale", torch.rand(4, 3), ValueError, "scale"),
    ("scale", torch.rand(3, 2), ValueError, "scale"),
    ("scale", torch.rand(3), ValueError, "scale"),
    ("scale", torch.rand(3, 3, dtype=torch.float64), TypeError, "scale"),
    ("scale", torch.rand(3, 3).bfloat16(), TypeError, "scale"),
    ("scale", torch.ones(3, 3, dtype=torch.int64), TypeError, "scale"),
    ("scale", [[1.0] * 3] * 3, TypeError, "scale"),
    ("scale", torch.rand(3, 3, device="meta"), ValueError, "scale on meta"),
]
BACKENDS = ["torch"] + (["kernel"] if _extension.available() else [])


@pytest.mark.parametrize("name, bad, error, match", BAD)
@pytest.mark.parametrize("backend", BACKENDS)
def test_segment_mean_bad_inputs_raise(name, bad, error, match, backend):
    args = {**valid_args(), name: bad}
    with pytest.raises(error, match=match):
        segment_mean(args["rows"], args["offsets"], backend=backend)


@pytest.mark.parametrize("name, bad, error, match", BAD + BAD_SCALE)
@pytest.mark.parametrize("backend", BACKENDS)
def test_ray_scale_bad_inputs_raise(name, bad, error, match, backend):
    args = {**valid_args(), name: bad}
    with pytest.raises(error, match=match):
        ray_scale(args["rows"], args["scale"], args["offsets"], backend=backend)


def test_bad_backend_raises():
    args = valid_args()
    with pytest.raises(ValueError, match="backend"):
        segment_mean(args["rows"], args["offsets"], backend="cuda")
    with pytest.raises(ValueError, match="backend"):
        ray_scale(args["rows"], args["scale"], args["offsets"], backend="cuda")


# ---------------------------------------------------------------------------------------------
# Registered ops


def op_samples(gen, device="cpu"):
    """(op, args) of every registered op, on layouts with empty rays and several channel counts."""
    samples = []
    for counts, C in (([3, 0, 5, 1], 3), ([0, 0], 8), ([7], 1)):
        rows, scale, offsets = make_inputs(counts, C, gen, torch.float32, device)
        grad_mean, grad_out = random_upstream(rows, scale, gen)
        ops = torch.ops.mixer_nerf
        samples += [
            (ops.segment_mean_fwd.default, (rows, offsets)),
            (ops.segment_mean_bwd.default, (grad_mean, offsets, rows.shape[0])),
            (ops.ray_scale_fwd.default, (rows, scale, offsets)),
            (ops.ray_scale_bwd.default, (grad_out, rows, scale, offsets)),
        ]
    return samples


@needs_kernels
def test_opcheck_cpu(gen):
    args = valid_args()
    ray_scale(args["rows"], args["scale"], args["offsets"], backend="kernel")  # registers the fakes
    for op, args in op_samples(gen):
        torch.library.opcheck(op, args)


# ---------------------------------------------------------------------------------------------
# CUDA kernels


def check_cuda(gen, rows, scale, offsets, rel):
    """CUDA kernels vs CPU kernels vs the float64 reference, outputs and gradients poisoned."""
    upstream = random_upstream(rows, scale, gen)
    cpu_out, cpu_grads = run(rows, scale, offsets, *upstream, backend="kernel")
    want_out, want_grads = truth(rows, scale, offsets, *upstream)
    size_out, size_grads = magnitudes(rows, scale, offsets, *upstream)
    on_gpu = [t.cuda() for t in (rows, scale, offsets, *upstream)]
    poison_allocator(cpu_out + cpu_grads)
    out, grads = run(*on_gpu, backend="kernel", check_values=False)  # no value-check temporaries
    assert all(t.device.type == "cuda" and t.dtype == rows.dtype for t in out + grads)
    assert_close(out, want_out, rel, "cuda outputs vs reference", size_out)
    assert_close(grads, want_grads, rel, "cuda grads vs reference", size_grads)
    assert_close(out, cpu_out, rel, "cuda vs cpu outputs", size_out)
    assert_close(grads, cpu_grads, rel, "cuda vs cpu grads", size_grads)


CUDA_DTYPES = {torch.float32: F32_REL, torch.float64: F64_REL, **HALF_REL}


@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("C", [1, 3, 8, 16, 256, 260])  # vectorised where C allows, else scalar
@pytest.mark.parametrize("dtype", list(CUDA_DTYPES))
@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_matches_cpu_and_reference(gen, layout, C, dtype):
    check_cuda(gen, *make_inputs(counts_named(layout, gen), C, gen, dtype), CUDA_DTYPES[dtype])


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_training_sized_batch(gen, dtype):
    """The SE's real shapes: ~8000 rays of 0..60 rows, C = 256 (16-byte vectors in bfloat16)."""
    counts = torch.randint(0, 61, (8000,), generator=gen)
    check_cuda(gen, *make_inputs(counts, 256, gen, dtype), CUDA_DTYPES[dtype])


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_misaligned_rows_take_the_scalar_path(gen):
    """Rows that start one element into their storage cannot be read in 16-byte vectors."""
    rows, scale, offsets = make_inputs([5, 0, 40], 16, gen, torch.bfloat16, "cuda")
    upstream = random_upstream(rows, scale, gen)
    want = run(rows, scale, offsets, *upstream, backend="kernel")
    views = [
        torch.empty(t.numel() + 1, dtype=t.dtype, device="cuda")[1:].view_as(t).copy_(t).requires_grad_()
        for t in (rows, scale)
    ]
    assert all(v.data_ptr() % 16 for v in views)
    mean = segment_mean(views[0], offsets, backend="kernel")
    scaled = ray_scale(*views, offsets, backend="kernel")
    (grad_mean,) = torch.autograd.grad(mean, views[0], upstream[0])
    grads = torch.autograd.grad(scaled, views, upstream[1])
    # Products are exact either way; sums are taken in another order (rows per thread differ).
    assert torch.equal(scaled, want[0][1]) and torch.equal(grad_mean, want[1][0])
    assert torch.equal(grads[0], want[1][1])
    size = magnitudes(rows, scale, offsets, *upstream)
    sums = [want[0][0], want[1][2]]
    assert_close([mean, grads[1]], sums, HALF_REL[torch.bfloat16], "sums", [size[0][0], size[1][2]])


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_float64_gradcheck(gen):
    rows, scale, offsets = make_inputs([40, 0, 3, 70], 3, gen, device="cuda")
    rows, scale = rows.requires_grad_(), scale.requires_grad_()
    assert torch.autograd.gradcheck(lambda v: segment_mean(v, offsets, backend="kernel"), (rows,))
    assert torch.autograd.gradcheck(lambda f, s: ray_scale(f, s, offsets, backend="kernel"), (rows, scale))


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_deterministic(gen):
    counts = torch.randint(0, 2000, (50,), generator=gen)
    rows, scale, offsets = make_inputs(counts, 256, gen, torch.float32, "cuda")
    upstream = random_upstream(rows, scale, gen)
    first = run(rows, scale, offsets, *upstream, backend="kernel")
    again = run(rows, scale, offsets, *upstream, backend="kernel")
    assert all(torch.equal(a, b) for a, b in zip(first[0] + first[1], again[0] + again[1], strict=True))


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_unchecked_bad_offsets_stay_in_bounds(gen):
    rows, scale, _ = make_inputs([3, 2], 3, gen, device="cuda")
    for bad in ([0, 100, 5], [-7, 2, 5], [0, 4, 2], [3, 1, 0]):
        offsets = torch.tensor(bad, device="cuda")
        upstream = random_upstream(rows, scale, gen)
        out, _ = run(rows, scale, offsets, *upstream, backend="kernel", check_values=False)
        torch.cuda.synchronize()
        assert torch.isfinite(out[0]).all()


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_cuda_wrong_device_is_a_clear_error(gen):
    rows, scale, offsets = make_inputs([3, 2], 3, gen, torch.float32, "cuda")
    with pytest.raises(ValueError, match="offsets on cpu"):
        segment_mean(rows, offsets.cpu(), backend="kernel")
    with pytest.raises(ValueError, match="scale on cpu"):
        ray_scale(rows, scale.cpu(), offsets, backend="kernel")
    with pytest.raises(RuntimeError, match="offsets"):  # the op called directly: the kernel's check
        torch.ops.mixer_nerf.segment_mean_fwd(rows, offsets.cpu())


@pytest.mark.cuda
@on_cuda
@needs_kernels
def test_opcheck_cuda(gen):
    args = valid_args()
    ray_scale(args["rows"].cuda(), args["scale"].cuda(), args["offsets"].cuda(), backend="kernel")
    for op, args in op_samples(gen, device="cuda"):
        torch.library.opcheck(op, args)
