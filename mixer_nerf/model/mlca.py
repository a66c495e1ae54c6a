"""MLCA: Mixer-NeRF's hybrid spatial feature learning module (token mixing + channel mixing).

Interpretation. A positional encoding of a ``D``-dimensional point with ``L`` octaves is laid out
``[x, sin(2^0 s x), cos(2^0 s x), ..., sin(2^(L-1) s x), cos(...)]``: ``T = 1 + 2L`` frequency
bands of ``D`` values each. MLCA reads it as an MLP-Mixer "image" of ``T`` tokens (the frequency
bands) by ``C`` channels:

1. lift:           each token's ``D`` coordinates -> ``C`` channels (one shared ``C x D`` map),
                   initialised to ``[I_D; 0]`` (copies the coordinates, extra channels start at 0);
2. token mixing:   ``Y = X + GELU(W_token X + b_token)``, ``W_token`` ``(T, T)`` mixes the frequency
                   bands, the same way for every channel;
3. channel mixing: ``Z = Y + GELU(Y W_channel^T + b_channel)``, ``W_channel`` ``(C, C)`` mixes the
                   channels of each token, the same way for every token;

and returns ``Z`` flattened token-major, ``T * C`` wide. The mixing weights and biases start at
zero, so with ``GELU(0) = 0`` the module starts as the (lifted) identity: a Mixer-NeRF starts as
exactly the NeRF it extends and learns how much mixing helps (the gradient at zero is not zero:
``GELU'(0) = 1/2``). Mixer-NeRF applies one MLCA to PE(x) before the trunk (T = 21 for 10 octaves)
and one to PE(d) before the view branch (T = 9 for 4 octaves); with
``ModelConfig.mlca_concat_direction`` (the paper's Eq. 7) the tokens of PE(x) and PE(d) are mixed
together (T = 30) and fed to the trunk.

Computation: one fused op, :func:`mixer_nerf.ops.mlca` (C++ and CUDA kernels with hand-written
backwards; ``backend`` as in :mod:`mixer_nerf.ops`). It does the lift, both mixings, GELUs and
residuals per point without materialising intermediates, and its backward recomputes them from
``encoded`` and reduces the weight gradients over the points in-kernel. The plain-PyTorch
formulation (and the ``backend="torch"`` path) is in ``mixer_nerf/ops/mlca_reference.py``.
"""

from __future__ import annotations

import torch
from torch import nn

from ..ops import mlca
from ..ops._checks import check_backend


class MLCA(nn.Module):
    """Token + channel mixing of an encoding of ``num_tokens`` tokens of ``token_dim`` values.

    Args:
        num_tokens: ``T``, tokens per point (frequency bands: ``include_input + 2 * num_freqs``).
        token_dim: ``D``, values per token in the input (the point's coordinates, 3).
        channels: ``C >= D``, channels per token after the lift.
        backend: ``"auto"``, ``"kernel"`` or ``"torch"``, for :func:`mixer_nerf.ops.mlca`.

    Shapes: ``(..., T * D)`` -> ``(..., T * C)``, both token-major. The parameters are cast to the
    dtype of ``encoded`` (a no-op when they match; under autocast both stay float32).
    """

    def __init__(self, num_tokens: int, token_dim: int = 3, channels: int = 8, backend: str = "auto") -> None:
        super().__init__()
        if channels < token_dim:
            raise ValueError(f"channels ({channels}) must be >= token_dim ({token_dim})")
        check_backend(backend)
        self.num_tokens, self.token_dim, self.channels = num_tokens, token_dim, channels
        self.backend = backend
        self.lift = nn.Parameter(torch.eye(channels, token_dim))
        self.token_weight = nn.Parameter(torch.zeros(num_tokens, num_tokens))
        self.token_bias = nn.Parameter(torch.zeros(num_tokens))
        self.channel_weight = nn.Parameter(torch.zeros(channels, channels))
        self.channel_bias = nn.Parameter(torch.zeros(channels))

    @property
    def out_features(self) -> int:
        return self.num_tokens * self.channels

    def mixing_weights(self) -> tuple[nn.Parameter, nn.Parameter]:
        """The token- and channel-mixing matrices: at zero the module is the identity (the lift
        copies the coordinates), so shrinking them pulls it toward the NeRF it extends."""
        return self.token_weight, self.channel_weight

    def forward(self, encoded: torch.Tensor) -> torch.Tensor:
        if encoded.shape[-1] != self.num_tokens * self.token_dim:
            raise ValueError(
                f"encoded must have {self.num_tokens} x {self.token_dim} = "
                f"{self.num_tokens * self.token_dim} features, got shape {tuple(encoded.shape)}"
            )
        weights = (self.lift, self.token_weight, self.token_bias, self.channel_weight, self.channel_bias)
        if self.lift.dtype != encoded.dtype:  # all five share one dtype: skip five no-op casts per call
            weights = tuple(w.to(encoded.dtype) for w in weights)
        return mlca(encoded, *weights, backend=self.backend)

    def extra_repr(self) -> str:
        return f"tokens={self.num_tokens}, token_dim={self.token_dim}, channels={self.channels}"
