"""Volume rendering of radiance fields: ``render_rays`` (NeRF's coarse + fine passes, training),
``render_image`` (chunked, no grad), ``ImageRenderer`` (chunked rendering for any sampler) and
``skipping`` (occupancy-grid marching, early termination, packed samples). Works with any
``nn.Module`` field ``f(x, d) -> (sigma, rgb)``."""

from .image_renderer import ChunkResult, ImageRenderer, ImageResult, render_in_chunks
from .renderer import RenderOutput, chunk_result, render_image, render_rays
from .samplers import sample_intervals, stratified_depths
from .volume import RayBundleResult, composite_samples, query_field

__all__ = [
    "ChunkResult",
    "ImageRenderer",
    "ImageResult",
    "RayBundleResult",
    "RenderOutput",
    "chunk_result",
    "composite_samples",
    "query_field",
    "render_image",
    "render_in_chunks",
    "render_rays",
    "sample_intervals",
    "stratified_depths",
]
