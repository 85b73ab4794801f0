"""`influences.cpu_influences` in numpy, without numba: the same float32 influences, for the encoder's numpy path
on small maps (`codec.compress.NUMPY_KERNEL_POINTS`)."""

from __future__ import annotations

import numpy as np


def cpu_influences(queries: np.ndarray, source: np.ndarray, neighbors: np.ndarray, kernel_points: np.ndarray,
                   sigma: float, first: int, stop: int, out: np.ndarray | None = None) -> np.ndarray:
    """`influences.cpu_influences` (the same arguments and values): max(0, 1 - |y - x - x_m| / sigma) in the
    kernel's float32 operations, ((dx^2 + dy^2) + dz^2), 0 for shadow neighbours (index len(source), 1e6 away).
    Each square is computed once per distinct kernel-point coordinate (a grid kernel has 3 per axis), each
    dx^2 + dy^2 once per distinct (x, y) pair."""
    if out is None:
        out = np.empty((stop - first, len(kernel_points), neighbors.shape[1]), dtype=np.float32)
    rows = np.asarray(neighbors[first:stop])
    shadow = rows >= len(source)
    kernel_points = np.asarray(kernel_points, dtype=np.float32)
    squares = []  # per axis: {coordinate: (dx^2 of every neighbour)}
    for a in range(3):
        relative = np.asarray(source, dtype=np.float32)[np.where(shadow, 0, rows), a]
        relative -= queries[first:stop, a, None].astype(np.float32)
        relative[shadow] = np.float32(1e6)  # a shadow neighbour sits 1e6 away: influence 0
        axis = {}
        for value in sorted(set(kernel_points[:, a].tolist())):
            difference = relative - np.float32(value)
            axis[value] = np.multiply(difference, difference, out=difference)
        squares.append(axis)
    planar = {}
    sigma = np.float32(sigma)
    for m, (x, y, z) in enumerate(kernel_points.tolist()):
        if (x, y) not in planar:
            planar[x, y] = squares[0][x] + squares[1][y]
        distance = planar[x, y] + squares[2][z]
        np.sqrt(distance, out=distance)
        distance /= sigma
        np.subtract(np.float32(1.0), distance, out=distance)
        np.maximum(distance, np.float32(0.0), out=out[:, m, :])  # 1 - d / sigma is never -0.0 or NaN
    return out
