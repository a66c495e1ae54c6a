"""Tests of mlca: CPU/CUDA kernels against the float64 reference (forward and every gradient), the
float64 gradcheck, adversarial inputs, argument validation, opcheck, and the MLCA module on top.

Inputs are fresh random each run (the seed is printed), with every weight non-zero so that each
term of the forward and backward matters. Tolerances are relative to the largest magnitude of the
compared tensor: the float32 kernels accumulate in float32, in another order than the reference.
"""

from __future__ import annotations

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.model import MLCA
from mixer_nerf.ops import mlca
from mixer_nerf.ops.mlca import MAX_CHANNELS, MAX_TOKEN_DIM, MAX_TOKENS
from mixer_nerf.ops.mlca_reference import mlca_reference
from cuda_poison import poison_allocator
from dispatch_count import dispatched_ops

needs_kernels = pytest.mark.skipif(not _extension.available(), reason="mixer_nerf kernels not built")
on_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU")

NAMES = ("encoded", "lift", "token_weight", "token_bias", "channel_weight", "channel_bias")
# (leading shape, T, C, D): the model's T = 21 (positions), 9 (directions), 30 (both mixed).
SHAPES = [
    ((1,), 21, 8, 3),
    ((37,), 9, 3, 3),
    ((300,), 21, 8, 3),
    ((257,), 30, 16, 3),
    ((4, 5), 7, 5, 2),
    ((), 3, 4, 1),
]
REL = {torch.float32: 2e-5, torch.float64: 1e-12, torch.float16: 2e-2, torch.bfloat16: 2e-1}


def make_inputs(lead, T, C, D, gen, dtype=torch.float32, device="cpu", magnitude=1.0, weight_scale=1.0):
    """encoded uniform in [-magnitude, magnitude], weights of about unit gain per layer."""

    def rand(*shape, scale=1.0):
        return (torch.randn(shape, generator=gen, dtype=torch.float64) * scale).to(dtype).to(device)

    encoded = ((torch.rand((*lead, T * D), generator=gen, dtype=torch.float64) * 2 - 1) * magnitude).to(dtype)
    return [
        encoded.to(device),
        rand(C, D, scale=weight_scale),
        rand(T, T, scale=weight_scale / T**0.5),
        rand(T, scale=0.5 * weight_scale),
        rand(C, C, scale=weight_scale / C**0.5),
        rand(C, scale=0.5 * weight_scale),
    ]


def forward_backward(inputs, grad, backend, input_grad=True):
    """Output and the gradients of every input (grad of encoded only with input_grad)."""
    leaves = [t.detach().clone().requires_grad_(i > 0 or input_grad) for i, t in enumerate(inputs)]
    out = mlca(*leaves, backend=backend)
    wrt = leaves if input_grad else leaves[1:]
    grads = torch.autograd.grad(out, wrt, grad)
    return out.detach(), list(grads) if input_grad else [None, *grads]


def truth(inputs, grad):
    return forward_backward([t.detach().double().cpu() for t in inputs], grad.double().cpu(), "torch")


def assert_close(got, want, rel, what):
    """|got - want| <= rel * max|want| (+ rel), tensor by tensor."""
    for name, g, w in zip(("out",) if torch.is_tensor(got) else NAMES, [got] if torch.is_tensor(got) else got,
                          [want] if torch.is_tensor(want) else want, strict=True):
        if w is None:
            assert g is None, f"{what}: {name} should be absent"
            continue
        assert g.shape == w.shape and bool(torch.isfinite(g).all()), f"{what}: {name}"
        err = (g.detach().double().cpu() - w.double().cpu()).abs().max().item() if w.numel() else 0.0
        bound = rel * (w.abs().max().item() if w.numel() else 0.0) + rel
        assert err <= bound, f"{what}: {name} max error {err:.3e} > {bound:.3e}"


def random_grad(inputs, C, gen):
    encoded = inputs[0]
    T = inputs[2].shape[0]
    return torch.randn((*encoded.shape[:-1], T * C), generator=gen, dtype=torch.float64).to(encoded.device, encoded.dtype)


# ---------------------------------------------------------------------------------------- CPU


