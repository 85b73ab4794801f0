"""Chamfer loss (paper eq. 6-8) with KD-tree nearest neighbours: O(N + M) memory, differentiable distances."""

from __future__ import annotations

import numpy as np
import torch
from pykdtree.kdtree import KDTree


def _kdtree(points: torch.Tensor) -> KDTree:
    return KDTree(np.ascontiguousarray(points.detach().cpu().numpy()))


def _nearest(tree: KDTree, queries: torch.Tensor) -> torch.Tensor:
    """Index of the nearest tree point of every query (no gradient)."""
    _, idx = tree.query(np.ascontiguousarray(queries.detach().cpu().numpy()), k=1)
    return torch.from_numpy(idx.astype(np.int64)).to(queries.device)


def _matched_squared_distances(reference: torch.Tensor, output: torch.Tensor, reference_tree: KDTree | None
                               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared distance of every output point to its nearest reference point, and of every reference point to its
    nearest output point (neighbours from KD-trees, distances in torch so gradients flow). The gathers are
    `index_select`s: their backward (`index_add_`) sums repeated indices in a fixed order on the CPU, where that of
    `tensor[indices]` (`index_put_` with accumulate) depends on the threads."""
    if reference_tree is None:
        reference_tree = _kdtree(reference)
    out_to_ref = _nearest(reference_tree, output)
    ref_to_out = _nearest(_kdtree(output), reference)
    return (((output - reference.index_select(0, out_to_ref)) ** 2).sum(dim=1),
            ((reference - output.index_select(0, ref_to_out)) ** 2).sum(dim=1))


def chamfer_loss(reference: torch.Tensor, output: torch.Tensor, reference_tree: KDTree | None = None):
    """Symmetric Chamfer distance D_CD (eq. 6-7): mean squared NN distance each way, halved and summed.

    The nearest neighbours come from KD-trees (pykdtree); the squared distances are computed in torch, so gradients
    flow to `output` (and `reference` if it requires grad). Pass `reference_tree` to reuse a tree over `reference`.
    """
    d_out, d_ref = _matched_squared_distances(reference, output, reference_tree)
    return 0.5 * d_out.mean() + 0.5 * d_ref.mean()


def depoco_loss(reference: torch.Tensor, output: torch.Tensor, intermediate: list[torch.Tensor],
                beta: float = 0.2) -> tuple[torch.Tensor, torch.Tensor]:
    """L = D_CD(in, out) + beta * sum_j D_CD(in, P_j) over the intermediate clouds (eq. 8). Returns (L, D_CD)."""
    tree = _kdtree(reference)
    main = chamfer_loss(reference, output, tree)
    loss = main
    if beta > 0:
        for cloud in intermediate:
            loss = loss + beta * chamfer_loss(reference, cloud, tree)
    return loss, main


def mean_distance_loss(reference: torch.Tensor, output: torch.Tensor, reference_tree: KDTree | None = None,
                       dead_zone: float = 0.0):
    """Symmetric mean nearest-neighbour distance (not squared): D_e (eq. 9) of `output` against `reference`, in the
    units of the inputs, differentiable in both (KD-tree neighbours as in `chamfer_loss`). With a dead zone z > 0,
    each distance d counts as max(d - z, 0) (encode-time refinement, `ModelConfig.refine_dead_zone_m`)."""
    d_out, d_ref = _matched_squared_distances(reference, output, reference_tree)
    eps = 1e-12  # keeps the gradient of sqrt finite where a point sits exactly on its neighbour
    d_out, d_ref = (d_out + eps).sqrt(), (d_ref + eps).sqrt()
    if dead_zone > 0:
        d_out, d_ref = torch.relu(d_out - dead_zone), torch.relu(d_ref - dead_zone)
    return 0.5 * d_out.mean() + 0.5 * d_ref.mean()
