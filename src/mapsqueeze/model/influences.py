"""The encoder's compiled CPU kernels: KPConv influences and the fused bias + LeakyReLU (numba)."""

from __future__ import annotations

import numpy as np

from mapsqueeze.geometry.jit import compiled
from mapsqueeze.geometry.threads import run_over_ranges


def cpu_influences(queries: np.ndarray, source: np.ndarray, neighbors: np.ndarray, kernel_points: np.ndarray,
                   sigma: float, first: int, stop: int, out: np.ndarray | None = None) -> np.ndarray:
    """Influence max(0, 1 - |y - x - x_m| / sigma) of each neighbour y of queries x in [first, stop) on each kernel
    point x_m: (stop - first, M, K) float32 (written into `out` when given), 0 for shadow neighbours (index
    len(source)). Arrays float32 / int64 or int32 (neighbours), C-contiguous; threads over query ranges
    (`run_over_ranges`)."""
    if out is None:
        out = np.empty((stop - first, len(kernel_points), neighbors.shape[1]), dtype=np.float32)
    args = (queries, source, neighbors, kernel_points, np.float32(sigma), first)
    run_over_ranges(lambda a, b: _influence_kernel(*args, first + a, first + b, out), stop - first, 64)
    return out


@compiled
def _influence_kernel(queries, source, neighbors, kernel_points, sigma, offset, first, stop, out):
    """Fills out[q - offset] for queries q in [first, stop) (see cpu_influences)."""
    n_neighbors = neighbors.shape[1]
    relative = np.empty((3, n_neighbors), dtype=np.float32)  # one row per axis: the k loop below vectorises
    for q in range(first, stop):
        for k in range(n_neighbors):
            n = neighbors[q, k]
            for a in range(3):  # a shadow neighbour sits 1e6 away: influence 0
                relative[a, k] = source[n, a] - queries[q, a] if n < source.shape[0] else np.float32(1e6)
        for m in range(kernel_points.shape[0]):
            for k in range(n_neighbors):
                dx = relative[0, k] - kernel_points[m, 0]
                dy = relative[1, k] - kernel_points[m, 1]
                dz = relative[2, k] - kernel_points[m, 2]
                weight = np.float32(1.0) - np.sqrt(dx * dx + dy * dy + dz * dz) / sigma
                out[q - offset, m, k] = weight if weight > np.float32(0.0) else np.float32(0.0)


@compiled
def bias_leaky_relu(x, bias, slope):
    """In place, one pass over x (N, C) float32: x + bias where that is > 0, else slope * (x + bias). (numpy's
    `np.maximum(x, slope * x)` makes a temporary copy and two passes: ~8x slower on the decoder's activations.)"""
    for i in range(x.shape[0]):
        for j in range(x.shape[1]):
            value = x[i, j] + bias[j]
            x[i, j] = value if value > 0 else value * slope
