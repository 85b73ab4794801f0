"""Bring a cloud to an exact point count: an evenly spread subset to thin it, midpoints to densify it."""

import numpy as np
from pykdtree.kdtree import KDTree

from mapsqueeze.geometry.morton import spread_subset

MAX_GAP_M = 2.0
"""Densifying places midpoints only between points at most this far apart (metres), so every point it makes lies
within 1 m of a point of the cloud; across wider gaps (the raw points of a sparse tile, two walls) nothing is
invented, and a cloud without enough close pairs is filled up with copies of its points."""


def resample_to_count(cloud: np.ndarray, n_points: int | None) -> np.ndarray:
    """Thin or densify a decoded cloud to exactly n_points (deterministic).

    Thinning keeps an evenly spread subset that follows the decoder's own density (`spread_subset`: D_e 2-6 %
    lower than a uniformly random subset on the real submaps, BENCHMARKS.md). Densifying keeps the cloud and adds
    midpoints towards each point's nearest neighbours within MAX_GAP_M, in as many rounds as needed, then copies.
    """
    if n_points is None or n_points == len(cloud):
        return cloud
    if n_points <= 0:
        return cloud[:0]
    if n_points < len(cloud):
        return cloud[spread_subset(cloud, n_points)]
    extra = n_points - len(cloud)
    midpoints = _midpoints(cloud, int(np.ceil(n_points / len(cloud))))
    if len(midpoints) == 0:  # no two points within MAX_GAP_M: copies, in turn
        return np.concatenate([cloud, np.resize(cloud, (extra, 3))], axis=0)
    if extra > len(midpoints):  # fewer close pairs than points to add: densify the denser cloud again
        return resample_to_count(np.concatenate([cloud, midpoints], axis=0), n_points)
    if extra < len(midpoints):
        midpoints = resample_to_count(midpoints, extra)
    return np.concatenate([cloud, midpoints[:extra]], axis=0)


def _midpoints(cloud: np.ndarray, k: int) -> np.ndarray:
    """Midpoints between each point and its k nearest other points within MAX_GAP_M, point by point."""
    if len(cloud) < 2:
        return cloud[:0]
    distance, index = KDTree(np.ascontiguousarray(cloud)).query(np.ascontiguousarray(cloud), k=min(k + 1, len(cloud)),
                                                               distance_upper_bound=MAX_GAP_M)
    distance, index = np.atleast_2d(distance)[:, 1:], np.atleast_2d(index.astype(np.int64))[:, 1:]
    close = np.isfinite(distance) & (index < len(cloud))
    rows, columns = np.nonzero(close)
    return 0.5 * (cloud[rows] + cloud[index[rows, columns]])
