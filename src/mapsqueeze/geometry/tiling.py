"""Grid tiling of a large map into boxes (default 40 x 40 x 15 m, the paper's submap size) for the codec.

Tiles lie on a grid anchored at a float64 origin: tile (i, j, k) covers [origin + (i, j, k) * size,
origin + (i + 1, j + 1, k + 1) * size) (half-open, so each point lands in exactly one tile; on a fitted grid the
last tile of an axis also takes the points on its upper face). The default grid is fitted to the map: as few
tiles per axis as its extent needs, centred on it, so a 40 x 40 m submap is one tile wherever it lies.
Coordinates inside a tile are float32 offsets from the tile's float64 origin, computed in float64 before the
cast, so maps in UTM or other large coordinates keep sub-millimetre precision.
"""

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.validation import validate_points
from mapsqueeze.geometry.voxel import as_lengths, pack_indices

TILE_SIZE_M = (40.0, 40.0, 15.0)
"""The paper's submap size (x, y, z) in metres."""


def to_local(points: np.ndarray, origin: np.ndarray, size: np.ndarray | None = None) -> np.ndarray:
    """float32 coordinates of float64 `points` relative to the float64 `origin` (subtract, then cast).

    With `size`, values that rounding puts just outside the box (float32 rounding up onto its upper face, or
    float64 rounding of a point on a face) are clamped into [0, size): a shift under 4 microns for 40 m boxes.
    """
    points, origin = np.asarray(points, dtype=np.float64), np.asarray(origin, dtype=np.float64)
    local = np.empty(np.broadcast_shapes(points.shape, origin.shape), dtype=np.float32)
    points, origin = np.broadcast_to(points, local.shape), np.broadcast_to(origin, local.shape)
    upper = None if size is None else np.broadcast_to(
        np.nextafter(np.asarray(size, dtype=np.float32), np.float32(0)), local.shape)
    # axis by axis on the strided columns: numpy's (N, 3) - (3,) runs a 3-long inner loop per row (2-5x slower)
    for axis in range(local.shape[-1]):
        column = local[..., axis]
        np.subtract(points[..., axis], origin[..., axis], out=column, casting="unsafe")  # float64 rounded to float32
        if upper is not None:
            np.clip(column, np.float32(0), upper[..., axis], out=column)
    return local


@dataclass(frozen=True)
class Tile:
    """One occupied grid cell: its (i, j, k) index, float64 origin (lower corner, metres) and the map's points in it."""

    index: tuple[int, int, int]
    origin: np.ndarray
    size: np.ndarray
    point_indices: np.ndarray  # int64 indices into the tiled map, ascending

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64: lower and upper corner in metres (upper excluded)."""
        return np.stack([self.origin, self.origin + self.size])

    def local_points(self, points: np.ndarray) -> np.ndarray:
        """This tile's points of the map `points` as float32 offsets from the tile origin, in [0, size)."""
        return to_local(points[self.point_indices], self.origin, self.size)


def fit_grid(lowest: np.ndarray, highest: np.ndarray, tile_size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The default grid of a map with bounding box [lowest, highest] (metres): n = max(1, ceil(extent / size))
    tiles per axis, centred on the box. Returns (origin, n): float64 lower corner, int64 tiles per axis."""
    lowest, highest = np.asarray(lowest, dtype=np.float64), np.asarray(highest, dtype=np.float64)
    size = np.asarray(tile_size, dtype=np.float64)
    extent = highest - lowest
    shape = np.maximum(1, np.ceil(extent / size)).astype(np.int64)
    return lowest - (shape * size - extent) / 2, shape


def tile_map(
    points: np.ndarray,
    tile_size: float | Iterable[float] = TILE_SIZE_M,
    origin: Iterable[float] | None = None,
    shape: Iterable[int] | None = None,
) -> list[Tile]:
    """Split (N, 3) float64 map points into non-empty tiles, ordered by index (i, then j, then k).

    Default grid: `fit_grid` of the points. A given `origin` anchors the grid (indices may be negative for points
    below it); a given `shape` (tiles per axis of a fitted grid holding every point) puts points on the grid's
    upper faces into its last tiles. One stable argsort on packed tile keys: O(N log N), fine for tens of
    millions of points.
    """
    points = validate_points(points, name="map")
    size = as_lengths(tile_size, "tile size")
    if origin is None:
        anchor, shape = fit_grid(*bounding_box(points), size)
    else:
        anchor = np.asarray(origin, dtype=np.float64).reshape(3)
    # A point on a face whose grid line float64 cannot represent exactly may fall a hair (~1e-10 m) outside its
    # tile's box; `to_local` clamps it.
    indices = np.empty((3, len(points)), dtype=np.int64).T  # (N, 3), each axis's column contiguous
    # axis by axis (as `to_local`): the same operations on each value, ~9x faster than on the (N, 3) array
    column = np.empty(len(points))
    for axis in range(3):
        np.subtract(points[:, axis], anchor[axis], out=column)
        column /= size[axis]
        indices[:, axis] = np.floor(column, out=column)
        if shape is not None:
            np.clip(indices[:, axis], 0, int(shape[axis]) - 1, out=indices[:, axis])
    keys = pack_indices(indices)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    tiles = []
    for group in np.split(order, starts[1:]):
        index = indices[group[0]]
        tiles.append(Tile(tuple(int(value) for value in index), anchor + index * size, size, group))
    return tiles
