"""Which build of a tiny TORCH_LIBRARY extension survives a TORCH_CHECK failure on this machine.

Usage: python tools/diagnose_exception_crash.py   (prints one line per variant)
Each variant is built with torch.utils.cpp_extension.load_inline and called in a subprocess, so a
crash shows up as that variant's exit status. Used to find why an exception thrown inside
mixer_nerf's extension killed the process on the GPU machine.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile

CPP = r"""
#include <torch/library.h>
#include <ATen/ATen.h>
at::Tensor always_throws(const at::Tensor& x) {
  TORCH_CHECK(x.dim() == 99, "always_throws: x must be 99-d, got shape ", x.sizes());
  return x;
}
TORCH_LIBRARY(NAMESPACE, m) { m.def("always_throws(Tensor x) -> Tensor"); }
TORCH_LIBRARY_IMPL(NAMESPACE, CPU, m) { m.impl("always_throws", &always_throws); }
"""

CU = r"""
#include <torch/library.h>
#include <ATen/ATen.h>
__global__ void noop() {}
at::Tensor cuda_throws(const at::Tensor& x) {
  noop<<<1, 1>>>();
  TORCH_CHECK(x.dim() == 99, "cuda_throws: x must be 99-d, got shape ", x.sizes());
  return x;
}
TORCH_LIBRARY_IMPL(NAMESPACE, CUDA, m) { m.impl("always_throws", &cuda_throws); }
"""

VARIANTS = {
    "cpp": dict(cflags=["-O3"], cuda=False),
    "cpp+openmp": dict(cflags=["-O3", "-fopenmp"], ldflags=["-fopenmp"], cuda=False),
    "cpp+cuda": dict(cflags=["-O3"], cuda=True),
    "cpp+cuda+openmp": dict(cflags=["-O3", "-fopenmp"], ldflags=["-fopenmp"], cuda=True),
}

CHILD = """
import sys, torch
from torch.utils.cpp_extension import load_inline
name, cflags, ldflags, cuda, build = sys.argv[1], sys.argv[2].split(), sys.argv[3].split(), sys.argv[4] == "1", sys.argv[5]
ns = name.replace("+", "_")
src = open(build + "/a.cpp").read().replace("NAMESPACE", ns)
cu = open(build + "/a.cu").read().replace("NAMESPACE", ns) if cuda else None
load_inline(ns, cpp_sources=[src], cuda_sources=[cu] if cu else None, extra_cflags=cflags,
            extra_ldflags=ldflags, is_python_module=False, build_directory=build, with_cuda=cuda)
dev = sys.argv[6]
try:
    getattr(torch.ops, ns).always_throws(torch.ones(2, device=dev))
except RuntimeError as exc:
    print("raised:", str(exc).splitlines()[0])
"""


MIXER_NERF_RAW_CALL = """
import torch
from mixer_nerf import _extension
_extension.load()
try:
    torch.ops.mixer_nerf.positional_encoding_bwd(torch.ones(4, 8), torch.ones(4, 3), 1, True, 1.0)
except RuntimeError as exc:
    print("raised:", str(exc).splitlines()[0])
"""


def mixer_nerf_under_gdb() -> None:
    """The failing call on mixer_nerf's own library, plain and (where gdb exists) with a backtrace."""
    r = subprocess.run([sys.executable, "-c", MIXER_NERF_RAW_CALL], capture_output=True, text=True, timeout=600)
    print(f"mixer_nerf raw op  cpu   rc={r.returncode:4d} {(r.stdout.strip() or r.stderr.strip()[-300:])}", flush=True)
    gdb = shutil.which("gdb")
    if r.returncode == 0 or gdb is None:
        print("gdb:", gdb)
        return
    cmd = [gdb, "-batch", "-ex", "run", "-ex", "bt 40", "--args", sys.executable, "-c", MIXER_NERF_RAW_CALL]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    print("\n".join((r.stdout + r.stderr).splitlines()[-60:]))


def main() -> None:
    import torch

    mixer_nerf_under_gdb()

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    for name, v in VARIANTS.items():
        if v["cuda"] and not torch.cuda.is_available():
            continue
        build = tempfile.mkdtemp(prefix=f"crash_{name.replace('+', '_')}_")
        open(os.path.join(build, "a.cpp"), "w").write(CPP)
        open(os.path.join(build, "a.cu"), "w").write(CU)
        for dev in devices if v["cuda"] else ["cpu"]:
            args = [name, " ".join(v["cflags"]), " ".join(v.get("ldflags", [])), "1" if v["cuda"] else "0", build, dev]
            r = subprocess.run([sys.executable, "-c", CHILD, *args], capture_output=True, text=True, timeout=600)
            tail = (r.stdout.strip().splitlines() or [""])[-1] or r.stderr.strip()[-300:]
            print(f"{name:18s} {dev:5s} rc={r.returncode:4d} {tail}", flush=True)


if __name__ == "__main__":
    main()
