"""Distance from each point to the centre of its own cell of a regular grid, where that centre is its nearest."""

from __future__ import annotations

import numpy as np

from mapsqueeze.geometry.jit import compiled


def own_cell_distances(points: np.ndarray, edge: float, max_cell: int, upper: np.ndarray, margin: float) -> np.ndarray:
    """(N,) float64 distance (metres) from each point to the float32 centre of its cell of edge `edge` (cells
    floor(p / edge) clipped to [0, max_cell], centres clipped into [0, upper]), NaN where another cell's centre may
    be as near: within `margin` of a cell face, or where the next cell's centre on some axis would be clipped (within
    1.5 edges + margin of `upper`). On a regular grid a point's own centre is nearer than any other by
    2 x edge x (its distance to the faces), far more than float32 centres are off the grid. The distance is the one a
    k-d tree search computes: sqrt((dx^2 + dy^2) + dz^2) in float64."""
    points = np.ascontiguousarray(points, dtype=np.float64)
    out = np.empty(len(points), dtype=np.float64)
    _own_cell_kernel(points, float(edge), int(max_cell), np.asarray(upper, dtype=np.float32), float(margin), out)
    return out


@compiled
def _own_cell_kernel(points, edge, max_cell, upper, margin, out):
    for i in range(points.shape[0]):
        total = 0.0
        safe = True
        for a in range(3):
            p = points[i, a]
            cell = min(max(np.floor(p / edge), 0.0), float(max_cell))
            exact = (cell + 0.5) * edge
            centre = np.float64(min(max(np.float32(exact), np.float32(0.0)), upper[a]))
            d = p - centre
            total = total + d * d if a else d * d
            if edge / 2 - abs(p - exact) < margin or not (cell + 1.5) * edge + margin < upper[a]:
                safe = False
        out[i] = np.sqrt(total) if safe else np.nan
