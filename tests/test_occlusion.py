"""FreeNeRF's occlusion regularisation on the proposal sampler's main field."""

from __future__ import annotations

import pytest
import torch

from mixer_nerf.render.skipping import occlusion_loss


def test_counts_the_weight_of_the_intervals_in_front_of_the_camera():
    edges = torch.tensor([[0.0, 0.05, 0.2, 0.6, 1.0], [0.0, 0.3, 0.5, 0.7, 1.0]])
    weights = torch.tensor([[0.5, 0.2, 0.2, 0.1], [0.4, 0.3, 0.2, 0.1]])
    # ray 0: midpoints 0.025, 0.125, 0.4, 0.8 -> first two below 0.15; ray 1: none below 0.15
    assert occlusion_loss(weights, edges, 0.15).item() == pytest.approx((0.7 + 0.0) / 2)
    assert occlusion_loss(weights, edges, 0.99).item() == pytest.approx(1.0)


def test_gradient_reaches_only_the_penalised_weights():
    edges = torch.linspace(0, 1, 9).expand(3, 9)
    weights = torch.rand(3, 8, requires_grad=True)
    occlusion_loss(weights, edges, 0.3).backward()
    torch.testing.assert_close(weights.grad, (edges[:, :-1] + 1 / 16 < 0.3).float() / 3)


def test_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="weights \\(R, N\\) and edges"):
        occlusion_loss(torch.rand(3, 8), torch.rand(3, 8), 0.1)
