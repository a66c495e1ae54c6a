"""The ops' autograd in C++ (csrc/autograd.cpp), across every op with a backward kernel: each
wrapper's output records a C++ node (no Python autograd Function), float64 gradients match
finite differences through it, a double backward raises, and opcheck passes on inputs that
require grad (autograd registration, AOT dispatch). Each op's own file tests its values."""

from __future__ import annotations

import pytest
import torch

from mixer_nerf import _extension
from mixer_nerf.ops import (
    composite,
    composite_packed,
    mlca,
    positional_encoding,
    ray_scale,
    sample_pdf,
    sample_pdf_packed,
    segment_mean,
)

pytestmark = pytest.mark.skipif(not _extension.available(), reason="mixer_nerf kernels not built")

OFFSETS = torch.tensor([0, 3, 3, 7])  # three rays, one of them empty


def leaf(gen, *shape, low=0.0):
    return (low + torch.rand(*shape, generator=gen, dtype=torch.float64)).requires_grad_()


def sorted_bins(gen, rays, edges):
    return (torch.rand(rays, edges, generator=gen, dtype=torch.float64).cumsum(-1)).requires_grad_()


def packed_bins(gen):
    """Ray r's B_r + 1 edges from offsets[r] + r (sample_pdf_packed's layout)."""
    counts = OFFSETS.diff()
    rows = [torch.rand(int(c) + 1, generator=gen, dtype=torch.float64).cumsum(0) for c in counts]
    return torch.cat(rows).requires_grad_()


def intervals(gen, shape):
    starts = torch.rand(*shape, generator=gen, dtype=torch.float64).cumsum(-1)
    return starts, starts + 0.1


