"""Grid subsampling and capped radius neighbours: the two geometric operations of the KPConv encoder.

Both follow the reference implementation's arithmetic so that its checkpoints reproduce their embeddings:
coordinates are normalised (metres / map size), voxel keys and tie-breaking distances are float32.
"""

from __future__ import annotations

import numpy as np

from mapsqueeze.geometry import gridnumpy
from mapsqueeze.geometry.gridnumpy import CELLS_PER_RADIUS
from mapsqueeze.geometry.introsort import introsort_argsort
from mapsqueeze.geometry.jit import compiled
from mapsqueeze.geometry.threads import run_over_ranges


def grid_subsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """Indices of the points kept by grid subsampling: per occupied voxel, the point nearest to the voxel centre.

    points: (N, 3) float32 normalised coordinates in [0, 1) (tile-local metres / map size);
    voxel_size: voxel edge in the same normalised unit. Returns int64 indices ordered by voxel key (x fastest).
    The sort key (voxel key + 0.7 * d^2 / max d^2) is float32 and sorted in the order of torch's CPU sort
    (`introsort_argsort`), exactly like the reference, so that ties resolve the same way and its checkpoints keep
    the same embedding points.
    """
    return gridnumpy.grid_subsample(points, voxel_size, argsort=introsort_argsort)


def radius_neighbors(source: np.ndarray, queries: np.ndarray, radius: float, max_neighbors: int,
                     dtype: type = np.int64) -> np.ndarray:
    """Padded neighbour indices of each query within `radius`, capped at `max_neighbors`.

    Neighbours are those at distance <= radius (float64 of the float32 inputs), listed in scan order: by search
    cell (edge a hair over radius / 2, doubled until the cell table fits MAX_CELLS; anchored at the lowest corner
    of source and queries; x slowest, z fastest), then by index. When a query has m > max_neighbors of them, an
    evenly spread subset is kept: column j holds the neighbour at position floor(m * j / max_neighbors) of that
    list (the reference's rule, applied to its octree's order; a scan of cells is likewise spatial). Missing
    entries hold len(source) (a "shadow" index). Returns (Q, K) of `dtype` (int64, or int32 for a source of
    fewer than 2^31 points: half the memory), K = the largest count (<= cap). A compiled
    kernel scans the 5 x 5 x 5 cells around each query on torch.get_num_threads() threads over contiguous query
    ranges; the result does not depend on the thread count.
    """
    source, queries, result = gridnumpy.neighbour_arrays(source, queries, max_neighbors, dtype)
    n_source, n_queries = len(source), len(queries)
    counts = np.zeros(n_queries, dtype=np.int64)
    if n_source and n_queries and max_neighbors > 0:
        low, cell, dims = gridnumpy.search_grid(source, queries, radius)
        cell_start, order, sorted_points = _cell_table(source, low, cell, dims, CELLS_PER_RADIUS)
        run_over_ranges(lambda first, stop: _capped_neighbors_kernel(
            cell_start, sorted_points, order, queries, first, stop, low, cell, dims, radius * radius, max_neighbors,
            CELLS_PER_RADIUS, result, counts), n_queries)
    return np.ascontiguousarray(result[:, :int(min(max_neighbors, counts.max(initial=0)))])


