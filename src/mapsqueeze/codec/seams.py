"""Decode-side density rule at the faces between two occupied tiles (no seams in a multi-tile map).

The encoder's last grid subsampling keeps, in each voxel, the point nearest to the voxel's centre. A voxel cut by
the tile's upper face has its centre beyond the face, so the point it keeps lies on the face: a tile holds several
times more embedding points within a few centimetres of such a face than elsewhere, and the decoder grows a clump
of points around each. The decoded tile piles up in a band just inside the face (on the 6-tile KITTI map of
BENCHMARKS.md, "Seams at tile faces": up to 8x the density of the band behind it, 3-12 cm inside the face at
y = 53.7 m), which shows as a sheet of points along the face.

The rule, on a network tile's decoded points, at each side of its points' box that lies on a face shared with
another occupied tile of the file: the points within NEAR_BAND_M of the face are split into columns of
COLUMN_M x COLUMN_M across the face and slices SLICE_M thick along it; a slice holding more points than the
density of its column's band behind the face (BEHIND_BAND_M deep, behind NEAR_BAND_M) allows keeps an evenly
spread subset of that many (every (n / allowed)-th along the Morton order, as `geometry.morton.spread_subset`). A column with nothing behind is left as it is (a
surface lying along the face).
It uses the decoded points and the tile table only, so the result does not depend on which other tiles are decoded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.container import TileCoding, TileEntry
from mapsqueeze.geometry.morton import morton_rank
from mapsqueeze.geometry.rows import select_rows

NEAR_BAND_M = 0.15
"""Depth (metres) of the band inside a face whose density is limited: the pile-up reaches 10-12 cm at e0."""

BEHIND_BAND_M = 0.30
"""Depth (metres) of the band behind it that sets the density limit."""

COLUMN_M = 1.0
"""Edge (metres) of the columns across the face in which the two bands are compared."""

SLICE_M = 0.01
"""Thickness (metres) of the slices of the near band that are held to that density each."""


@dataclass(frozen=True)
class InternalFace:
    """A side of a tile's points box on a face shared with another occupied tile: the axis (0, 1, 2), whether it is
    the box's upper side, and its coordinate in the tile's coding frame (metres)."""

    axis: int
    upper: bool
    plane_m: float


def internal_faces(entry: TileEntry, occupied: set[tuple[int, int, int]], tile_size: np.ndarray
                   ) -> tuple[InternalFace, ...]:
    """The sides of a network tile's points box that lie within NEAR_BAND_M of a grid face shared with a tile of
    `occupied` (the indices of every tile in the file), as planes in the tile's coding frame; none for a tile coded
    otherwise (raw and octree tiles do not pile up)."""
    if entry.coding is not TileCoding.network:
        return ()
    faces = []
    bounds_m = entry.bounds_m(tile_size)
    extent = bounds_m[1] - bounds_m[0]
    for axis in range(3):
        for upper in (False, True):
            neighbour = list(entry.index)
            neighbour[axis] += 1 if upper else -1
            face_local = float(tile_size[axis]) if upper else 0.0
            side = float(bounds_m[1 if upper else 0][axis])
            if tuple(neighbour) in occupied and abs(side - face_local) < NEAR_BAND_M:
                faces.append(InternalFace(axis, upper, float(extent[axis]) if upper else 0.0))
    return tuple(faces)


def thin_at_faces(cloud: np.ndarray, faces: tuple[InternalFace, ...]) -> np.ndarray:
    """The (K, 3) frame-local points of a decoded tile with the density rule applied at each face (in order): a
    subset of `cloud`, in its order (deterministic); `cloud` itself when there is no face."""
    if not faces:
        return cloud
    keep = np.ones(len(cloud), dtype=bool)
    for face in faces:
        depth = np.abs(cloud[:, face.axis].astype(np.float64) - face.plane_m)
        banded = np.flatnonzero(keep & (depth < NEAR_BAND_M + BEHIND_BAND_M))  # the near and behind bands
        keep[banded[_excess(cloud[banded], depth[banded], face.axis)]] = False
    return select_rows(cloud, keep)


def _excess(points: np.ndarray, depth: np.ndarray, axis: int) -> np.ndarray:
    """Boolean mask of the points (within NEAR_BAND_M + BEHIND_BAND_M of a face across `axis`, at `depth` metres
    from it) that the rule removes: in each (column, slice) over its allowance, all but every (n / allowed)-th
    point along the Morton order of the points (`geometry.morton`, as `spread_subset`)."""
    excess = np.zeros(len(points), dtype=bool)
    if len(points) == 0:
        return excess
    near = depth < NEAR_BAND_M
    cells = np.floor(np.delete(points, axis, axis=1).astype(np.float64) / COLUMN_M).astype(np.int64)
    cells -= cells.min(axis=0)
    _, column = np.unique(cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1], return_inverse=True)
    column = column.ravel()
    n_columns = int(column.max()) + 1
    behind_counts = np.bincount(column[~near], minlength=n_columns)
    # Allowed per slice: the behind band's density over the slice, rounded so that the slices of a column add up.
    n_slices = int(np.ceil(NEAR_BAND_M / SLICE_M))
    reach = np.minimum(np.arange(n_slices + 1) * SLICE_M, NEAR_BAND_M) / BEHIND_BAND_M
    cumulative = np.floor(behind_counts[:, None] * reach[None, :] + 0.5).astype(np.int64)
    allowed = np.diff(cumulative, axis=1).ravel()  # (column * n_slices + slice) -> points allowed
    candidates = np.flatnonzero(near)
    group = column[candidates] * n_slices + np.minimum(depth[candidates] // SLICE_M, n_slices - 1).astype(np.int64)
    counts = np.bincount(group, minlength=n_columns * n_slices)
    over = (counts > allowed) & np.repeat(behind_counts > 0, n_slices)
    candidates, group = candidates[over[group]], group[over[group]]
    if len(candidates) == 0:
        return excess
    order = np.lexsort((morton_rank(points[candidates]), group))  # by group, then along the Morton order
    candidates, group = candidates[order], group[order]
    n, quota = counts[group], allowed[group]
    position = np.arange(len(group)) - np.searchsorted(group, group)  # rank within its group
    pick = (position * quota + n - 1) // n  # the first j with j * n >= position * quota
    excess[candidates[(pick >= quota) | (pick * n >= (position + 1) * quota)]] = True
    return excess