@needs_kernels
@pytest.mark.parametrize("lead, T, C, D", SHAPES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpu_matches_reference(lead, T, C, D, dtype, gen):
    inputs = make_inputs(lead, T, C, D, gen, dtype)
    grad = random_grad(inputs, C, gen)
    out, grads = forward_backward(inputs, grad, "kernel")
    want_out, want_grads = truth(inputs, grad)
    assert out.shape == (*lead, T * C) and out.dtype == dtype
    assert_close(out, want_out, REL[dtype], "cpu out")
    assert_close(grads, want_grads, REL[dtype], "cpu grads")


@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_cpu_half_precision(dtype, gen):
    inputs = make_inputs((50,), 9, 8, 3, gen, dtype)
    grad = random_grad(inputs, 8, gen)
    out, grads = forward_backward(inputs, grad, "kernel")
    assert out.dtype == dtype and all(g.dtype == dtype for g in grads)
    want_out, want_grads = truth(inputs, grad)
    assert_close(out, want_out, REL[dtype], "half out")
    assert_close(grads, want_grads, REL[dtype], "half grads")


@needs_kernels
def test_gradcheck_float64(gen):
    inputs = [t.requires_grad_() for t in make_inputs((3,), 5, 4, 3, gen, torch.float64)]
    assert torch.autograd.gradcheck(lambda *args: mlca(*args, backend="kernel"), inputs)


@needs_kernels
def test_weight_grads_without_input_grad(gen):
    """encoded needing no grad (the positions' encoding in training): the op skips grad_encoded."""
    inputs = make_inputs((40,), 21, 8, 3, gen, torch.float64)
    grad = random_grad(inputs, 8, gen)
    _, grads = forward_backward(inputs, grad, "kernel", input_grad=False)
    _, want = truth(inputs, grad)
    assert_close(grads, [None, *want[1:]], REL[torch.float64], "weight grads")
    op_grads = torch.ops.mixer_nerf.mlca_bwd(grad, *inputs, False)
    assert op_grads[0] is None


@needs_kernels
@pytest.mark.parametrize("C", [8, 5])  # the compile-time channel count and a run-time one
def test_cpu_results_do_not_depend_on_the_thread_count(C, gen):
    inputs = make_inputs((1000,), 21, C, 3, gen)  # several chunks of points, the last one partial
    grad = random_grad(inputs, C, gen)
    threads = torch.get_num_threads()
    try:
        runs = []
        for n in (1, 2):
            torch.set_num_threads(n)
            runs.append(forward_backward(inputs, grad, "kernel"))
    finally:
        torch.set_num_threads(threads)
    (out_1, grads_1), (out_2, grads_2) = runs
    assert torch.equal(out_1, out_2)
    assert all(torch.equal(a, b) for a, b in zip(grads_1, grads_2, strict=True))


@needs_kernels
def test_cpu_op_refuses_more_channels_than_it_holds(gen):
    """The op's own checks (mlca() refuses C > 32 and D > 32 before them): the kernels keep a row of C
    and the backward a chunk's dlift on the stack."""
    inputs = make_inputs((2,), 3, 33, 2, gen)
    with pytest.raises(RuntimeError, match="C <= 32"):
        torch.ops.mixer_nerf.mlca_fwd(*inputs)
    inputs = make_inputs((2,), 3, 8, 33, gen)  # D > 32: the backward sums dlift (C x D) on the stack
    grad = torch.ones(2, 3 * 8)
    with pytest.raises(RuntimeError, match="D <= 32"):
        torch.ops.mixer_nerf.mlca_bwd(grad, *inputs, False)


@needs_kernels
@pytest.mark.parametrize(
    "magnitude, weight_scale", [(1e4, 1.0), (0.0, 1.0), (1.0, 30.0), (1e4, 30.0), (1e-30, 1.0)]
)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_adversarial_inputs_stay_finite(magnitude, weight_scale, dtype, gen):
    inputs = make_inputs((200,), 21, 8, 3, gen, dtype, magnitude=magnitude, weight_scale=weight_scale)
    grad = random_grad(inputs, 8, gen)
    out, grads = forward_backward(inputs, grad, "kernel")
    want_out, want_grads = truth(inputs, grad)
    assert all(bool(torch.isfinite(g).all()) for g in grads)
    if dtype == torch.float64:
        assert_close(out, want_out, 1e-10, "adversarial out")
        assert_close(grads, want_grads, 1e-10, "adversarial grads")
        return
    # float32: the forward stays within ~1e-6 of its largest value. The gradients are ill-conditioned:
    # GELU's slope at a pre-activation that is a cancelling sum of terms up to ~1e9 is decided by
    # float32 rounding, and the encoded gradient sums cancelling products. Eager float32 PyTorch
    # misses the float64 truth by the same order (1500 draws each: worst 9e-4 of the largest value
    # at weight scale 30, 6e-4 at magnitude 1e4, 3e-2 with both, where only finiteness is checked).
    assert_close(out, want_out, 1e-5, "adversarial out")
    if magnitude * weight_scale < 1e5:
        assert_close(grads, want_grads, 1e-2, "adversarial grads")


@needs_kernels
def test_empty_batch(gen):
    inputs = make_inputs((0,), 9, 8, 3, gen)
    out, grads = forward_backward(inputs, torch.zeros(0, 72), "kernel")
    assert out.shape == (0, 72) and grads[0].shape == (0, 27)
    assert all(bool((g == 0).all()) for g in grads[1:])


@needs_kernels
def test_deterministic_and_non_contiguous(gen):
    inputs = make_inputs((700,), 21, 8, 3, gen)
    grad = random_grad(inputs, 8, gen)
    first = forward_backward(inputs, grad, "kernel")
    strided = [inputs[0].t().contiguous().t(), *[t.t().contiguous().t() if t.dim() == 2 else t for t in inputs[1:]]]
    assert not strided[0].is_contiguous()
    second = forward_backward(strided, grad, "kernel")
    assert torch.equal(first[0], second[0])
    assert all(torch.equal(a, b) for a, b in zip(first[1], second[1], strict=True))


@needs_kernels
def test_opcheck(gen):
    inputs = make_inputs((17,), 5, 4, 3, gen)
    mlca(*inputs, backend="kernel")  # loads the ops, registers the fake kernels
    grad = random_grad(inputs, 4, gen)
    torch.library.opcheck(torch.ops.mixer_nerf.mlca_fwd.default, tuple(inputs))
    for input_grad in (True, False):
        torch.library.opcheck(torch.ops.mixer_nerf.mlca_bwd.default, (grad, *inputs, input_grad))


def valid(**changes):
    T, C, D = 5, 4, 3
    args = {
        "encoded": torch.zeros(6, T * D),
        "lift": torch.zeros(C, D),
        "token_weight": torch.zeros(T, T),
        "token_bias": torch.zeros(T),
        "channel_weight": torch.zeros(C, C),
        "channel_bias": torch.zeros(C),
    }
    return {**args, **changes}


@pytest.mark.parametrize("backend", ["torch", "kernel"] if _extension.available() else ["torch"])
@pytest.mark.parametrize(
    "changes, error, match",
    [
        ({"encoded": [[0.0] * 15]}, TypeError, "encoded"),
        ({"encoded": torch.zeros(6, 15, dtype=torch.int64)}, TypeError, "encoded"),
        ({"encoded": torch.zeros(6, 14)}, ValueError, "encoded"),
        ({"encoded": torch.zeros(6, 5, 3)}, ValueError, "encoded"),
        ({"encoded": torch.tensor(0.0)}, ValueError, "encoded"),
        ({"lift": torch.zeros(4)}, ValueError, "lift"),
        ({"lift": torch.zeros(4, 0)}, ValueError, "lift"),
        ({"lift": torch.zeros(4, 2)}, ValueError, "encoded"),  # D = 2 does not match 15 = 5 * 3
        ({"token_weight": torch.zeros(5, 4)}, ValueError, "token_weight"),
        ({"token_weight": torch.zeros(0, 0), "encoded": torch.zeros(6, 0)}, ValueError, "token_weight"),
        ({"token_weight": torch.zeros(MAX_TOKENS + 1, MAX_TOKENS + 1), "encoded": torch.zeros(1, 3 * MAX_TOKENS + 3)},
         ValueError, "token_weight"),
        ({"lift": torch.zeros(MAX_CHANNELS + 1, 3)}, ValueError, "lift"),
        ({"lift": torch.zeros(4, MAX_TOKEN_DIM + 1)}, ValueError, "lift"),
        ({"token_bias": torch.zeros(4)}, ValueError, "token_bias"),
        ({"token_bias": torch.zeros(5, 1)}, ValueError, "token_bias"),
        ({"channel_weight": torch.zeros(4, 3)}, ValueError, "channel_weight"),
        ({"channel_weight": torch.zeros(3, 3)}, ValueError, "channel_weight"),
        ({"channel_bias": torch.zeros(5)}, ValueError, "channel_bias"),
        ({"channel_bias": torch.zeros(4, dtype=torch.int32)}, TypeError, "channel_bias"),
        ({"lift": torch.zeros(4, 3, dtype=torch.float64)}, TypeError, "lift is torch.float64"),
        ({"encoded": torch.zeros(6, 15, dtype=torch.float16)}, TypeError, "encoded is torch.float16"),
        ({"token_bias": torch.zeros(5, device="meta")}, ValueError, "token_bias on meta"),
        ({"encoded": torch.zeros(6, 15, device="meta")}, ValueError, "encoded on meta"),
    ],
)
def test_bad_input(changes, error, match, backend):
    with pytest.raises(error, match=match):
        mlca(**valid(**changes), backend=backend)


def test_bad_backend():
    with pytest.raises(ValueError, match="backend"):
        mlca(**valid(), backend="cuda")
    with pytest.raises(ValueError, match="backend"):
        MLCA(5, 3, 4, backend="fast")


# ------------------------------------------------------------------------------------- module


def randomized(module, gen):
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.3)
    return module


