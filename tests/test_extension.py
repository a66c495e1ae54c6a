"""Loading the kernels: the MIXER_NERF_EXTENSION switch, fallback on a failed build, stale
prebuilt detection. Each case runs in a fresh interpreter: the loader keeps its outcome per process."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def run_python(code: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True, text=True, timeout=600,
        env={**os.environ, "PYTHONPATH": str(ROOT), **env},
    )


def test_off_uses_the_reference_path_and_kernel_backend_says_why():
    result = run_python(
        """
        import torch
        from mixer_nerf import _extension
        from mixer_nerf.ops import positional_encoding
        x = torch.rand(5, 3)
        out = positional_encoding(x, 2)  # auto: falls back silently when switched off
        assert out.shape == (5, 15) and not _extension.available()
        try:
            positional_encoding(x, 2, backend="kernel")
        except _extension.ExtensionUnavailable as e:
            print("raised:", e)
        """,
        MIXER_NERF_EXTENSION="off",
    )
    assert result.returncode == 0, result.stderr
    assert "raised: kernels disabled by MIXER_NERF_EXTENSION=off" in result.stdout
    assert "Warning" not in result.stderr  # switching them off is not a failure


def test_failed_build_warns_once_and_the_reference_path_still_works(tmp_path):
    result = run_python(
        """
        import warnings, torch
        from torch.utils import cpp_extension
        def broken_load(*args, **kwargs):
            raise RuntimeError("compiler exploded")
        cpp_extension.load = broken_load
        from mixer_nerf.ops import composite
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for _ in range(3):
                out = composite(torch.rand(2, 4), torch.rand(2, 4, 3), torch.zeros(2, 4), torch.ones(2, 4))
        print(len([w for w in caught if "JIT build" in str(w.message)]), out.color.shape)
        """,
        MIXER_NERF_EXTENSION="jit", MIXER_NERF_CACHE=str(tmp_path),
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["1", "torch.Size([2,", "3])"]


def test_prebuilt_only_refuses_a_missing_or_stale_module_with_a_clear_message(tmp_path):
    result = run_python(
        """
        from mixer_nerf import _extension
        ok, why = _extension._prebuilt_is_current()
        if ok:
            print("current")
        else:
            try:
                _extension.load()
            except _extension.ExtensionUnavailable as e:
                print("raised:", e)
        """,
        MIXER_NERF_EXTENSION="prebuilt",
    )
    assert result.returncode == 0, result.stderr
    out = result.stdout.strip()
    assert out == "current" or ("MIXER_NERF_EXTENSION=prebuilt forbids a JIT build" in out), out


def test_unknown_mode_is_a_clear_error():
    result = run_python("from mixer_nerf import _extension; _extension.available()", MIXER_NERF_EXTENSION="maybe")
    assert result.returncode != 0
    assert "MIXER_NERF_EXTENSION='maybe'" in result.stderr


def test_source_hash_changes_with_the_sources(tmp_path):
    from mixer_nerf import _sources

    (tmp_path / "a.cpp").write_text("int a;")
    first = _sources.source_hash(tmp_path)
    (tmp_path / "a.cpp").write_text("int b;")
    assert _sources.source_hash(tmp_path) != first
    assert _sources.source_hash(tmp_path / "missing") is None


def test_jit_cache_hit_loads_the_library_without_building(tmp_path):
    """A library in the build directory of the current sources is loaded as is: no compiler, no
    ninja (a copied checkout or cache has file times ninja would distrust)."""
    result = run_python(
        """
        import importlib.util, shutil
        from torch.utils import cpp_extension
        from mixer_nerf import _extension
        prebuilt = importlib.util.find_spec("mixer_nerf._C")
        if prebuilt is None:
            print("no prebuilt library to stand in for a cached build")
            raise SystemExit
        build_dir = _extension._jit_build_dir(_extension._want_cuda())
        build_dir.mkdir(parents=True)
        shutil.copy(prebuilt.origin, build_dir / "mixer_nerf_C.so")
        def no_build(*args, **kwargs):
            raise AssertionError("a cache hit must not build")
        cpp_extension.load = no_build
        print("loaded" if _extension.available() else "failed")
        """,
        MIXER_NERF_EXTENSION="jit", MIXER_NERF_CACHE=str(tmp_path),
    )
    assert result.returncode == 0, result.stderr
    if "no prebuilt" in result.stdout:
        pytest.skip(result.stdout.strip())
    assert result.stdout.strip() == "loaded", result.stdout + result.stderr
