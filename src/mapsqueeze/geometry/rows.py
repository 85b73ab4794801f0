"""Selecting whole rows of a point array."""

from __future__ import annotations

import numpy as np


def select_rows(points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """points[mask] of a C-contiguous (N, k) array and an (N,) boolean mask, the same rows in the same order.

    numpy selects an (N, 3) array's rows element by element; as one k-element record per row the copy is ~10x
    faster (0.5 against 6 ms for 512k float32 rows)."""
    if not points.flags.c_contiguous:
        return points[mask]
    records = points.view(np.dtype((np.void, points.itemsize * points.shape[1]))).reshape(len(points))
    return records[mask].view(points.dtype).reshape(-1, points.shape[1])
