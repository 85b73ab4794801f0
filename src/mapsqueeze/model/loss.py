"""Chamfer loss (paper eq. 6-8) with KD-tree nearest neighbours: O(N + M) memory, differentiable distances."""

from __future__ import annotations

import torch
from scipy.spatial import cKDTree


def nearest_indices(source: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Index into `targets` of the nearest neighbour of every source point (no gradient)."""
    tree = cKDTree(targets.detach().cpu().numpy())
    _, idx = tree.query(source.detach().cpu().numpy(), k=1, workers=-1)
    return torch.from_numpy(idx).to(source.device)


def chamfer_loss(reference: torch.Tensor, output: torch.Tensor, reference_tree: cKDTree | None = None):
    """Symmetric Chamfer distance D_CD (eq. 6-7): mean squared NN distance each way, halved and summed.

    The nearest neighbours come from KD-trees; the squared distances are computed in torch, so gradients flow to
    `output` (and `reference` if it requires grad). Pass `reference_tree` to reuse a tree over `reference`.
    """
    if reference_tree is None:
        reference_tree = cKDTree(reference.detach().cpu().numpy())
    _, out_to_ref = reference_tree.query(output.detach().cpu().numpy(), k=1, workers=-1)
    ref_to_out = nearest_indices(reference, output)
    out_to_ref = torch.from_numpy(out_to_ref).to(output.device)
    d_out = ((output - reference[out_to_ref]) ** 2).sum(dim=1).mean()
    d_ref = ((reference - output[ref_to_out]) ** 2).sum(dim=1).mean()
    return 0.5 * d_out + 0.5 * d_ref


def depoco_loss(reference: torch.Tensor, output: torch.Tensor, intermediate: list[torch.Tensor],
                beta: float = 0.2) -> tuple[torch.Tensor, torch.Tensor]:
    """L = D_CD(in, out) + beta * sum_j D_CD(in, P_j) over the intermediate clouds (eq. 8). Returns (L, D_CD)."""
    tree = cKDTree(reference.detach().cpu().numpy())
    main = chamfer_loss(reference, output, tree)
    loss = main
    if beta > 0:
        for cloud in intermediate:
            loss = loss + beta * chamfer_loss(reference, cloud, tree)
    return loss, main
