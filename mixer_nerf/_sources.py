"""Where the C++/CUDA sources live and a content hash of them.

Imported by ``setup.py`` (before torch may exist) and by the runtime loader, so it must not
import torch. The hash lets the loader tell a prebuilt extension built from other sources.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

CSRC = Path(__file__).resolve().parent.parent / "csrc"


def cpp_sources(root: Path = CSRC) -> list[Path]:
    """The C++ sources (CPU kernels and op registration), sorted."""
    return sorted(root.glob("*.cpp"))


def cuda_sources(root: Path = CSRC) -> list[Path]:
    """The CUDA sources, sorted."""
    return sorted((root / "cuda").glob("*.cu"))


def source_hash(root: Path = CSRC) -> str | None:
    """SHA-256 over every source and header under ``root``; None when the sources are absent."""
    if not root.is_dir():
        return None
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.suffix in {".cpp", ".cu", ".h", ".cuh"}):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()
