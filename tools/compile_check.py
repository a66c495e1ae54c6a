"""Compile-only check of C++/CUDA sources against the installed torch's headers.

Usage: python tools/compile_check.py [FILE ...]   (default: every csrc/*.cpp and csrc/cuda/*.cu)
C++ files get ``g++ -fsyntax-only``; CUDA files get ``nvcc -c`` for sm_90 into a temporary
object, with the flags the extension build passes. Works with a CPU-only torch (its wheel ships
the CUDA headers), so CI catches CUDA code that does not compile without a GPU. Files compile in
parallel; exits non-zero if any fails, with its compiler output.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import sysconfig
import tempfile
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from torch.utils.cpp_extension import COMMON_NVCC_FLAGS, include_paths

ROOT = Path(__file__).resolve().parent.parent
CSRC = ROOT / "csrc"


# A CPU wheel of torch ships the c10/cuda headers but not this one, which its CMake build generates.
CUDA_CMAKE_MACROS = "#pragma once\n#define C10_CUDA_BUILD_SHARED_LIBS\n"


@contextlib.contextmanager
def header_stub() -> Iterator[Path]:
    """A temporary include directory holding the generated torch header a CPU wheel lacks."""
    with tempfile.TemporaryDirectory() as tmp:
        stub = Path(tmp) / "c10" / "cuda" / "impl" / "cuda_cmake_macros.h"
        stub.parent.mkdir(parents=True)
        stub.write_text(CUDA_CMAKE_MACROS)
        yield Path(tmp)


def common_flags(stub_dir: Path) -> list[str]:
    includes = [f"-I{p}" for p in [*include_paths(), sysconfig.get_paths()["include"], str(CSRC), str(stub_dir)]]
    # C++17, the oldest standard a supported torch builds extensions with (2.11 does): code that
    # compiles only as C++20 (std::tie in device code, say) fails there. Newer headers warn only.
    return [*includes, "-DTORCH_EXTENSION_NAME=_C", "-DTORCH_API_INCLUDE_EXTENSION_H", "-std=c++17"]


def nvcc_command(path: Path, stub_dir: Path) -> list[str]:
    """nvcc for sm_90 with setup.py's flags (torch's COMMON_NVCC_FLAGS, -O3, -lineinfo); the
    caller appends what to emit (``-c -o x.o``, ``-cubin -o x.cubin``)."""
    return [
        "nvcc", str(path), *COMMON_NVCC_FLAGS, "-O3", "-lineinfo",
        "-gencode=arch=compute_90,code=sm_90", "-Xcompiler", "-fPIC,-Wno-c++20-extensions", "-diag-suppress", "3306",
        *common_flags(stub_dir),
    ]


def command(path: Path, obj: Path, stub_dir: Path) -> list[str]:
    if path.suffix == ".cu":
        return [*nvcc_command(path, stub_dir), "-c", "-o", str(obj)]
    return ["g++", "-fsyntax-only", "-fopenmp", "-Wall", "-Wextra", "-Wno-c++20-extensions", str(path),
            *common_flags(stub_dir)]


def main(argv: list[str]) -> int:
    files = [Path(a).resolve() for a in argv] or sorted(CSRC.glob("*.cpp")) + sorted(CSRC.glob("cuda/*.cu"))
    with header_stub() as stub_dir, ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        # One compiler per core: nvcc at -O3 takes minutes a file, and CI waits for all of them.
        runs = {path: pool.submit(subprocess.run, command(path, stub_dir / (path.stem + ".o"), stub_dir),
                                  capture_output=True, text=True) for path in files}
        failed = 0
        for path, run in runs.items():
            result = run.result()
            print(f"compile-check {path.relative_to(ROOT)}: {'ok' if result.returncode == 0 else 'FAILED'}",
                  flush=True)
            if result.returncode != 0:
                print(result.stdout + result.stderr, file=sys.stderr)
                failed = failed or result.returncode
    return failed


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
