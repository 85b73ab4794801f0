"""`grid.grid_subsample` and `grid.radius_neighbors` in numpy, without numba: the same indices, for the encoder's
numpy path on small maps (`codec.compress.NUMPY_KERNEL_POINTS`: loading numba costs a process ~0.5 CPU-s, more
than these take on a few thousand points)."""

from __future__ import annotations

import math

import numpy as np

from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.introsortnumpy import introsort_argsort

CELLS_PER_RADIUS = 2
"""Cell edge radius / 2 of the radius search (both paths): 5 x 5 columns of 5 cells scanned per query."""
MAX_CELLS = 1 << 22
"""Cell table entries (int64) of the radius search (both paths): 32 MB at most."""
CHUNK_CANDIDATES = 1 << 16
"""(query, scanned point) pairs tested at once (their temporaries, ~6 MB, stay in the CPU's cache)."""


def grid_subsample(points: np.ndarray, voxel_size: float, argsort=introsort_argsort) -> np.ndarray:
    """`grid.grid_subsample` (the same arguments, the same indices); `argsort` sorts the float32 keys in the order of
    torch's CPU sort: the numpy introsort here, the compiled one for `grid`."""
    pts = np.ascontiguousarray(points, dtype=np.float32)
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64)
    size = np.float32(voxel_size)
    grid = np.floor(pts / size)
    dist = ((pts - (grid + np.float32(0.5)) * size) ** 2).sum(axis=1, dtype=np.float32)
    max_dist = dist.max()
    if max_dist > 0:
        dist = dist / max_dist * np.float32(0.7)
    cells_per_axis = np.float32(math.ceil(1.0 / voxel_size))
    key = grid[:, 0] + grid[:, 1] * cells_per_axis + grid[:, 2] * cells_per_axis * cells_per_axis
    order = argsort(key + dist)
    sorted_key = key[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = sorted_key[1:] != sorted_key[:-1]
    return order[first]


def search_grid(source: np.ndarray, queries: np.ndarray, radius: float) -> tuple[np.ndarray, float, np.ndarray]:
    """The radius search's cell grid over (N, 3) float32 source and query points, for both paths: its low corner
    (float64), cell edge and table dims. Cells are a hair over radius / 2 (round-off cannot skip one), coarser only
    if the table would exceed MAX_CELLS (a cloud hundreds of radii across: more candidates per query, a coarser
    scan order); a margin of CELLS_PER_RADIUS cells on each side keeps every scanned cell inside the table."""
    (source_low, source_high), (query_low, query_high) = bounding_box(source), bounding_box(queries)
    low = np.minimum(source_low, query_low).astype(np.float64)
    extent = np.maximum(source_high, query_high) - low
    cell = radius * (1 + 1e-9) / CELLS_PER_RADIUS
    while np.prod(np.floor(extent / cell) + 2 * CELLS_PER_RADIUS + 1) > MAX_CELLS:
        cell *= 2
    return low, cell, np.floor(extent / cell).astype(np.int64) + 2 * CELLS_PER_RADIUS + 1


def neighbour_arrays(source: np.ndarray, queries: np.ndarray, max_neighbors: int,
                     dtype: type) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The radius search's inputs as contiguous float32 and its (Q, max_neighbors) result of `dtype` filled with the
    shadow index len(source), for both paths; a `dtype` too narrow to index the source is a ValueError."""
    source = np.ascontiguousarray(source, dtype=np.float32)
    queries = np.ascontiguousarray(queries, dtype=np.float32)
    if np.iinfo(dtype).max < len(source):
        raise ValueError(f"{np.dtype(dtype).name} cannot index {len(source):,} points")
    return source, queries, np.full((len(queries), max_neighbors), len(source), dtype=dtype)


def radius_neighbors(source: np.ndarray, queries: np.ndarray, radius: float, max_neighbors: int,
                     dtype: type = np.int64) -> np.ndarray:
    """`grid.radius_neighbors` (the same arguments, the same padded indices): each query's in-radius neighbours
    listed in the kernel's scan order (its 5 x 5 columns of 5 search cells, x slowest, each cell's points by
    index), capped as the kernel caps them."""
    source, queries, result = neighbour_arrays(source, queries, max_neighbors, dtype)
    n_source, n_queries = len(source), len(queries)
    most = 0
    if n_source and n_queries and max_neighbors > 0:
        low, cell, dims = search_grid(source, queries, radius)
        c = np.floor((source - low) / cell).astype(np.int64) + CELLS_PER_RADIUS
        keys = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
        order = np.argsort(keys, kind="stable")
        cell_start = np.concatenate([[0], np.cumsum(np.bincount(keys, minlength=int(np.prod(dims))))])
        sorted_points = source[order].astype(np.float64)
        q = np.floor((queries.astype(np.float64) - low) / cell).astype(np.int64)
        span = 2 * CELLS_PER_RADIUS + 1
        steps = np.arange(span)
        columns = (((q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2])[:, None]
                   + ((steps[:, None] * dims[1] + steps[None, :]) * dims[2]).ravel()[None, :])  # (Q, 25), scan order
        starts, stops = cell_start[columns], cell_start[columns + span]
        scanned = (stops - starts).sum(axis=1)
        first = 0
        while first < n_queries:  # query ranges of about CHUNK_CANDIDATES scanned points
            stop = first + 1 + int(np.searchsorted(np.cumsum(scanned[first:]), CHUNK_CANDIDATES, side="right"))
            stop = min(stop, n_queries)
            most = max(most, _fill(result, first, stop, queries, starts, stops, sorted_points, order, radius,
                                   max_neighbors))
            first = stop
    return np.ascontiguousarray(result[:, :int(min(max_neighbors, most))])


def _fill(result: np.ndarray, first: int, stop: int, queries: np.ndarray, starts: np.ndarray, stops: np.ndarray,
          sorted_points: np.ndarray, order: np.ndarray, radius: float, max_neighbors: int) -> int:
    """result[first:stop] for queries [first, stop) from their scanned runs [starts, stops) of the sorted points;
    the largest in-radius count among them."""
    lengths = (stops[first:stop] - starts[first:stop]).ravel()
    total = int(lengths.sum())
    run_of = np.repeat(np.arange(len(lengths)), lengths)
    scanned = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(lengths) - lengths, lengths) \
        + starts[first:stop].ravel()[run_of]
    query = first + run_of // starts.shape[1]
    near = sorted_points[scanned]
    point = queries[query].astype(np.float64)
    ddx, ddy, ddz = near[:, 0] - point[:, 0], near[:, 1] - point[:, 1], near[:, 2] - point[:, 2]
    inside = ddx * ddx + ddy * ddy + ddz * ddz <= radius * radius
    found, owner = order[scanned[inside]], query[inside] - first
    counts = np.bincount(owner, minlength=stop - first)
    offsets = np.cumsum(counts) - counts
    for j in range(max_neighbors):
        rows = np.flatnonzero(counts > j)
        if not len(rows):
            break
        m = counts[rows]
        result[first + rows, j] = found[offsets[rows] + np.maximum((m * j) // max_neighbors, j)]
    return int(counts.max(initial=0))
