"""Grid subsampling and capped radius neighbours: the two geometric operations of the KPConv encoder.

Both follow the reference implementation's arithmetic so that its checkpoints reproduce their embeddings:
coordinates are normalised (metres / map size), voxel keys and tie-breaking distances are float32.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch
from scipy.spatial import cKDTree


def grid_subsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Indices of the points kept by grid subsampling: per occupied voxel, the point nearest to the voxel centre.

    points: (N, 3) float32 normalised coordinates in [0, 1) (tile-local metres / map size);
    voxel_size: voxel edge in the same normalised unit. Returns int64 indices ordered by voxel key (x fastest).
    The sort key (voxel key + 0.7 * d^2 / max d^2) is float32 and sorted with torch's sort, exactly like the
    reference, so that ties resolve the same way and its checkpoints keep the same embedding points.
    """
    pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32))
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64)
    grid = torch.floor(pts / voxel_size)
    dist = ((pts - (grid + 0.5) * voxel_size) ** 2).sum(dim=1)
    max_dist = dist.max()
    if max_dist > 0:
        dist = dist / max_dist * 0.7
    cells_per_axis = float(math.ceil(1.0 / voxel_size))
    key = grid[:, 0] + grid[:, 1] * cells_per_axis + grid[:, 2] * cells_per_axis * cells_per_axis
    order = torch.argsort(key + dist)
    sorted_key = key[order]
    first = torch.ones(len(order), dtype=torch.bool)
    first[1:] = sorted_key[1:] != sorted_key[:-1]
    return order[first].numpy().astype(np.int64)


def radius_neighbors(source: np.ndarray, queries: np.ndarray, radius: float, max_neighbors: int) -> np.ndarray:
    """Padded neighbour indices of each query within `radius`, capped at `max_neighbors`.

    When a query has more than `max_neighbors` neighbours, an evenly spread subset is kept: with the neighbours in
    index order n_0 < ... < n_{m-1}, column j holds n_{floor(m * j / max_neighbors)} (the reference's rule).
    Missing entries hold len(source) (a "shadow" index). Returns (Q, K) int64, K = the largest count (<= cap).
    The search runs on torch.get_num_threads() threads over contiguous query ranges; the result does not depend
    on the thread count.
    """
    n_source = len(source)
    source_tree = cKDTree(source)

    def sorted_pair_keys(query_range: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(query, source index) pairs within radius as one sorted int64 key each, and the count per query
        (scipy and numpy release the GIL here, so query ranges run in parallel)."""
        if len(query_range) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        pairs = cKDTree(queries[query_range]).sparse_distance_matrix(source_tree, radius, output_type="ndarray")
        rows = pairs["i"].astype(np.int64)
        keys = np.sort((rows + query_range[0]) * n_source + pairs["j"])
        return keys, np.bincount(rows, minlength=len(query_range))

    ranges = np.array_split(np.arange(len(queries)), max(1, min(torch.get_num_threads(), len(queries) // 256)))
    with ThreadPoolExecutor(len(ranges)) as pool:
        parts = list(pool.map(sorted_pair_keys, ranges))
    keys = np.concatenate([k for k, _ in parts])
    counts = np.concatenate([c for _, c in parts])
    width = int(min(max_neighbors, counts.max(initial=0)))
    result = np.full((len(queries), width), len(source), dtype=np.int64)
    if width == 0:
        return result
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    kept = np.minimum(counts, max_neighbors)
    rows = np.repeat(np.arange(len(queries)), kept)
    cols = np.arange(kept.sum()) - np.repeat(np.cumsum(kept) - kept, kept)
    step = np.maximum((np.repeat(counts, kept) * cols) // max_neighbors, cols)
    result[rows, cols] = keys[np.repeat(starts, kept) + step] - rows * n_source
    return result
