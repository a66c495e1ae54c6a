"""Builds the mixer_nerf kernels ahead of time when torch is importable at build time.

``pip install --no-build-isolation -e .`` sees the installed torch and compiles ``mixer_nerf._C``
(C++ always; CUDA too when torch is a CUDA build and nvcc is found). A build without torch (the
default isolated build) installs pure Python; the package then JIT-builds on first use.
``MIXER_NERF_EXTENSION=jit`` or ``off`` at install time skips the ahead-of-time build.
"""

import importlib.util
import os
from pathlib import Path

from setuptools import setup

ROOT = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("_sources", ROOT / "mixer_nerf" / "_sources.py")
_sources = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_sources)


def extension_build():
    if os.environ.get("MIXER_NERF_EXTENSION", "auto").lower() in ("jit", "off"):
        return [], {}
    try:
        import torch
        from torch.utils.cpp_extension import CUDA_HOME, BuildExtension, CppExtension, CUDAExtension
    except ImportError:
        return [], {}

    class BuildWithSourceStamp(BuildExtension):
        """Records which sources the module was built from, so the loader can spot a stale one."""

        def run(self):
            super().run()
            for ext in self.extensions:
                stamp = Path(self.get_ext_fullpath(ext.name)).with_name("_C.sources.sha256")
                stamp.write_text(_sources.source_hash() + "\n")

    with_cuda = torch.version.cuda is not None and CUDA_HOME is not None and _sources.cuda_sources()
    sources = [str(p.relative_to(ROOT)) for p in _sources.cpp_sources()]
    kwargs = dict(
        name="mixer_nerf._C",
        include_dirs=[str(_sources.CSRC)],
        extra_compile_args={
            "cxx": ["-O3", "-fopenmp"],
            "nvcc": ["-O3", "-lineinfo"],
        },
        extra_link_args=["-fopenmp"],
    )
    if with_cuda:
        sources += [str(p.relative_to(ROOT)) for p in _sources.cuda_sources()]
        ext = CUDAExtension(sources=sources, **kwargs)
    else:
        kwargs["extra_compile_args"] = kwargs["extra_compile_args"]["cxx"]
        ext = CppExtension(sources=sources, **kwargs)
    return [ext], {"build_ext": BuildWithSourceStamp.with_options(use_ninja=True)}


ext_modules, cmdclass = extension_build()
setup(ext_modules=ext_modules, cmdclass=cmdclass)
