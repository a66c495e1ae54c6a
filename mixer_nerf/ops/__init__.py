"""The fused ops. Each takes ``backend="auto" | "kernel" | "torch"``:

- ``"kernel"``: our C++ (CPU) or CUDA kernel with its hand-written backward;
- ``"torch"``: the pure-PyTorch reference path (``<op>_reference.py`` beside each wrapper);
- ``"auto"``: the kernel where one is built for the tensors' device, else the reference path.

``linear_relu`` and ``linear`` have no kernel of ours: their ``"kernel"`` is hand-written passes around
cuBLAS(Lt).
"""

from ._dispatch import use_kernel
from .composite import composite, composite_packed
from .deferred_checks import check_pending
from .hierarchical_samples import hierarchical_samples
from .linear_relu import linear, linear_relu
from .mlca import mlca
from .positional_encoding import positional_encoding
from .ray_marching import FixedSamples, PackedSamples, filter_by_transmittance, ray_marching, ray_marching_fixed
from .sample_pdf import sample_pdf, sample_pdf_packed
from .segment_ops import ray_scale, segment_mean

__all__ = [
    "FixedSamples",
    "PackedSamples",
    "check_pending",
    "composite",
    "composite_packed",
    "filter_by_transmittance",
    "hierarchical_samples",
    "linear",
    "linear_relu",
    "mlca",
    "positional_encoding",
    "ray_marching",
    "ray_marching_fixed",
    "ray_scale",
    "sample_pdf",
    "sample_pdf_packed",
    "segment_mean",
    "use_kernel",
]
