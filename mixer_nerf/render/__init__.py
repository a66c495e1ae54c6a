"""Volume rendering of radiance fields: ``render_rays`` (training) and ``render_image`` (chunked,
no grad). Works with any ``nn.Module`` field ``f(x, d) -> (sigma, rgb)``."""

from .renderer import ImageResult, RenderOutput, render_image, render_rays
from .samplers import sample_intervals, stratified_depths
from .volume import RayBundleResult, composite_samples, query_field

__all__ = [
    "ImageResult",
    "RayBundleResult",
    "RenderOutput",
    "composite_samples",
    "query_field",
    "render_image",
    "render_rays",
    "sample_intervals",
    "stratified_depths",
]
