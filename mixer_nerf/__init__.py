"""mixer_nerf: fast, accurate neural radiance fields (Mixer-NeRF) with fused C++/CUDA kernels."""

__version__ = "0.1.0"