# name -> (gen -> the wrapper's differentiable inputs, (*inputs) -> the output to differentiate)
CASES = {
    "positional_encoding": (lambda g: [leaf(g, 5, 3)], lambda x: positional_encoding(x, 3, backend="kernel")),
    "sample_pdf": (
        lambda g: [sorted_bins(g, 4, 6), leaf(g, 4, 5, low=0.1)],
        lambda b, w: sample_pdf(b, w, 7, deterministic=True, backend="kernel"),
    ),
    "sample_pdf, stratified": (
        lambda g: [sorted_bins(g, 4, 6), leaf(g, 4, 5, low=0.1)],
        lambda b, w: sample_pdf(b, w, 7, generator=torch.Generator().manual_seed(3), backend="kernel"),
    ),
    "sample_pdf_packed": (
        lambda g: [packed_bins(g), leaf(g, 7, low=0.1)],
        lambda b, w: sample_pdf_packed(b, w, OFFSETS, 5, deterministic=True, backend="kernel"),
    ),
    "sample_pdf_packed, stratified": (
        lambda g: [packed_bins(g), leaf(g, 7, low=0.1)],
        lambda b, w: sample_pdf_packed(b, w, OFFSETS, 5, generator=torch.Generator().manual_seed(3), backend="kernel"),
    ),
    "mlca": (
        lambda g: [leaf(g, 6, 4 * 3), leaf(g, 5, 3), leaf(g, 4, 4), leaf(g, 4), leaf(g, 5, 5), leaf(g, 5)],
        lambda *a: mlca(*a, backend="kernel"),
    ),
    "segment_mean": (lambda g: [leaf(g, 7, 4)], lambda v: segment_mean(v, OFFSETS, backend="kernel")),
    "ray_scale": (lambda g: [leaf(g, 7, 4), leaf(g, 3, 4)], lambda f, s: ray_scale(f, s, OFFSETS, backend="kernel")),
    "composite": (
        lambda g: [leaf(g, 3, 5), leaf(g, 3, 5, 3), *(t.requires_grad_() for t in intervals(g, (3, 5))), leaf(g, 3)],
        lambda s, c, t0, t1, bg: composite(s, c, t0, t1, bg, backend="kernel").color,
    ),
    "composite_packed": (
        lambda g: [leaf(g, 7), leaf(g, 7, 3), *(t.requires_grad_() for t in intervals(g, (7,))), leaf(g, 3, 3)],
        lambda s, c, t0, t1, bg: composite_packed(s, c, t0, t1, OFFSETS, bg, backend="kernel").color,
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_backward_is_a_cpp_node_and_exact(gen, case):
    make, fn = CASES[case]
    inputs = make(gen)
    out = fn(*inputs)
    assert "KernelFunction" in out.grad_fn.name()
    assert torch.autograd.gradcheck(fn, tuple(inputs))


@pytest.mark.parametrize("case", ["positional_encoding", "mlca", "composite"])
def test_double_backward_raises(gen, case):
    """A backward that would have to be differentiated (create_graph, an upstream gradient that
    depends on the inputs) says so instead of returning gradients with no history."""
    make, fn = CASES[case]
    inputs = make(gen)
    with pytest.raises(RuntimeError, match="differentiable once"):
        torch.autograd.grad(fn(*inputs).pow(2).sum(), inputs[0], create_graph=True)


def test_only_the_wanted_gradients(gen):
    """Inputs that want no gradient get none, and the op's flags skip their work (mlca's encoding)."""
    make, fn = CASES["mlca"]
    encoded, *weights = make(gen)
    encoded.requires_grad_(False)
    grads = torch.autograd.grad(fn(encoded, *weights).sum(), weights)
    assert all(g is not None and g.shape == w.shape for g, w in zip(grads, weights))


def test_inference_mode_takes_any_strides(gen):
    """Inference mode skips autograd kernels, where the inputs are made contiguous: the wrapper does it."""
    x = torch.rand(3, 5, generator=gen, dtype=torch.float64).t()
    assert not x.is_contiguous()
    want = positional_encoding(x.contiguous(), 3, backend="kernel")
    with torch.inference_mode():
        got = positional_encoding(x, 3, backend="kernel")
    torch.testing.assert_close(got, want)


def test_opcheck_with_grad(gen):
    """The forward ops' autograd as torch.library checks it (registration, AOT dispatch, fakes)."""
    positional_encoding(torch.zeros(1, 3), 1, backend="kernel")  # loads the ops, registers the fakes
    x = torch.rand(5, 3, generator=gen).requires_grad_()
    torch.library.opcheck(torch.ops.mixer_nerf.positional_encoding_fwd.default, (x, 3, True, 3.14))
    values = torch.rand(7, 4, generator=gen).requires_grad_()
    torch.library.opcheck(torch.ops.mixer_nerf.segment_mean_fwd.default, (values, OFFSETS))
    scale = torch.rand(3, 4, generator=gen).requires_grad_()
    torch.library.opcheck(torch.ops.mixer_nerf.ray_scale_fwd.default, (values, scale, OFFSETS))
    bins = torch.rand(4, 6, generator=gen).cumsum(-1).requires_grad_()
    weights = (0.1 + torch.rand(4, 5, generator=gen)).requires_grad_()
    u = torch.rand(4, 7, generator=gen).sort(-1).values
    torch.library.opcheck(torch.ops.mixer_nerf.sample_pdf_fwd.default, (bins, weights, u, 0.0))


def test_a_strided_view_passes_its_gradient_to_its_base(gen):
    """The autograd kernel makes a view contiguous with a differentiable copy: the base gets the gradient."""
    base = leaf(gen, 3, 5)
    x = base.t()
    assert not x.is_contiguous()
    assert torch.autograd.gradcheck(lambda b: positional_encoding(b.t(), 3, backend="kernel"), (base,))
    (grad,) = torch.autograd.grad(positional_encoding(x, 3, backend="kernel").sum(), base)
    (want,) = torch.autograd.grad(positional_encoding(x, 3, backend="torch").sum(), base)
    torch.testing.assert_close(grad, want)
