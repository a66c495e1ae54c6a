"""The Mixer-NeRF radiance field and its building blocks.

``MixerNeRF(preset_config("D"))`` is an ``nn.Module`` ``f(x, d) -> (sigma, rgb)``; presets A (NeRF),
B (+SE), C (+MLCA) and D (Mixer-NeRF) differ only in ``ModelConfig.use_se`` / ``use_mlca``.
"""

from .config import PRESETS, ModelConfig, preset_config
from .mlca import MLCA
from .network import MixerNeRF
from .squeeze_excitation import SqueezeExcitation, mean_over_ray_indices

__all__ = [
    "MLCA",
    "PRESETS",
    "MixerNeRF",
    "ModelConfig",
    "SqueezeExcitation",
    "mean_over_ray_indices",
    "preset_config",
]