@needs_kernels
def test_module_kernel_matches_torch_backend(gen):
    kernel = randomized(MLCA(21, 3, 8, backend="kernel"), gen)
    torch_ = MLCA(21, 3, 8, backend="torch")
    torch_.load_state_dict(kernel.state_dict())
    x = torch.randn(3, 11, 63, generator=gen)
    outs = []
    for module in (kernel, torch_):
        module.zero_grad()
        out = module(x)
        out.pow(2).sum().backward()
        outs.append((out, [p.grad for p in module.parameters()]))
    torch.testing.assert_close(outs[0][0], outs[1][0], rtol=1e-5, atol=1e-5)
    for a, b in zip(outs[0][1], outs[1][1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


def test_module_keeps_its_checkpoint_layout():
    """Same parameter names, shapes and init as before the fused op: old checkpoints load."""
    module = MLCA(21, 3, 8)
    shapes = {name: tuple(t.shape) for name, t in module.state_dict().items()}
    assert shapes == {
        "lift": (8, 3),
        "token_weight": (21, 21),
        "token_bias": (21,),
        "channel_weight": (8, 8),
        "channel_bias": (8,),
    }
    assert torch.equal(module.lift, torch.eye(8, 3))
    assert all(bool((getattr(module, n) == 0).all()) for n in shapes if n != "lift")


@needs_kernels
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-5), (torch.bfloat16, 5e-2)])
def test_module_casts_its_parameters_to_the_input_dtype(dtype, tol, gen):
    module = randomized(MLCA(9, 3, 8, backend="kernel"), gen)
    x = torch.randn(20, 27, generator=gen)
    out = module(x.to(dtype))
    assert out.dtype == dtype
    torch.testing.assert_close(out.float(), module(x), rtol=tol, atol=tol)
    out.float().sum().backward()
    assert module.token_weight.grad.dtype == torch.float32


