"""Classical fallback for a tile: the occupancy octree of `baselines.octree` over the tile frame, leaves at their
cells' centres.

Layout of an octree payload: f32 leaf edge (metres), u8 depth, varint leaf count, then the arithmetic-coded
occupancy bytes of every level (`baselines.octree.encode_occupancy`). The root cube's lower corner is the tile frame.
"""

from __future__ import annotations

import math

import numpy as np

from mapsqueeze.codec.entropy import ByteReader, ByteWriter
from mapsqueeze.errors import ContainerError
from mapsqueeze.geometry.morton import MAX_BITS, morton_cells, morton_codes, sorted_unique

OCTREE_LEAVES_M = (0.1, 0.2, 0.4, 0.8, 1.6)
"""Leaf edges (metres) the compressor tries for a tile's classical fallback (the benchmark's octree sweep)."""
MIN_LEAF_M = 0.001
"""Smallest leaf edge a payload may state (metres)."""
LEAF_MARGIN_M = 2e-4
"""`own_leaf_distances` trusts a point's own leaf centre as its nearest only this far inside the leaf (metres):
float32 centres are off their grid by under 3 microns in a 40 m tile, which shifts distances far less."""


def octree_depth(tile_size: np.ndarray, leaf_m: float) -> int:
    """Levels of a root cube that holds a whole tile with leaves of leaf_m metres."""
    cells = math.ceil(float(np.max(tile_size)) / leaf_m)
    depth = max(1, (cells - 1).bit_length())
    if depth > MAX_BITS:
        raise ValueError(f"a {leaf_m} m octree leaf is too small for a {np.max(tile_size)} m tile")
    return depth


def encode_octree_tile(points_local: np.ndarray, tile_size: np.ndarray, leaf_m: float) -> bytes:
    """Points (N, 3) metres relative to the tile frame, in [0, tile_size] -> octree payload."""
    return encode_octree_tiles(points_local, tile_size, (leaf_m,))[0][0]


def encode_octree_tiles(points_local: np.ndarray, tile_size: np.ndarray,
                        leaves_m: tuple[float, ...]) -> list[tuple[bytes, np.ndarray]]:
    """`encode_octree_tile` at each leaf edge of leaves_m, with the leaf centres (K, 3) float32 metres its payload
    decodes to (`decode_octree_tile`'s, in Morton order). One sort serves every leaf whose float32 edge is the
    finest's times 2^s and whose octree is s levels shallower (OCTREE_LEAVES_M in tiles wider than 1.6 m): its
    leaves are the finest's Morton codes shifted right by 3 s bits (floor(p / (2^s l)) = floor(p / l) >> s, both in
    float arithmetic, as scaling by 2^s is exact) and its occupancy levels the finest's first ones."""
    from mapsqueeze.baselines.octree import arithmetic_encode, occupancy_levels  # the CLI starts without them

    if not leaves_m:
        return []
    points = np.asarray(points_local, dtype=np.float64)
    leaves = [float(np.float32(leaf)) for leaf in leaves_m]
    finest = min(leaves)
    finest_depth = octree_depth(tile_size, finest)
    finest_codes = _leaf_codes(points, finest, finest_depth)
    finest_levels = occupancy_levels(finest_codes, finest_depth)
    coded = []
    for leaf in leaves:
        depth = octree_depth(tile_size, leaf)
        shift = finest_depth - depth
        if leaf == finest * 2.0**shift:
            codes = finest_codes >> (3 * shift)
            codes = codes[np.concatenate([[True], codes[1:] != codes[:-1]])]
            levels = finest_levels[:depth]
        else:
            codes = _leaf_codes(points, leaf, depth)
            levels = occupancy_levels(codes, depth)
        writer = ByteWriter()
        writer.pack("fB", leaf, depth)
        writer.varint(len(codes))
        writer.raw(arithmetic_encode(levels))
        coded.append((writer.getvalue(), _leaf_centres(morton_cells(codes), leaf)))
    return coded


def _leaf_codes(points: np.ndarray, leaf_m: float, depth: int) -> np.ndarray:
    """Sorted distinct Morton codes of the points' leaves (cells of edge leaf_m clipped into the depth's cube)."""
    cells = np.clip(np.floor(points / leaf_m), 0, (1 << depth) - 1).astype(np.int64)
    return sorted_unique(morton_codes(cells, depth))


def _leaf_centres(cells: np.ndarray, leaf_m: float) -> np.ndarray:
    return ((cells + 0.5) * leaf_m).astype(np.float32)


def decode_octree_tile(payload: bytes, tile_size: np.ndarray, max_points: int, what: str) -> np.ndarray:
    """Octree payload -> leaf centres (K, 3) float32 metres relative to the tile frame; K <= max_points."""
    reader = ByteReader(payload, what)
    leaf_m, depth = reader.unpack("fB")
    if not (math.isfinite(leaf_m) and leaf_m >= MIN_LEAF_M):
        raise reader.fail(f"octree leaf edge {leaf_m} m")
    try:
        expected_depth = octree_depth(tile_size, leaf_m)
    except ValueError as exc:
        raise reader.fail(str(exc)) from None
    if depth != expected_depth:
        raise reader.fail(f"octree depth {depth} does not fit a {leaf_m:g} m leaf in the tile")
    leaf_count = reader.varint(limit=max_points + 1)
    if leaf_count < 1:
        raise reader.fail("octree tile without leaves")
    from mapsqueeze.baselines.octree import decode_occupancy

    try:
        cells = decode_occupancy(reader.raw(reader.remaining), depth, leaf_count)
    except ContainerError as exc:
        raise reader.fail(str(exc)) from None
    return _leaf_centres(cells, leaf_m)


def own_leaf_distances(points_local: np.ndarray, tile_size: np.ndarray, leaf_m: float,
                       extent_m: np.ndarray, compiled: bool = True) -> np.ndarray:
    """(N,) float64 distance (metres) from each point (relative to the tile frame) to the nearest leaf centre of
    its octree at leaf_m as `tilepoints.octree_points` places them (inside [0, extent_m]), where that is the centre
    of the point's own leaf (always occupied); NaN where it may not be (`geometry.cells.own_cell_distances`;
    compiled=False: `geometry.cellsnumpy`'s, the same values without numba)."""
    if compiled:
        from mapsqueeze.geometry.cells import own_cell_distances  # imported here: the CLI starts without numba
    else:
        from mapsqueeze.geometry.cellsnumpy import own_cell_distances

    leaf = float(np.float32(leaf_m))
    return own_cell_distances(points_local, leaf, (1 << octree_depth(tile_size, leaf)) - 1,
                              np.asarray(extent_m).astype(np.float32), LEAF_MARGIN_M)


def octree_leaf_m(payload: bytes, what: str) -> float:
    """The leaf edge (metres) an octree payload states."""
    return float(ByteReader(payload, what).unpack("f")[0])
