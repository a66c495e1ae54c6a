"""Compile-only check of C++/CUDA sources against the installed torch's headers.

Usage: python tools/compile_check.py [FILE ...]   (default: every csrc/*.cpp and csrc/cuda/*.cu)
C++ files get ``g++ -fsyntax-only``; CUDA files get ``nvcc -c`` for sm_90 into a temporary
object. Works with a CPU-only torch (its wheel ships the CUDA headers), so CI catches CUDA code
that does not compile without a GPU. Exits non-zero on the first failure.
"""

from __future__ import annotations

import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

from torch.utils.cpp_extension import include_paths

ROOT = Path(__file__).resolve().parent.parent
CSRC = ROOT / "csrc"


# A CPU wheel of torch ships the c10/cuda headers but not this one, which its CMake build generates.
CUDA_CMAKE_MACROS = "#pragma once\n#define C10_CUDA_BUILD_SHARED_LIBS\n"


def command(path: Path, obj: Path, stub_dir: Path) -> list[str]:
    includes = [f"-I{p}" for p in [*include_paths(), sysconfig.get_paths()["include"], str(CSRC), str(stub_dir)]]
    defines = ["-DTORCH_EXTENSION_NAME=_C", "-DTORCH_API_INCLUDE_EXTENSION_H"]
    if path.suffix == ".cu":
        return [
            "nvcc", "-c", str(path), "-o", str(obj), "-std=c++20", "-O3",
            "-gencode=arch=compute_90,code=sm_90", "-Xcompiler", "-fPIC", *includes, *defines,
        ]
    return ["g++", "-fsyntax-only", "-std=c++20", "-fopenmp", "-Wall", "-Wextra", str(path), *includes, *defines]


def main(argv: list[str]) -> int:
    files = [Path(a).resolve() for a in argv] or sorted(CSRC.glob("*.cpp")) + sorted(CSRC.glob("cuda/*.cu"))
    with tempfile.TemporaryDirectory() as tmp:
        stub = Path(tmp) / "stub" / "c10" / "cuda" / "impl" / "cuda_cmake_macros.h"
        stub.parent.mkdir(parents=True)
        stub.write_text(CUDA_CMAKE_MACROS)
        for path in files:
            print(f"compile-check {path.relative_to(ROOT)}", flush=True)
            result = subprocess.run(command(path, Path(tmp) / (path.stem + ".o"), Path(tmp) / "stub"))
            if result.returncode != 0:
                print(f"FAILED: {path.relative_to(ROOT)}", file=sys.stderr)
                return result.returncode
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
