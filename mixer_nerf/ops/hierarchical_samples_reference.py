"""Pure-PyTorch reference of NeRF's fine-pass depths (what ``backend="torch"`` runs): the PDF of
:mod:`mixer_nerf.ops.sample_pdf_reference` on the midpoints of the coarse depths, its samples
merged with the coarse depths by one sort."""

from __future__ import annotations

import torch

from .sample_pdf_reference import accumulation_dtype, sample_pdf_reference


def hierarchical_samples_reference(
    z_coarse: torch.Tensor, weights_coarse: torch.Tensor, u: torch.Tensor, weight_padding: float = 0.0
) -> torch.Tensor:
    """z_coarse (R, S) sorted, weights_coarse (R, S), u (R, N) or (N,) -> merged (R, S+N), no grad.

    Like NeRF: the bins are the midpoints of z_coarse and the weights weights_coarse[:, 1:-1].
    """
    with torch.no_grad():
        acc = accumulation_dtype(z_coarse.dtype)
        z = z_coarse.to(acc)
        mids = 0.5 * (z[:, 1:] + z[:, :-1])
        fine = sample_pdf_reference(mids, weights_coarse[:, 1:-1], u, weight_padding).to(z_coarse.dtype)
        return torch.sort(torch.cat([z_coarse, fine], dim=-1), dim=-1).values
