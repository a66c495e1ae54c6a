"""The export error and the optional libraries behind it."""

from __future__ import annotations

from types import ModuleType


class ExportError(RuntimeError):
    """An export cannot be made from this checkpoint, or a library it needs is missing."""


def require_trimesh() -> ModuleType:
    """``trimesh``, or an ExportError saying how to install it."""
    try:
        import trimesh
    except ImportError as e:
        raise ExportError(
            "mesh and point-cloud exports need trimesh: pip install 'mixer_nerf[export]'"
        ) from e
    return trimesh


def require_mcubes() -> ModuleType:
    """``mcubes`` (PyMCubes), or an ExportError saying how to install it."""
    try:
        import mcubes
    except ImportError as e:
        raise ExportError("mesh export needs PyMCubes: pip install 'mixer_nerf[export]'") from e
    return mcubes
