"""Which TORCH_CHECK messages survive being raised from a C++ extension on this machine.

Usage: python tools/diagnose_exception_crash.py   (prints one line per case)

Builds one tiny TORCH_LIBRARY extension (torch.utils.cpp_extension.load_inline) whose ops fail a
check with messages of different kinds, and calls each in a subprocess, so that a crash shows up
as that case's exit status; then calls a mixer_nerf op with bad arguments the same way. Found on
the GPU machine (torch 2.11+cu130, g++ 13.3, 2026-11-23): a message that streams a shape killed
the process with SIGSEGV whatever the build flags (-fopenmp, CUDA sources) while a literal
message raised; hence MIXER_NERF_CHECK in csrc/common.h, which builds the message itself.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile

CASES = {  # op name -> the failing check's message arguments
    "literal": '"x must be 99-d"',
    "streamed_int": '"x must be 99-d, got ", x.dim()',
    "streamed_shape": '"x must be 99-d, got shape ", x.sizes()',
    "one_c_string": '(std::string("x must be 99-d, got ") + std::to_string(x.dim())).c_str()',
}

SOURCE = "#include <torch/library.h>\n#include <ATen/ATen.h>\n#include <string>\n" + "".join(
    f"at::Tensor {name}(const at::Tensor& x) {{ TORCH_CHECK(x.dim() == 99, {message}); return x; }}\n"
    for name, message in CASES.items()
) + "TORCH_LIBRARY(crash_probe, m) {\n" + "".join(
    f'  m.def("{name}(Tensor x) -> Tensor", &{name});\n' for name in CASES
) + "}\n"

CALL = """
import sys, torch
torch.ops.load_library(sys.argv[1])
try:
    getattr(torch.ops.crash_probe, sys.argv[2])(torch.ones(2))
except RuntimeError as exc:
    print("raised:", str(exc).splitlines()[0])
"""

MIXER_NERF_CALL = """
import torch
from mixer_nerf import _extension
_extension.load()
try:
    torch.ops.mixer_nerf.positional_encoding_bwd(torch.ones(4, 8), torch.ones(4, 3), 1, True, 1.0)
except RuntimeError as exc:
    print("raised:", str(exc).splitlines()[0])
"""


def report(label: str, result: subprocess.CompletedProcess) -> None:
    tail = (result.stdout.strip().splitlines() or [""])[-1] or result.stderr.strip()[-300:]
    print(f"{label:32s} rc={result.returncode:4d} {tail}", flush=True)


def main() -> None:
    from torch.utils.cpp_extension import load_inline

    build = tempfile.mkdtemp(prefix="crash_probe_")
    load_inline("crash_probe", cpp_sources=[SOURCE], is_python_module=False, build_directory=build)
    for name in CASES:
        args = [sys.executable, "-c", CALL, f"{build}/crash_probe.so", name]
        report(f"tiny extension, {name}", subprocess.run(args, capture_output=True, text=True, timeout=300))
    args = [sys.executable, "-c", MIXER_NERF_CALL]
    report("mixer_nerf raw op", subprocess.run(args, capture_output=True, text=True, timeout=600))


if __name__ == "__main__":
    main()
