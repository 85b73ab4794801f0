"""The KPConv geometry both forwards share (torch's `kpconv.KPConv` and numpy's `inference.InferenceNetwork`):
kernel points, their influence extent and the chunking of queries (the compiled kernels are in `influences`, so
that the decoder, which needs none of them, runs without numba)."""

from __future__ import annotations

import math

import numpy as np

CHUNK_ELEMENTS = 1 << 21
"""(query, neighbour, kernel point) triples of one chunk of queries: the (Q, M, K) influences then stay in cache
instead of being allocated whole (~6x faster on the CPU)."""


def grid_kernel_points(radius: float, num_kernel_points: int = 27) -> np.ndarray:
    """Kernel points on a regular n x n x n grid inside the sphere of `radius` (corners at distance radius)."""
    n = round(num_kernel_points ** (1 / 3))
    if n**3 != num_kernel_points:
        raise ValueError(f"num_kernel_points must be a cube, got {num_kernel_points}")
    axis = np.linspace(-1.0, 1.0, n)
    mesh = np.meshgrid(axis, axis, axis)  # 'xy' indexing: the reference's kernel order
    points = np.stack([m.reshape(-1) for m in mesh], axis=1) / math.sqrt(3.0)
    return (points * radius).astype(np.float32)


def kernel_sigma(radius: float, num_kernel_points: int) -> float:
    """Influence extent of each kernel point: 1.5 grid spacings of the kernel (units of `radius`)."""
    return radius / (round(num_kernel_points ** (1 / 3)) - 1) * 1.5


def query_chunk(n_neighbors: int, n_kernel_points: int) -> int:
    """Queries per chunk (CHUNK_ELEMENTS triples)."""
    return max(1, CHUNK_ELEMENTS // max(1, n_neighbors * n_kernel_points))
