"""Chooses between the compiled kernels and the PyTorch reference path for one call."""

from __future__ import annotations

import torch

from .. import _extension
from ._checks import check_backend
from ._kernel_op import register_declared


def use_kernel(backend: str, device: torch.device) -> bool:
    """True to run the compiled kernel, False for the reference path.

    ``"torch"``: never. ``"kernel"``: always, raising :class:`ExtensionUnavailable` if the
    extension or a kernel for ``device`` is missing. ``"auto"``: when both are there. Picking a
    kernel registers the ops' fake kernels and backwards (see :mod:`mixer_nerf.ops._kernel_op`).
    """
    check_backend(backend)
    if backend == "torch":
        return False
    if device.type == "cpu":
        supported = _extension.available()
    elif device.type == "cuda":
        supported = _extension.has_cuda_kernels()
    else:
        supported = False
    if backend == "kernel" and not supported:
        _extension.load()  # raises with the build error if that is the reason
        raise _extension.ExtensionUnavailable(f"mixer_nerf has no kernels for device {device}")
    if supported:
        register_declared()
    return supported