@needs_kernels
def test_module_on_packed_rows_dispatches_only_its_kernels(gen):
    """Parameters in the input's dtype and rows (N, T*D): no casts, no reshapes, forward or backward
    (autograd's detach of each accumulated gradient aside)."""
    module = randomized(MLCA(21, 3, 8, backend="kernel"), gen)
    x, upstream = torch.randn(30, 63, generator=gen), torch.randn(30, 168, generator=gen)
    with dispatched_ops() as ops:
        module(x).backward(upstream)
    assert ops["mixer_nerf.mlca_fwd"] == ops["mixer_nerf.mlca_bwd"] == 1
    assert set(ops) <= {"mixer_nerf.mlca_fwd", "mixer_nerf.mlca_bwd", "aten.detach"}, ops


@needs_kernels
def test_module_under_autocast_computes_in_float32(gen):
    module = randomized(MLCA(21, 3, 8, backend="kernel"), gen)
    x = torch.randn(30, 63, generator=gen)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = module(x)
    assert out.dtype == torch.float32
    assert torch.equal(out, module(x))


# --------------------------------------------------------------------------------------- CUDA


CUDA_SHAPES = [
    ((1,), 21, 8, 3),
    ((65536 + 77,), 21, 8, 3),
    ((1000,), 9, 8, 3),
    ((300,), 20, 8, 3),  # the model's C and D in the T = 21 bucket: the run-time-size kernels
    ((65536 + 77,), 21, 3, 3),  # mlca_channels = 3: exact-size kernels too
    ((1000,), 9, 3, 3),
    ((333,), 30, 16, 3),
    ((129,), 32, 4, 3),
    ((50,), 5, 3, 3),
    ((41,), 25, 6, 2),
    ((7, 3), 13, 24, 5),
    ((0,), 21, 8, 3),
]


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize("lead, T, C, D", CUDA_SHAPES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu_and_reference(lead, T, C, D, dtype, gen):
    inputs = make_inputs(lead, T, C, D, gen, dtype)
    grad = random_grad(inputs, C, gen)
    cpu_out, cpu_grads = forward_backward(inputs, grad, "kernel")
    want_out, want_grads = truth(inputs, grad)
    cuda_inputs, cuda_grad = [t.cuda() for t in inputs], grad.cuda()

    poison_allocator([cpu_out])
    out = mlca(*cuda_inputs, backend="kernel")
    leaves = [t.clone().requires_grad_() for t in cuda_inputs]
    out_for_grad = mlca(*leaves, backend="kernel")
    poison_allocator(inputs)
    grads = torch.autograd.grad(out_for_grad, leaves, cuda_grad)

    assert out.dtype == dtype and out.device.type == "cuda"
    # Sums over 65k points in float32: a little more rounding than the CPU's chunked sums.
    rel = REL[dtype] * (5 if dtype == torch.float32 else 1)
    assert_close(out, want_out, rel, "cuda out vs reference")
    assert_close(list(grads), want_grads, rel, "cuda grads vs reference")
    assert_close(out, cpu_out, rel, "cuda out vs cpu")
    assert_close(list(grads), cpu_grads, rel, "cuda grads vs cpu")


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_cuda_half_precision(dtype, gen):
    inputs = make_inputs((3000,), 21, 8, 3, gen, dtype, device="cuda")
    grad = random_grad(inputs, 8, gen)
    out, grads = forward_backward(inputs, grad, "kernel")
    want_out, want_grads = truth(inputs, grad)
    assert_close(out, want_out, REL[dtype], "cuda half out")
    assert_close(grads, want_grads, REL[dtype], "cuda half grads")


@pytest.mark.cuda
@pytest.mark.profiler
@on_cuda
@needs_kernels
@pytest.mark.parametrize("T, C, dtype, channels", [(21, 8, torch.float32, 8), (9, 8, torch.float32, 8),
                                                    (21, 3, torch.float32, 3), (9, 3, torch.float32, 3),
                                                    (20, 8, torch.float32, 0), (21, 8, torch.float64, 0),
                                                    (21, 5, torch.float32, 0)])
def test_cuda_the_models_sizes_run_the_exact_size_kernels(T, C, dtype, channels, gen):
    """float32 at the model's sizes (T = 21 or 9, C = 8 or 3, D = 3) runs the kernels compiled for
    them (their C in the name); other sizes and dtypes the run-time-size ones (channels 0)."""
    inputs = make_inputs((500,), T, C, 3, gen, dtype, device="cuda")
    grad = random_grad(inputs, C, gen)
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
        forward_backward(inputs, grad, "kernel")
        torch.cuda.synchronize()
    names = {e.name for e in prof.events() if "mlca_" in e.name}
    bucket = 21 if T > 9 else 9
    for kernel in ("mlca_forward", "mlca_backward"):
        assert any(f"{kernel}<{'float' if dtype == torch.float32 else 'double'}, {bucket}, {channels}>" in n
                   for n in names), names


@pytest.mark.cuda
@on_cuda
@needs_kernels
@pytest.mark.parametrize("rows", [1003, 100_003])  # the small one is racecheck's (it skips 100003)
def test_cuda_deterministic_without_input_grad(rows, gen):
    inputs = make_inputs((rows,), 21, 8, 3, gen, device="cuda")
    grad = random_grad(inputs, 8, gen)
    first = forward_backward(inputs, grad, "kernel", input_grad=False)
    second = forward_backward(inputs, grad, "kernel", input_grad=False)
    assert first[1][0] is None
    assert torch.equal(first[0], second[0])
    assert all(torch.equal(a, b) for a, b in zip(first[1][1:], second[1][1:], strict=True))
    _, want = truth(inputs, grad)
    assert_close(first[1], [None, *want[1:]], 1e-4, "cuda weight grads")


@pytest.mark.cuda
@on_cuda
def test_cuda_mixed_devices_raise(gen):
    args = valid(lift=torch.zeros(4, 3, device="cuda"))
    with pytest.raises(ValueError, match="lift on cuda"):
        mlca(**args, backend="auto")
