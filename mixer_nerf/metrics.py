"""Image quality metrics for rendered views: PSNR, SSIM and (when its weights are installed) LPIPS.

Images are float tensors in [0, 1], (H, W, 3) for one image or (N, H, W, 3) for a batch; every
metric returns one value per image: a 0-d tensor or an (N,) tensor. Clamp predictions to [0, 1]
first: the metrics do not, so that out-of-range renders are not hidden (LPIPS refuses them).
"""

from __future__ import annotations

import functools
import warnings

import torch

from . import lpips_alex

LPIPS_BACKBONES = ("alex",)
LPIPS_MIN_SIZE = lpips_alex.MIN_SIZE


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB for a peak value of 1: -10 log10(MSE).

    Identical images give +inf (not a capped value): a finite cap would silently bias averages.
    Average the per-image values over a test set, as NeRF papers report.

    Args:
        pred, target: (H, W, 3) or (N, H, W, 3), values in [0, 1].

    Returns:
        () or (N,) float tensor.
    """
    _check_images(pred, target)
    mse = (pred.double() - target.double()).square().mean(dim=(-3, -2, -1))
    return (-10.0 * torch.log10(mse)).to(pred.dtype)


def ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004): 11x11 Gaussian window, sigma 1.5, K1 0.01,
    K2 0.03, data range 1, averaged over the colour channels and valid window positions.

    Args:
        pred, target: (H, W, 3) or (N, H, W, 3) with H, W >= 11, values in [0, 1].

    Returns:
        () or (N,) float tensor; 1 for identical images.
    """
    from torchmetrics.functional.image import structural_similarity_index_measure

    _check_images(pred, target)
    if min(pred.shape[-3:-1]) < 11:
        raise ValueError(f"ssim needs images of at least 11x11 pixels, got shape {tuple(pred.shape)}")
    values = structural_similarity_index_measure(
        _to_nchw(pred).double(),
        _to_nchw(target).double(),
        gaussian_kernel=True,
        sigma=1.5,
        kernel_size=11,
        data_range=1.0,
        k1=0.01,
        k2=0.03,
        reduction="none",
    )
    return values.to(pred.dtype).reshape(pred.shape[:-3])


def lpips_unavailable_reason(net: str = "alex") -> str | None:
    """None if LPIPS with backbone ``net`` can run, else a one-line reason naming what to install.

    Only the AlexNet backbone ("alex", the usual choice for NeRF papers) is provided: see
    :mod:`mixer_nerf.lpips_alex` for where its weights come from. Nothing is ever downloaded.
    """
    if net not in LPIPS_BACKBONES:
        return f"unknown LPIPS backbone {net!r} (choose from {list(LPIPS_BACKBONES)})"
    return lpips_alex.unavailable_reason()


def lpips_available(net: str = "alex") -> bool:
    """Whether :func:`lpips` can compute a value offline for backbone ``net``."""
    return lpips_unavailable_reason(net) is None


def lpips(pred: torch.Tensor, target: torch.Tensor, net: str = "alex") -> torch.Tensor | None:
    """Learned perceptual distance (Zhang et al. 2018, v0.1 linear heads; lower is closer), or None
    with a warning giving the reason when its weights are not installed.

    Args:
        pred, target: (H, W, 3) or (N, H, W, 3) with H, W >= LPIPS_MIN_SIZE, values in [0, 1].
        net: backbone; only "alex".

    Returns:
        () or (N,) float tensor; 0 for identical images.
    """
    _check_images(pred, target)
    if min(pred.shape[-3:-1]) < LPIPS_MIN_SIZE:
        raise ValueError(
            f"lpips needs images of at least {LPIPS_MIN_SIZE}x{LPIPS_MIN_SIZE} pixels, "
            f"got shape {tuple(pred.shape)}"
        )
    for name, images in (("pred", pred), ("target", target)):
        if not ((images >= 0) & (images <= 1)).all():
            raise ValueError(f"lpips needs {name} values in [0, 1] (clamp renders first; NaN is refused)")
    reason = lpips_unavailable_reason(net)
    if reason is not None:
        warnings.warn(reason, RuntimeWarning, stacklevel=2)
        return None
    model = _lpips_model(pred.device)
    with torch.no_grad():
        values = model(_to_nchw(pred).float(), _to_nchw(target).float())
    return values.reshape(pred.shape[:-3]).to(pred.dtype)


@functools.cache
def _lpips_model(device: torch.device) -> lpips_alex.AlexLPIPS:
    return lpips_alex.load().to(device)


def _check_images(pred: torch.Tensor, target: torch.Tensor) -> None:
    if pred.shape != target.shape:
        raise ValueError(
            f"pred and target must have one shape, got {tuple(pred.shape)} and {tuple(target.shape)}"
        )
    if pred.dim() not in (3, 4) or pred.shape[-1] != 3:
        raise ValueError(f"images must be (H, W, 3) or (N, H, W, 3), got {tuple(pred.shape)}")
    if not (pred.is_floating_point() and target.is_floating_point()):
        raise TypeError(f"images must be floating point, got {pred.dtype} and {target.dtype}")


def _to_nchw(images: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) or (N, H, W, 3) -> (N, 3, H, W)."""
    return images.reshape(-1, *images.shape[-3:]).permute(0, 3, 1, 2)
