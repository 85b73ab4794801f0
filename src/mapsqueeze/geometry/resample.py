"""Bring a cloud to an exact point count: an evenly spread subset to thin it, midpoints to densify it."""

import numpy as np
from pykdtree.kdtree import KDTree

from mapsqueeze.geometry.morton import spread_subset


def resample_to_count(cloud: np.ndarray, n_points: int | None) -> np.ndarray:
    """Thin or densify a decoded cloud to exactly n_points (deterministic).

    Thinning keeps an evenly spread subset that follows the decoder's own density (`spread_subset`: D_e 2-6 %
    lower than a uniformly random subset on the real submaps, BENCHMARKS.md).
    """
    if n_points is None or n_points == len(cloud):
        return cloud
    if n_points <= 0:
        return cloud[:0]
    if n_points < len(cloud):
        return cloud[spread_subset(cloud, n_points)]
    # Densify: midpoints towards the k nearest neighbours, as many rounds of k as needed.
    k = int(np.ceil(n_points / len(cloud)))
    _, nn_idx = KDTree(np.ascontiguousarray(cloud)).query(np.ascontiguousarray(cloud), k=min(k + 1, len(cloud)))
    nn_idx = np.atleast_2d(nn_idx.astype(np.int64))[:, 1:] if len(cloud) > 1 else np.zeros((1, 0), dtype=np.int64)
    if nn_idx.shape[1] == 0:
        return np.repeat(cloud, int(np.ceil(n_points / len(cloud))), axis=0)[:n_points]
    midpoints = 0.5 * (cloud[:, None, :] + cloud[nn_idx]).reshape(-1, 3)
    extra = n_points - len(cloud)
    if extra > len(midpoints):  # fewer points than a round's k neighbours: densify the denser cloud again
        return resample_to_count(np.concatenate([cloud, midpoints], axis=0), n_points)
    if extra < len(midpoints):
        midpoints = resample_to_count(midpoints, extra)
    return np.concatenate([cloud, midpoints[:extra]], axis=0)
