"""Exact nearest-neighbour distances from a uniform grid of cells: for a few thousand queries against a cloud
(the encoder's D_e estimates, `codec.distortion`), counting the cloud's points into cells costs a fraction of a k-d
tree's build, and each query scans the cells around its own shell by shell until no unscanned point can be nearer.
The distances are those of a k-d tree search (`metrics.nearest_tree`): sqrt((dx^2 + dy^2) + dz^2) in float64 of the
nearest point."""

from __future__ import annotations

import numpy as np

from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.jit import compiled

CELLS_PER_POINT = 0.25
"""Cells of the grid per point of the cloud, about (the box cut into cubes): on decoded tiles, whose points lie on
surfaces, fewer larger cells cost less to scan than many small ones, most of them empty."""

MAX_CELLS_PER_AXIS = 1 << 10
"""Cells along one axis at most (a flat or thin cloud's box has little volume: its cells are sized along its
longer axes)."""

MAX_SHELLS = 8
"""Shells of cells a query scans around its own before it is left to a k-d tree (a query far from the cloud: the
shells would grow over the whole grid)."""


class NearestGrid:
    """The points of a non-empty (N, 3) cloud counted into the cells of a uniform grid over their box."""

    def __init__(self, points: np.ndarray):
        points = np.ascontiguousarray(points, dtype=np.float64)
        if not len(points) or not np.isfinite(points).all():
            raise ValueError("a nearest-point grid needs at least one point, all finite")
        low, high = bounding_box(points)
        extent = high - low
        edge = max(float(np.prod(extent) / (CELLS_PER_POINT * len(points))) ** (1 / 3),
                   float(extent.max()) / MAX_CELLS_PER_AXIS, 1e-9)
        while np.prod(np.floor(extent / edge) + 1) > max(64.0, 2 * CELLS_PER_POINT * len(points)):
            edge *= 2
        self.low, self.edge = low, edge
        self.dims = (np.floor(extent / edge) + 1).astype(np.int64)
        self.margin = 1e-9 * (edge + float(np.abs(low).max() + extent.max()))  # round-off of a point's cell
        self.cell_start = np.zeros(int(np.prod(self.dims)) + 1, dtype=np.int64)
        self.sorted = np.empty((3, len(points)))  # one row per axis, cell after cell
        _count_into_cells(points, low, edge, self.dims, self.cell_start, self.sorted)

    def distances(self, queries: np.ndarray) -> np.ndarray:
        """(Q,) float64 distance from each (Q, 3) query to its nearest point of the cloud."""
        queries = np.ascontiguousarray(queries, dtype=np.float64)
        out = np.empty(len(queries))
        _nearest_kernel(self.sorted, self.cell_start, self.low, self.edge, self.dims, self.margin, queries, out)
        far = np.isnan(out)
        if far.any():
            from pykdtree.kdtree import KDTree

            out[far] = KDTree(np.ascontiguousarray(self.sorted.T)).query(queries[far], k=1)[0]
        return out


@compiled
def _cell_of(value, low, edge, size):
    """The cell index along one axis of a coordinate, clamped into [0, size - 1]."""
    return min(max(np.int64(np.floor((value - low) / edge)), 0), size - 1)


@compiled
def _count_into_cells(points, low, edge, dims, cell_start, sorted_points):
    """Counting sort of the points by cell (x slowest, z fastest): cell c's points in sorted_points[:, cell_start[c]:
    cell_start[c + 1]], in their order."""
    n = points.shape[0]
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):  # no branch: vectorised
        cx = min(max(np.int64(np.floor((points[i, 0] - low[0]) / edge)), 0), dims[0] - 1)
        cy = min(max(np.int64(np.floor((points[i, 1] - low[1]) / edge)), 0), dims[1] - 1)
        cz = min(max(np.int64(np.floor((points[i, 2] - low[2]) / edge)), 0), dims[2] - 1)
        keys[i] = (cx * dims[1] + cy) * dims[2] + cz
    for i in range(n):
        cell_start[keys[i] + 1] += 1
    for c in range(1, cell_start.shape[0]):
        cell_start[c] += cell_start[c - 1]
    filled = cell_start[:-1].copy()
    for i in range(n):
        row = filled[keys[i]]
        filled[keys[i]] += 1
        sorted_points[0, row], sorted_points[1, row], sorted_points[2, row] = points[i, 0], points[i, 1], points[i, 2]


@compiled
def _scan_run(sorted_points, first, stop, qx, qy, qz, best):
    """The smaller of best and the squared distance ((dx^2 + dy^2) + dz^2) from (qx, qy, qz) to each sorted point
    first .. stop - 1 (points of consecutive cells)."""
    for s in range(first, stop):
        dx = qx - sorted_points[0, s]
        dy = qy - sorted_points[1, s]
        dz = qz - sorted_points[2, s]
        best = min(best, dx * dx + dy * dy + dz * dz)
    return best


@compiled
def _nearest_kernel(sorted_points, cell_start, low, edge, dims, margin, queries, out):
    """out[i]: the distance from queries[i] to its nearest point. Shell r holds the cells r cells (Chebyshev) from
    the query's own (clamped into the grid); after it, every unscanned point lies beyond a face of the scanned block
    on some axis, at least the query's distance to that face (less the round-off margin): the scan stops once the
    nearest distance found is within it, or the block covers the grid; NaN where MAX_SHELLS shells did not
    settle it."""
    for i in range(queries.shape[0]):
        qx, qy, qz = queries[i, 0], queries[i, 1], queries[i, 2]
        cx = _cell_of(qx, low[0], edge, dims[0])
        cy = _cell_of(qy, low[1], edge, dims[1])
        cz = _cell_of(qz, low[2], edge, dims[2])
        best = np.inf
        r = 0
        while True:
            z_low, z_high = max(cz - r, 0), min(cz + r, dims[2] - 1)
            for x in range(max(cx - r, 0), min(cx + r, dims[0] - 1) + 1):
                for y in range(max(cy - r, 0), min(cy + r, dims[1] - 1) + 1):
                    column = (x * dims[1] + y) * dims[2]
                    if abs(x - cx) == r or abs(y - cy) == r:  # on the shell: the block's z cells, one run
                        best = _scan_run(sorted_points, cell_start[column + z_low], cell_start[column + z_high + 1],
                                         qx, qy, qz, best)
                    else:  # inside the shell's x, y range: its two z faces
                        if cz - r >= 0:
                            best = _scan_run(sorted_points, cell_start[column + cz - r],
                                             cell_start[column + cz - r + 1], qx, qy, qz, best)
                        if r > 0 and cz + r < dims[2]:
                            best = _scan_run(sorted_points, cell_start[column + cz + r],
                                             cell_start[column + cz + r + 1], qx, qy, qz, best)
            if r == MAX_SHELLS:  # a query far from the cloud: left to the caller
                best = np.nan
                break
            bound = np.inf
            for axis in range(3):
                value = qx if axis == 0 else (qy if axis == 1 else qz)
                cell = cx if axis == 0 else (cy if axis == 1 else cz)
                if cell - r > 0:
                    bound = min(bound, value - (low[axis] + (cell - r) * edge))
                if cell + r < dims[axis] - 1:
                    bound = min(bound, low[axis] + (cell + r + 1) * edge - value)
            if bound == np.inf:
                break
            bound -= margin
            if bound > 0 and best <= bound * bound:
                break
            r += 1
        out[i] = np.sqrt(best)
