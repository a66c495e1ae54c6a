"""tools/sass_fingerprint.py's reading of cuobjdump output (no nvcc or GPU needed)."""

import importlib.util
import sys
from pathlib import Path

TOOLS = Path(__file__).resolve().parent.parent / "tools"


def _tool():
    sys.path.insert(0, str(TOOLS))  # the tool imports its sibling compile_check
    try:
        spec = importlib.util.spec_from_file_location("sass_fingerprint", TOOLS / "sass_fingerprint.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(TOOLS))


def _dump(tag: str, address: str) -> str:
    name = f"_ZN10mixer_nerf{len(tag)}{tag}20write_samples_kernelIffEEvl"
    return f"""
\tcode for sm_90
\t\tFunction : {name}
\t.headerflags\t@"EF_CUDA_SM90 EF_CUDA_VIRTUAL_SM(EF_CUDA_SM90)"
        /*{address}*/                   LDC R1, c[0x0][0x28] ;      /* 0x00000a00ff017b82 */
                                                                    /* 0x000fe20000000800 */
        /*0010*/                   EXIT ;                            /* 0x000000000000794d */
\t\t..........
"""


def test_addresses_and_anonymous_namespace_tags_do_not_count():
    tool = _tool()
    a = tool.functions(_dump("_GLOBAL__N__7bdfe3a2_15_ray_marching_cu_d6dac05f_5211", "0000"))
    b = tool.functions(_dump("_GLOBAL__N__76215580_15_ray_marching_cu_3e5dcd5f_60320", "0a00"))
    assert a == b
    (name,) = a
    assert name == "_ZN10mixer_nerf11_GLOBAL__N_20write_samples_kernelIffEEvl"
    assert "LDC R1" in a[name] and "0x00000a00ff017b82" in a[name] and "/*0000*/" not in a[name]


def test_a_changed_instruction_changes_the_body():
    tool = _tool()
    dump = _dump("_GLOBAL__N__7bdfe3a2_15_ray_marching_cu_d6dac05f_5211", "0000")
    (before,) = tool.functions(dump).values()
    (after,) = tool.functions(dump.replace("c[0x0][0x28]", "c[0x0][0x2c]")).values()
    assert before != after
