"""mip-NeRF 360's distortion loss: the O(N) prefix-sum form against the O(N^2) definition."""

from __future__ import annotations

import pytest
import torch
from dispatch_count import dispatched_ops

from mixer_nerf.render.skipping import distortion_loss


def naive_distortion(weights: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Eq. 15 of mip-NeRF 360 as written: every pair of intervals, mean over rays."""
    mids = 0.5 * (edges[:, 1:] + edges[:, :-1])
    pairs = weights[:, :, None] * weights[:, None, :] * (mids[:, :, None] - mids[:, None, :]).abs()
    within = (weights.square() * (edges[:, 1:] - edges[:, :-1])).sum(-1) / 3
    return (pairs.sum((-1, -2)) + within).mean()


def random_rays(rays: int, n: int, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights summing to at most 1 and sorted edges in [0, 1] (drawn fresh each run)."""
    weights = torch.rand(rays, n, dtype=dtype)
    weights = weights / weights.sum(-1, keepdim=True) * torch.rand(rays, 1, dtype=dtype)
    inner = torch.rand(rays, n - 1, dtype=dtype).sort(-1).values
    edges = torch.cat([torch.zeros(rays, 1, dtype=dtype), inner, torch.ones(rays, 1, dtype=dtype)], -1)
    return weights, edges


@pytest.mark.parametrize("rays, n", [(1, 1), (3, 2), (16, 7), (64, 48)])
def test_matches_the_pairwise_definition(rays, n):
    weights, edges = random_rays(rays, n)
    torch.testing.assert_close(distortion_loss(weights, edges), naive_distortion(weights, edges))


def test_gradient_matches_finite_differences_in_weights_and_edges():
    weights, edges = random_rays(4, 6)
    weights.requires_grad_(True)
    edges.requires_grad_(True)
    assert torch.autograd.gradcheck(distortion_loss, (weights, edges))
    got = torch.autograd.grad(distortion_loss(weights, edges), (weights, edges))
    want = torch.autograd.grad(naive_distortion(weights, edges), (weights, edges))
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w)


def test_zero_weights_give_zero():
    _, edges = random_rays(5, 8)
    assert distortion_loss(torch.zeros(5, 8, dtype=torch.float64), edges).item() == 0.0


def test_all_weight_in_one_interval_leaves_only_its_own_term():
    _, edges = random_rays(3, 9)
    weights = torch.zeros(3, 9, dtype=torch.float64)
    weights[:, 4] = torch.tensor([0.2, 0.7, 1.0], dtype=torch.float64)
    width = edges[:, 5] - edges[:, 4]
    expected = (weights[:, 4].square() * width / 3).mean()
    torch.testing.assert_close(distortion_loss(weights, edges), expected)
    single = torch.tensor([[0.25, 0.75]], dtype=torch.float64)  # one interval per ray
    torch.testing.assert_close(distortion_loss(torch.tensor([[0.8]], dtype=torch.float64), single),
                               torch.tensor(0.8**2 * 0.5 / 3, dtype=torch.float64))


def test_spreading_weight_apart_costs_more_than_keeping_it_together():
    edges = torch.linspace(0, 1, 11, dtype=torch.float64)[None]
    together = torch.zeros(1, 10, dtype=torch.float64)
    together[0, 4:6] = 0.5
    apart = torch.zeros(1, 10, dtype=torch.float64)
    apart[0, [0, 9]] = 0.5
    assert distortion_loss(apart, edges) > distortion_loss(together, edges)


@pytest.mark.parametrize("shapes", [((4, 6), (4, 6)), ((4, 6), (3, 7)), ((6,), (7,))])
def test_rejects_mismatched_shapes(shapes):
    with pytest.raises(ValueError, match="weights"):
        distortion_loss(torch.rand(*shapes[0]), torch.rand(*shapes[1]))


def test_forward_and_backward_never_read_a_value_back_to_the_host():
    weights, edges = random_rays(8, 5, torch.float32)
    weights.requires_grad_(True)
    with dispatched_ops() as ops:
        distortion_loss(weights, edges).backward()
    assert "aten._local_scalar_dense" not in ops and "aten.item" not in ops, ops  # a GPU sync each
