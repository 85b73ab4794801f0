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
from mapsqueeze.geometry.morton import MAX_BITS

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
    from mapsqueeze.baselines.octree import encode_occupancy  # imported here: the CLI starts without the baselines

    leaf_m = float(np.float32(leaf_m))
    depth = octree_depth(tile_size, leaf_m)
    cells = np.clip(np.floor(np.asarray(points_local, dtype=np.float64) / leaf_m), 0, (1 << depth) - 1)
    leaf_count, occupancy = encode_occupancy(cells.astype(np.int64), depth)
    writer = ByteWriter()
    writer.pack("fB", leaf_m, depth)
    writer.varint(leaf_count)
    writer.raw(occupancy)
    return writer.getvalue()


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
    return ((cells + 0.5) * leaf_m).astype(np.float32)


def own_leaf_distances(points_local: np.ndarray, tile_size: np.ndarray, leaf_m: float,
                       extent_m: np.ndarray) -> np.ndarray:
    """(N,) float64 distance (metres) from each point (relative to the tile frame) to the nearest leaf centre of
    its octree at leaf_m as `tilepoints.octree_points` places them (inside [0, extent_m]), where that is the centre
    of the point's own leaf (always occupied); NaN where it may not be (`geometry.cells.own_cell_distances`)."""
    from mapsqueeze.geometry.cells import own_cell_distances  # imported here: the CLI starts without numba

    leaf = float(np.float32(leaf_m))
    return own_cell_distances(points_local, leaf, (1 << octree_depth(tile_size, leaf)) - 1,
                              np.asarray(extent_m).astype(np.float32), LEAF_MARGIN_M)


def octree_leaf_m(payload: bytes, what: str) -> float:
    """The leaf edge (metres) an octree payload states."""
    return float(ByteReader(payload, what).unpack("f")[0])
