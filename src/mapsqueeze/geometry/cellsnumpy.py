"""`cells.own_cell_distances` in numpy, without numba: the same distances, for the encoder's numpy path on small
maps (`codec.compress.NUMPY_KERNEL_POINTS`)."""

from __future__ import annotations

import numpy as np


def own_cell_distances(points: np.ndarray, edge: float, max_cell: int, upper: np.ndarray, margin: float) -> np.ndarray:
    """`cells.own_cell_distances` (the same arguments and values, the kernel's operations axis by axis)."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float32)
    edge, margin = float(edge), float(margin)
    total = np.zeros(len(points))
    safe = np.ones(len(points), dtype=bool)
    for a in range(3):
        p = points[:, a]
        cell = np.minimum(np.maximum(np.floor(p / edge), 0.0), float(max_cell))
        exact = (cell + 0.5) * edge
        centre = np.minimum(np.maximum(exact.astype(np.float32), np.float32(0.0)), upper[a]).astype(np.float64)
        d = p - centre
        total = total + d * d if a else d * d
        safe &= ~((edge / 2 - np.abs(p - exact) < margin) | ~((cell + 1.5) * edge + margin < upper[a]))
    return np.where(safe, np.sqrt(total), np.nan)