@compiled
def _cell_table(points, low, cell, dims, margin):
    """(cell_start, order, sorted_points) of the points in the search cells: each point's cell key (row-major, z
    fastest, offset by the scan margin of `margin` cells), its cell the floor of (float64 point - low) / cell; the
    cell table (the points of cell c are order[cell_start[c]:cell_start[c + 1]]), order listing the points by key,
    then by index (a counting sort, stable: numpy's stable argsort of the keys); sorted_points (3, N) float64 their
    coordinates in that order, one row per axis."""
    n, n_cells = points.shape[0], dims[0] * dims[1] * dims[2]
    keys = np.empty(n, dtype=np.int64)
    cell_start = np.zeros(n_cells + 1, dtype=np.int64)
    for i in range(n):
        c0 = np.int64(np.floor((np.float64(points[i, 0]) - low[0]) / cell)) + margin
        c1 = np.int64(np.floor((np.float64(points[i, 1]) - low[1]) / cell)) + margin
        c2 = np.int64(np.floor((np.float64(points[i, 2]) - low[2]) / cell)) + margin
        keys[i] = (c0 * dims[1] + c1) * dims[2] + c2
        cell_start[keys[i] + 1] += 1
    for c in range(n_cells):
        cell_start[c + 1] += cell_start[c]
    fill = cell_start[:n_cells].copy()
    order = np.empty(n, dtype=np.int64)
    for i in range(n):
        order[fill[keys[i]]] = i
        fill[keys[i]] += 1
    sorted_points = np.empty((3, n), dtype=np.float64)
    for s in range(n):
        for a in range(3):
            sorted_points[a, s] = np.float64(points[order[s], a])
    return cell_start, order, sorted_points


@compiled
def _capped_neighbors_kernel(cell_start, sorted_points, order, queries, first, stop, low, cell, dims, radius2,
                             max_neighbors, cells_per_radius, result, counts):
    """Fills result[first:stop] and counts[first:stop]: the capped in-radius neighbours of queries[first:stop].
    The queries are visited cell by cell (their results do not depend on the order): the points of a cell's
    5 x 5 x 5 scanned cells are gathered once, in scan order, for all its queries, whose distance tests then run
    over one contiguous run (vectorised) before the in-radius points are listed; the spread positions
    floor(m * j / max_neighbors) are stepped through without a division."""
    n = len(order)
    xs, ys, zs = sorted_points[0], sorted_points[1], sorted_points[2]
    near_x, near_y, near_z = np.empty(n), np.empty(n), np.empty(n)
    near_index = np.empty(n, dtype=np.int64)
    inside = np.empty(n, dtype=np.uint8)
    found = np.empty(n, dtype=np.int64)
    span = 2 * cells_per_radius + 1
    keys = np.empty(stop - first, dtype=np.int64)
    for q in range(first, stop):
        cx = int(np.floor((np.float64(queries[q, 0]) - low[0]) / cell))
        cy = int(np.floor((np.float64(queries[q, 1]) - low[1]) / cell))
        cz = int(np.floor((np.float64(queries[q, 2]) - low[2]) / cell))
        keys[q - first] = (cx * dims[1] + cy) * dims[2] + cz  # its first scanned cell: z cells cz-margin..cz+margin
    visit = np.argsort(keys)
    gathered_key, n_near = -1, 0
    for position in range(stop - first):
        q = first + visit[position]
        key = keys[q - first]
        if key != gathered_key:
            gathered_key, n_near = key, 0
            for dx in range(span):
                for dy in range(span):
                    column = key + (dx * dims[1] + dy) * dims[2]
                    for s in range(cell_start[column], cell_start[column + span]):
                        near_x[n_near], near_y[n_near], near_z[n_near] = xs[s], ys[s], zs[s]
                        near_index[n_near] = order[s]
                        n_near += 1
        qx, qy, qz = np.float64(queries[q, 0]), np.float64(queries[q, 1]), np.float64(queries[q, 2])
        for s in range(n_near):
            ddx = near_x[s] - qx
            ddy = near_y[s] - qy
            ddz = near_z[s] - qz
            inside[s] = ddx * ddx + ddy * ddy + ddz * ddz <= radius2
        m = 0
        for s in range(n_near):
            found[m] = near_index[s]  # kept when in the radius (no branch: the test is unpredictable)
            m += inside[s]
        counts[q] = m
        step, part = m // max_neighbors, m % max_neighbors
        spread, remainder = 0, 0  # spread = floor(m * j / max_neighbors), remainder = m * j % max_neighbors
        for j in range(min(m, max_neighbors)):
            result[q, j] = found[max(spread, j)]
            spread += step
            remainder += part
            carry = remainder >= max_neighbors
            remainder -= carry * max_neighbors
            spread += carry
