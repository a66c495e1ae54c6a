"""The value checks' reductions (ops/_checks.py): one min instead of a comparison's any(), with the
same verdict as the comparison on every input, NaNs, infinities, zeros and subnormals included."""

from __future__ import annotations

import warnings

import pytest
import torch

from mixer_nerf.ops._checks import check_in_range, has_descent, has_negative

FLOATS = [torch.float16, torch.bfloat16, torch.float32, torch.float64]
SPECIALS = [float("nan"), float("inf"), -float("inf"), 0.0, -0.0]


def spiced(n, dtype, gen, specials):
    """n values around 0 with a few special values written over random places."""
    t = torch.randn(n, generator=gen, dtype=torch.float64)
    where = torch.randint(0, n, (len(specials),), generator=gen)
    t[where] = torch.tensor(specials, dtype=torch.float64)
    return t.to(dtype)


@pytest.mark.parametrize("dtype", FLOATS)
def test_has_negative_agrees_with_the_comparison(gen, dtype):
    for trial in range(200):
        specials = [SPECIALS[i] for i in torch.randint(0, 5, (trial % 4,), generator=gen)]
        t = spiced(int(torch.randint(1, 40, (), generator=gen)), dtype, gen, specials)
        if trial % 3 == 0:
            t = t.abs()  # no negative left, unless a special is one
        assert has_negative(t) == bool((t < 0).any()), t


@pytest.mark.parametrize("dtype", FLOATS)
def test_has_descent_agrees_with_the_comparison(gen, dtype):
    for trial in range(200):
        n = int(torch.randint(1, 40, (), generator=gen))
        specials = [SPECIALS[i] for i in torch.randint(0, 5, (trial % 4,), generator=gen)]
        low = spiced(n, dtype, gen, specials)
        step = torch.rand(n, generator=gen, dtype=torch.float64).to(dtype)
        high = low + step if trial % 2 else low - step * (torch.rand(n, generator=gen) < 0.1)
        assert has_descent(low, high) == bool((high < low).any()), (low, high)


@pytest.mark.parametrize(
    "values, negative",
    [([], False), ([float("nan"), 1.0], False), ([float("nan"), 1.0, -1.0], True), ([0.0, -0.0], False)],
)
def test_has_negative_cases(values, negative):
    assert has_negative(torch.tensor(values)) is negative
    assert has_negative(torch.tensor(values, dtype=torch.float64)) is negative


def test_has_descent_cases():
    nan, inf = float("nan"), float("inf")
    t = torch.tensor
    assert not has_descent(t([]), t([]))
    assert not has_descent(t([1.0, 2.0]), t([1.0, 2.0]))  # equal: a zero gap, not a descent
    assert not has_descent(t([0.0, 1.0]), t([-0.0, 1.0]))  # a -0 gap, and -0 is not below +0
    assert has_descent(t([nan, 2.0]), t([nan, 1.0]))  # the NaN pair hides nothing
    assert not has_descent(t([nan, 1.0]), t([0.0, 2.0]))
    assert not has_descent(t([inf, -inf]), t([inf, -inf]))  # inf - inf is NaN, and no descent
    assert has_descent(t([0.0]), t([-inf]))
    assert has_descent(t([3], dtype=torch.int64), t([2], dtype=torch.int64))
    assert not has_descent(t([2], dtype=torch.int64), t([2], dtype=torch.int64))


def test_has_descent_sees_a_subnormal_gap_flushed_to_zero():
    """With denormals flushed, high - low of two close normal values below 2e-38 is 0: still a descent."""
    low, high = torch.tensor([1.5e-38, 0.0]), torch.tensor([1.4e-38, 0.0])
    if not torch.set_flush_denormal(True):
        pytest.skip("this CPU cannot flush denormals")
    try:
        assert float((high - low).amin()) == 0 and has_descent(low, high)
    finally:
        torch.set_flush_denormal(False)


def test_tensors_that_require_grad_are_checked_without_a_warning():
    """Op inputs usually require grad: reading their min must not warn about it."""
    t = torch.rand(5, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not has_negative(t) and not has_descent(t, t + 1)


@pytest.mark.parametrize("dtype", FLOATS)
def test_check_in_range_agrees_with_the_comparison(gen, dtype):
    """[0, 1] by the min and max; a NaN anywhere fails, as the elementwise test did."""
    for trial in range(200):
        picks = torch.randint(0, 5, (trial % 3,), generator=gen)
        specials = [[float("nan"), 1.0, 0.0, -0.0, float("inf")][i] for i in picks]
        t = spiced(int(torch.randint(1, 40, (), generator=gen)), dtype, gen, specials)
        t = t.abs().clamp(max=1) if trial % 2 else t
        inside = bool(((t >= 0) & (t <= 1)).all())
        try:
            check_in_range("u", t, 0.0, 1.0)
            refused = False
        except ValueError:
            refused = True
        assert refused is not inside, t
