"""Pure-PyTorch MLCA (token + channel mixing): the readable formulation, and what
``backend="torch"`` runs. Autograd gives its gradients."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def mlca_reference(
    encoded: torch.Tensor,
    lift: torch.Tensor,
    token_weight: torch.Tensor,
    token_bias: torch.Tensor,
    channel_weight: torch.Tensor,
    channel_bias: torch.Tensor,
) -> torch.Tensor:
    """encoded ``(..., T*D)`` token-major, lift ``(C, D)``, token_weight ``(T, T)``, token_bias
    ``(T,)``, channel_weight ``(C, C)``, channel_bias ``(C,)`` -> ``(..., T*C)`` token-major:

        L = X lift^T,  Y = L + GELU(W_t L + b_t),  Z = Y + GELU(Y W_c^T + b_c)

    per point, with ``X = encoded.view(T, D)`` and ``b_t`` added along each token's channels.
    """
    num_tokens, token_dim = token_weight.shape[0], lift.shape[1]
    tokens = encoded.unflatten(-1, (num_tokens, token_dim))  # (..., T, D)
    lifted = F.linear(tokens, lift)  # (..., T, C)
    token_pre = torch.einsum("ts,...sc->...tc", token_weight, lifted) + token_bias[:, None]
    mixed = lifted + F.gelu(token_pre)
    mixed = mixed + F.gelu(F.linear(mixed, channel_weight, channel_bias))
    return mixed.flatten(-2)
