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
from mapsqueeze.geometry.bounds import bounding_box
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
    return encode_octree_tiles(points_local, tile_size, (leaf_m,))[0][1]


def encode_octree_tiles(points_local: np.ndarray, tile_size: np.ndarray, leaves_m: tuple[float, ...],
                        max_bytes: int | None = None) -> list[tuple[float, bytes, np.ndarray]]:
    """(leaf edge, `encode_octree_tile` payload, the leaf centres (K, 3) float32 metres it decodes to, in Morton
    order) at each leaf edge of leaves_m, in their order.

    A leaf whose float32 edge is the finest's times 2^s and whose octree is s levels shallower (OCTREE_LEAVES_M in
    tiles wider than 1.6 m) is nested in the finest's octree: its cells are the finest's shifted right by s bits
    (floor(p / (2^s l)) = floor(p / l) >> s, both in float arithmetic, as scaling by 2^s is exact), its Morton codes
    the finest's shifted right by 3 s bits and its occupancy levels the finest's first ones, so one sort of the
    finest's codes serves every nested leaf. max_bytes given: the leaves coarsest first, leaving out those finer
    than the first whose payload exceeds max_bytes + OCTREE_GROWTH_SLACK_BYTES, as theirs would exceed max_bytes too
    (a finer octree codes the coarser one's levels under the same models, plus more levels); the nested leaves whose
    cell box is small enough for a bitmap take their distinct cells from one (`_distinct_cells`, one pass over the
    points for all of them), and the sort is made only if a finer leaf is coded."""
    from mapsqueeze.baselines.octree import arithmetic_encode, occupancy_levels  # the CLI starts without them

    if not leaves_m:
        return []
    points = np.asarray(points_local, dtype=np.float64)
    leaves = [float(np.float32(leaf)) for leaf in leaves_m]
    finest = min(leaves)
    finest_depth = octree_depth(tile_size, finest)
    finest_cells = _cells(points, finest, finest_depth)
    shifts = {leaf: finest_depth - octree_depth(tile_size, leaf) for leaf in leaves}
    nested = {leaf: shift for leaf, shift in shifts.items() if leaf == finest * 2.0**shift}
    shared: list = []  # the finest's sorted distinct codes and occupancy levels, once a leaf needs them
    distinct: dict[int, np.ndarray] = {}  # distinct cells of the bitmap leaves, by shift
    bitmap_shifts = []
    if max_bytes is not None and len(points):  # the finest cells' upper corner (floor and the clip are monotonic)
        top = _cells(bounding_box(points)[1][None, :], finest, finest_depth)[0]
        bitmap_shifts = [shift for shift in nested.values()
                         if np.prod((top >> shift) + 1) <= BITMAP_CELLS_PER_POINT * len(points)]

    def codes_and_levels(leaf: float, depth: int) -> tuple[np.ndarray, list[np.ndarray]]:
        shift = nested.get(leaf)
        if shift is None:
            codes = sorted_unique(morton_codes(_cells(points, leaf, depth), depth))
            return codes, occupancy_levels(codes, depth)
        if shift in bitmap_shifts:
            if not distinct:
                first = min(bitmap_shifts)
                distinct[first] = _distinct_cells(finest_cells >> first, (top >> first) + 1)
            base = max(known for known in distinct if known <= shift)
            if shift not in distinct:
                distinct[shift] = _distinct_cells(distinct[base] >> (shift - base))
            codes = np.sort(morton_codes(distinct[shift], depth))
            return codes, occupancy_levels(codes, depth)
        if not shared:
            finest_codes = sorted_unique(morton_codes(finest_cells, finest_depth))
            shared.extend([finest_codes, occupancy_levels(finest_codes, finest_depth)])
        codes = shared[0] >> (3 * shift)
        return codes[np.concatenate([[True], codes[1:] != codes[:-1]])], shared[1][:depth]

    coded = {}
    for leaf in sorted(set(leaves), reverse=True):
        depth = octree_depth(tile_size, leaf)
        codes, levels = codes_and_levels(leaf, depth)
        writer = ByteWriter()
        writer.pack("fB", leaf, depth)
        writer.varint(len(codes))
        writer.raw(arithmetic_encode(levels))
        coded[leaf] = (writer.getvalue(), codes)
        if max_bytes is not None and len(coded[leaf][0]) > max_bytes + OCTREE_GROWTH_SLACK_BYTES:
            break
    return [(leaf, coded[leaf][0], _leaf_centres(morton_cells(coded[leaf][1]), leaf))
            for leaf in leaves if leaf in coded]


OCTREE_GROWTH_SLACK_BYTES = 16
"""Bytes by which a finer octree's payload may fall short of a coarser one's (`encode_octree_tiles`): its ANS
stream holds the coarser one's levels under the same per-level models plus more levels, so it is at least that
stream less the coder's final 32-bit words; the leaf count's varint is at least as long."""

BITMAP_CELLS_PER_POINT = 16
"""`_distinct_cells` finds the occupied cells on a dense bitmap of their box when it holds at most this many cells
per point (one pass), else by sorting the cells' packed keys."""


def _cells(points: np.ndarray, leaf_m: float, depth: int) -> np.ndarray:
    """(N, 3) int64 leaf cells of the points: floor(p / leaf_m) clipped into the depth's cube."""
    scaled = np.divide(points, leaf_m)
    np.floor(scaled, out=scaled)
    np.clip(scaled, 0, (1 << depth) - 1, out=scaled)
    return scaled.astype(np.int64)


def _distinct_cells(cells: np.ndarray, dims: np.ndarray | None = None) -> np.ndarray:
    """The distinct rows of (N, 3) non-negative int64 cells, (K, 3), in the order of their packed keys; dims: their
    largest values plus one per axis, when known."""
    if not len(cells):
        return cells
    dims = cells.max(axis=0) + 1 if dims is None else dims
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    if int(np.prod(dims)) <= BITMAP_CELLS_PER_POINT * len(cells):
        occupied = np.zeros(int(np.prod(dims)), dtype=bool)
        occupied[keys] = True
        keys = np.flatnonzero(occupied)
    else:
        keys = sorted_unique(keys)
    return np.stack(np.unravel_index(keys, tuple(int(d) for d in dims)), axis=1)


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
