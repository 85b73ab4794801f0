"""Bring a cloud to an exact point count: an evenly spread subset to thin it, midpoints to densify it."""

import numpy as np
from pykdtree.kdtree import KDTree

from mapsqueeze.geometry.morton import spread_subset

MAX_GAP_M = 2.0
"""Densifying places midpoints only between points at most this far apart (metres), so every point it makes lies
within 1 m of a point of the cloud; a point without such a neighbour is copied instead, so nothing is invented
across wider gaps (the raw points of a sparse tile, two walls) and every point adds its share."""


def resample_to_count(cloud: np.ndarray, n_points: int | None) -> np.ndarray:
    """Thin or densify a decoded cloud to exactly n_points (deterministic).

    Thinning keeps an evenly spread subset that follows the decoder's own density (`spread_subset`: D_e 2-6 %
    lower than a uniformly random subset on the real submaps, BENCHMARKS.md). Densifying keeps the cloud and adds,
    for each point, the midpoints towards its nearest neighbours (copies of itself for those farther than
    MAX_GAP_M), as many rounds as needed, then an evenly spread subset of what was added.
    """
    if n_points is None or n_points == len(cloud):
        return cloud
    if n_points <= 0:
        return cloud[:0]
    if n_points < len(cloud):
        return cloud[spread_subset(cloud, n_points)]
    if len(cloud) == 1:
        return np.repeat(cloud, n_points, axis=0)
    extra = n_points - len(cloud)
    added, any_close = _neighbour_midpoints(cloud, int(np.ceil(n_points / len(cloud))))
    if extra > len(added) and not any_close:  # no two points within MAX_GAP_M: copies, in turn
        return np.concatenate([cloud, np.resize(cloud, (extra, 3))], axis=0)
    if extra > len(added):  # fewer points than a round's neighbours: densify the denser cloud again
        return resample_to_count(np.concatenate([cloud, added], axis=0), n_points)
    if extra < len(added):
        added = resample_to_count(added, extra)
    return np.concatenate([cloud, added[:extra]], axis=0)


def _neighbour_midpoints(cloud: np.ndarray, k: int) -> tuple[np.ndarray, bool]:
    """Point by point, the midpoints between it and its k nearest other points (at most len - 1), each one the
    point itself where that neighbour lies farther than MAX_GAP_M; and whether any neighbour lies within it."""
    tree = KDTree(np.ascontiguousarray(cloud))
    _, index = tree.query(np.ascontiguousarray(cloud), k=min(k + 1, len(cloud)), distance_upper_bound=MAX_GAP_M)
    index = np.atleast_2d(index.astype(np.int64))[:, 1:]
    close = index < len(cloud)
    index = np.where(close, index, np.arange(len(cloud))[:, None])  # beyond MAX_GAP_M: itself
    return (0.5 * (cloud[:, None, :] + cloud[index])).reshape(-1, 3), bool(close.any())
