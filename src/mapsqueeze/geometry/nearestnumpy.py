"""`nearest.NearestGrid` without numba: the same distances from a k-d tree (pykdtree, whose search computes them
as the grid's kernel does: the square root of ((dx^2 + dy^2) + dz^2) in float64 of the nearest point), for the
encoder's numpy path on small maps (`codec.compress.NUMPY_KERNEL_POINTS`)."""

from __future__ import annotations

import numpy as np


class NearestTree:
    """`nearest.NearestGrid`'s interface over a k-d tree of a non-empty (N, 3) cloud."""

    def __init__(self, points: np.ndarray):
        from pykdtree.kdtree import KDTree

        points = np.ascontiguousarray(points, dtype=np.float64)
        if not len(points) or not np.isfinite(points).all():
            raise ValueError("a nearest-point tree needs at least one point, all finite")
        self.tree = KDTree(points)

    def distances(self, queries: np.ndarray) -> np.ndarray:
        """(Q,) float64 distance from each (Q, 3) query to its nearest point of the cloud."""
        return self.tree.query(np.ascontiguousarray(queries, dtype=np.float64), k=1)[0]
