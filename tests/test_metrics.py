"""PSNR, SSIM and the offline-only LPIPS helper."""

from __future__ import annotations

import math

import pytest
import torch

from mixer_nerf import lpips_alex
from mixer_nerf.metrics import lpips, lpips_available, lpips_unavailable_reason, psnr, ssim


def _noisy_pair(n: int = 2, size: int = 24) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    target = torch.rand(n, size, size, 3, generator=g)
    pred = (target + 0.1 * torch.randn(target.shape, generator=g)).clamp(0, 1)
    return pred, target


def test_psnr_of_identical_images_is_inf():
    img = torch.rand(8, 8, 3)
    assert psnr(img, img.clone()).item() == math.inf


def test_psnr_known_mse_and_per_image_batch():
    target = torch.full((2, 4, 4, 3), 0.5)
    pred = target.clone()
    pred[0] += 0.1  # MSE 0.01 -> 20 dB
    pred[1] += 0.01  # MSE 1e-4 -> 40 dB
    values = psnr(pred, target)
    assert values.shape == (2,)
    torch.testing.assert_close(values, torch.tensor([20.0, 40.0]))
    assert psnr(pred[0], target[0]).shape == ()


def test_ssim_of_identical_images_is_one():
    pred, _ = _noisy_pair()
    torch.testing.assert_close(ssim(pred, pred.clone()), torch.ones(2))


def test_ssim_of_constant_images_has_closed_form():
    # No structure: only the luminance term (2ab + C1) / (a^2 + b^2 + C1) remains.
    a, b, c1 = 0.5, 0.8, 0.01**2
    value = ssim(torch.full((16, 16, 3), a), torch.full((16, 16, 3), b))
    assert value.shape == ()
    assert value.item() == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-5)


def test_ssim_orders_by_noise_and_is_per_image():
    pred, target = _noisy_pair()
    worse = (target + 0.3 * (pred - target) / 0.1).clamp(0, 1)
    values = ssim(pred, target)
    assert values.shape == (2,) and (values < 1).all() and (values > 0).all()
    assert (ssim(worse, target) < values).all()
    torch.testing.assert_close(ssim(pred[1], target[1]), values[1])


@pytest.mark.parametrize(
    "pred, target, error",
    [
        (torch.rand(8, 8, 3), torch.rand(8, 9, 3), ValueError),
        (torch.rand(8, 8, 4), torch.rand(8, 8, 4), ValueError),
        (torch.zeros(8, 8, 3, dtype=torch.uint8), torch.zeros(8, 8, 3, dtype=torch.uint8), TypeError),
    ],
)
def test_metrics_reject_bad_inputs(pred, target, error):
    with pytest.raises(error):
        psnr(pred, target)


def test_ssim_rejects_images_smaller_than_the_window():
    with pytest.raises(ValueError, match="11x11"):
        ssim(torch.rand(8, 8, 3), torch.rand(8, 8, 3))


def test_lpips_reports_why_it_is_unavailable(monkeypatch):
    assert "unknown LPIPS backbone" in lpips_unavailable_reason("resnet")
    monkeypatch.setattr(lpips_alex, "weights_path", lambda: None)  # as where they are not installed
    reason = lpips_unavailable_reason()
    assert reason.startswith("LPIPS unavailable") and "\n" not in reason
    pred, target = _noisy_pair(1, 32)
    with pytest.warns(RuntimeWarning, match="LPIPS unavailable"):
        assert lpips(pred, target) is None


def test_lpips_when_available():
    if not lpips_available():
        pytest.skip(lpips_unavailable_reason())
    pred, target = _noisy_pair(2, 32)
    values = lpips(pred, target)
    assert values.shape == (2,) and (values > 0).all()
    torch.testing.assert_close(lpips(target, target), torch.zeros(2), atol=1e-6, rtol=0)
