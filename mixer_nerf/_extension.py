"""Loads the compiled kernels: the prebuilt ``mixer_nerf._C`` or a JIT build, once per process.

``MIXER_NERF_EXTENSION`` picks the source:
  ``auto`` (default)  the prebuilt module if it was built from the current sources, else JIT-build
  ``prebuilt``        only the prebuilt module
  ``jit``             always JIT-build (cached under ``MIXER_NERF_CACHE`` or ``~/.cache/mixer_nerf``)
  ``off``             no kernels; ``backend="auto"`` uses the PyTorch reference path
Nothing is built or loaded at import time: the first kernel call does it. A failed build warns
once and leaves the reference path working; ``backend="kernel"`` then raises with the reason.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import warnings
from pathlib import Path

import torch

from . import _sources

_MODES = ("auto", "prebuilt", "jit", "off")
_JIT_NAME = "mixer_nerf_C"
_state: dict = {}


class ExtensionUnavailable(RuntimeError):
    """The compiled kernels could not be loaded; the message says why."""


def _mode() -> str:
    mode = os.environ.get("MIXER_NERF_EXTENSION", "auto").strip().lower()
    if mode not in _MODES:
        raise ValueError(f"MIXER_NERF_EXTENSION={mode!r}: expected one of {', '.join(_MODES)}")
    return mode


def cache_dir() -> Path:
    """Root of the JIT build cache."""
    return Path(os.environ.get("MIXER_NERF_CACHE", Path.home() / ".cache" / "mixer_nerf"))


def _prebuilt_is_current() -> tuple[bool, str]:
    spec = importlib.util.find_spec("mixer_nerf._C")
    if spec is None:
        return False, "no prebuilt mixer_nerf._C (pure-Python install)"
    current = _sources.source_hash()
    if current is None:  # installed without sources: nothing to compare against
        return True, ""
    stamp = Path(spec.origin).with_name("_C.sources.sha256")
    built = stamp.read_text().strip() if stamp.exists() else None
    if built != current:
        return False, "prebuilt mixer_nerf._C is stale (csrc/ changed since it was built)"
    return True, ""


def _want_cuda() -> bool:
    from torch.utils.cpp_extension import CUDA_HOME

    return torch.version.cuda is not None and CUDA_HOME is not None and bool(_sources.cuda_sources())


def _jit_build_dir(with_cuda: bool) -> Path:
    """One build directory per torch version, source hash and CUDA target set: a library found
    there was built from exactly these sources, so it is loaded without invoking ninja (whose
    staleness check trusts file times, which a copied checkout or cache does not keep)."""
    flavour = f"torch{torch.__version__}-{'cuda' if with_cuda else 'cpu'}".replace("+", "_")
    key = _sources.source_hash() or ""
    if with_cuda:  # torch builds for TORCH_CUDA_ARCH_LIST, else for the GPUs it sees
        archs = os.environ.get("TORCH_CUDA_ARCH_LIST") or ",".join(
            "{}.{}".format(*torch.cuda.get_device_capability(i)) for i in range(torch.cuda.device_count())
        )
        key += "|" + archs
    return cache_dir() / "build" / f"{flavour}-{hashlib.sha256(key.encode()).hexdigest()[:16]}"


def _jit_build() -> None:
    from torch.utils import cpp_extension

    with_cuda = _want_cuda()
    build_dir = _jit_build_dir(with_cuda)
    library = build_dir / f"{_JIT_NAME}.so"
    _state["source"] = f"JIT build {library}"
    if library.exists():
        torch.ops.load_library(str(library))
        return
    build_dir.mkdir(parents=True, exist_ok=True)
    sources = _sources.cpp_sources() + (_sources.cuda_sources() if with_cuda else [])
    print(
        f"mixer_nerf: compiling {'C++/CUDA' if with_cuda else 'C++'} kernels on first use "
        f"(cached in {build_dir}); this takes a minute or two once",
        file=sys.stderr,
        flush=True,
    )
    cpp_extension.load(
        name=_JIT_NAME,
        sources=[str(s) for s in sources],
        extra_cflags=["-O3", "-fopenmp"],
        extra_ldflags=["-fopenmp"],
        extra_cuda_cflags=["-O3", "-lineinfo"] + _cuda_arch_flags(),
        extra_include_paths=[str(_sources.CSRC)],
        build_directory=str(build_dir),
        with_cuda=with_cuda,
        is_python_module=False,
        verbose=os.environ.get("MIXER_NERF_VERBOSE_BUILD") == "1",
    )


def _cuda_arch_flags() -> list[str]:
    # TORCH_CUDA_ARCH_LIST (torch's own knob) wins; otherwise torch builds for the visible GPU.
    return []


def _load() -> None:
    mode = _mode()
    if mode == "off":
        raise ExtensionUnavailable("kernels disabled by MIXER_NERF_EXTENSION=off")
    if mode in ("auto", "prebuilt"):
        ok, why = _prebuilt_is_current()
        if ok:
            _state["source"] = f"prebuilt {importlib.import_module('mixer_nerf._C').__file__}"
            return
        if mode == "prebuilt":
            raise ExtensionUnavailable(f"{why} and MIXER_NERF_EXTENSION=prebuilt forbids a JIT build")
    try:
        _jit_build()
    except Exception as exc:  # compiler missing, build error: keep the reference path usable
        raise ExtensionUnavailable(f"JIT build of the mixer_nerf kernels failed: {exc}") from exc


def load() -> None:
    """Load the kernels once; raise :class:`ExtensionUnavailable` (every call) if that failed."""
    if "error" not in _state and "loaded" not in _state:
        try:
            _load()
            _state["loaded"] = True
        except ExtensionUnavailable as exc:
            _state["error"] = exc
            if _mode() != "off":
                warnings.warn(f"{exc}; falling back to the PyTorch reference path", RuntimeWarning, stacklevel=3)
    if "error" in _state:
        raise _state["error"]


def available() -> bool:
    """Whether the compiled kernels are loaded (loading them on first call)."""
    try:
        load()
    except ExtensionUnavailable:
        return False
    return True


def describe() -> str:
    """Which kernels this process runs: the prebuilt module or a JIT build (with its file), or
    the reference fallback and why (loading them on first call)."""
    if available():
        return _state["source"]
    return f"none, PyTorch reference fallback: {_state['error']}"


def has_cuda_kernels() -> bool:
    """Whether the loaded extension holds CUDA kernels (the dispatcher is asked once: every op call
    on a GPU comes here, and its lookup takes ~4 us of host time)."""
    if not available():
        return False
    if "cuda_kernels" not in _state:
        has = torch._C._dispatch_has_kernel_for_dispatch_key
        _state["cuda_kernels"] = has("mixer_nerf::composite_fwd", "CUDA")
    return _state["cuda_kernels"]
