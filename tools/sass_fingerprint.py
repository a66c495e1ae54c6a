"""One hash of normalised sm_90 SASS per CUDA kernel, to prove a source refactor changed no code.

Usage: python tools/sass_fingerprint.py [--dump DIR] [FILE ...]   (default: every csrc/cuda/*.cu)
Compiles each file to a cubin with the build's nvcc flags (tools/compile_check.py), disassembles
it with ``cuobjdump -sass`` and prints ``<sha256[:16]>  <file>  <mangled kernel>`` per function,
sorted. Instruction addresses and the per-compile tag of anonymous namespaces are dropped
before hashing; encodings are kept. ``--dump DIR``
also writes each function's normalised SASS there, for ``diff -r``. cuobjdump (and the nvdisasm
it runs, found on PATH) come with the CUDA toolkit or from ``pip install nvidia-cuda-cuobjdump
nvidia-cuda-nvdisasm``; CUOBJDUMP may name the cuobjdump to use.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from compile_check import CSRC, ROOT, header_stub, nvcc_command

FUNCTION = re.compile(r"^\s*Function : (\S+)\s*$")
ADDRESS = re.compile(r"/\*[0-9a-f]{4,}\*/")
# nvcc names a file's anonymous namespace with a tag that differs on every compile.
ANONYMOUS = re.compile(r"(?<!\d)(\d+)_GLOBAL__N_")


def without_anonymous_tags(text: str) -> str:
    """Replace each mangled ``<length>_GLOBAL__N_<tag>`` namespace by ``11_GLOBAL__N_``."""
    out, end = [], 0
    for match in ANONYMOUS.finditer(text):
        if match.start() < end:
            continue
        out.append(text[end : match.start()] + "11_GLOBAL__N_")
        end = match.end(1) + int(match.group(1))
    return "".join(out) + text[end:]


def cuobjdump() -> str:
    found = os.environ.get("CUOBJDUMP") or shutil.which("cuobjdump")
    nvcc = shutil.which("nvcc")
    if not found and nvcc:
        beside = Path(nvcc).resolve().parent / "cuobjdump"
        found = str(beside) if beside.exists() else None
    if not found:
        sys.exit("cuobjdump not found: put it on PATH or set CUOBJDUMP (pip install nvidia-cuda-cuobjdump)")
    return found


def functions(sass: str) -> dict[str, str]:
    """Mangled function name -> its SASS with instruction addresses stripped."""
    bodies: dict[str, list[str]] = {}
    current = None
    for line in without_anonymous_tags(sass).splitlines():
        match = FUNCTION.match(line)
        if match:
            current = bodies.setdefault(match.group(1), [])
        elif current is not None and line.strip() and not line.lstrip().startswith("..."):
            current.append(" ".join(ADDRESS.sub("", line).split()))
    return {name: "\n".join(lines) + "\n" for name, lines in bodies.items()}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dump", type=Path, help="write each function's normalised SASS under this folder")
    parser.add_argument("files", nargs="*", type=Path)
    args = parser.parse_args(argv)
    files = [f.resolve() for f in args.files] or sorted((CSRC / "cuda").glob("*.cu"))
    tool = cuobjdump()
    rows = []
    with header_stub() as stub_dir:
        for path in files:
            cubin = stub_dir / (path.stem + ".cubin")
            subprocess.run([*nvcc_command(path, stub_dir), "-cubin", "-o", str(cubin)], check=True)
            sass = subprocess.run([tool, "-sass", str(cubin)], check=True, capture_output=True, text=True).stdout
            for name, body in functions(sass).items():
                rows.append(f"{hashlib.sha256(body.encode()).hexdigest()[:16]}  {path.relative_to(ROOT)}  {name}")
                if args.dump:
                    target = args.dump / path.stem / (hashlib.sha256(name.encode()).hexdigest()[:12] + ".sass")
                    target.parent.mkdir(parents=True, exist_ok=True)
                    target.write_text(f"// {name}\n{body}")
    print("\n".join(sorted(rows, key=lambda row: row.split("  ", 1)[1])))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
