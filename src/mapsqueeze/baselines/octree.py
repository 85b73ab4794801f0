"""The paper's plain binary octree: one occupancy byte per internal node, breadth first; leaves decode as cells'
centres. "octree-ac" entropy-codes the same bytes (level by level, each level's model learned from the previous).

Layout (little-endian): magic b"MSOT", version u8, coding u8 (0 raw, 1 arithmetic-coded), depth u8, leaf count
u32, CRC-32 of the payload u32, origin 3 x f64 (metres, the root cube's minimum corner), root cube edge f64
(metres), then the payload. Raw payload: the occupancy bytes of levels 0..depth-1, each level's nodes in Morton
order (child bit i = x + 2y + 4z, Morton code bit 3b + axis); the bytes of level L+1 number the set bits of
level L. Arithmetic payload: constriction ANS words (u32) of the same bytes.
"""

import math
import struct
import zlib
from typing import ClassVar

import constriction
import numpy as np

from mapsqueeze.baselines.base import BaselineCodec, Setting, setting_number
from mapsqueeze.errors import BaselineError, ContainerError
from mapsqueeze.geometry.morton import MAX_BITS, morton_cells, morton_codes, sorted_unique
from mapsqueeze.geometry.validation import MAX_ABS_COORDINATE_M, validate_points
from mapsqueeze.geometry.voxel import voxel_indices

_MAGIC = b"MSOT"
_VERSION = 1
_HEADER = struct.Struct("<4sBBBII3dd")
_RAW, _ARITHMETIC = 0, 1
MAX_DEPTH = MAX_BITS
"""Morton codes hold 3 x 21 bits in an int64: at most 2,097,152 leaves per axis."""
MAX_LEAVES = 1 << 27
"""Largest leaf count a decoder accepts (about 1 GiB of Morton codes), so a forged header cannot exhaust memory."""

LEAF_SIZES_M = (0.1, 0.2, 0.4, 0.8, 1.6)
"""Leaf cell edges (metres) of the benchmark sweep."""


def occupancy_levels(leaf_codes: np.ndarray, depth: int) -> list[np.ndarray]:
    """Occupancy bytes (uint8) of each level, root first, nodes in Morton order; `leaf_codes` sorted unique."""
    levels = []
    codes = leaf_codes
    for _ in range(depth):
        shifted = codes >> 3  # sorted: each parent's children are adjacent
        first = np.flatnonzero(np.concatenate([[True], shifted[1:] != shifted[:-1]]))
        parents = shifted[first]
        levels.append(np.bitwise_or.reduceat(np.left_shift(1, codes & 7), first).astype(np.uint8))
        codes = parents
    return levels[::-1]


def _children(codes: np.ndarray, occupancy: np.ndarray) -> np.ndarray:
    """Codes of the occupied children, in Morton order, of nodes `codes` with occupancy bytes `occupancy`."""
    node, child = np.nonzero(np.unpackbits(occupancy[:, None], axis=1, bitorder="little"))
    return (codes[node] << 3) | child


def _level_model(previous_level: np.ndarray | None):
    """Categorical model of (byte - 1) in 0..254: previous level's byte counts + 0.5 (uniform for the root)."""
    counts = np.full(255, 0.5)
    if previous_level is not None:
        counts += np.bincount(previous_level.astype(np.int64) - 1, minlength=255)
    return constriction.stream.model.Categorical(counts / counts.sum(), perfect=False)


def arithmetic_encode(levels: list[np.ndarray]) -> bytes:
    """The arithmetic-coded occupancy bytes of levels 0..len(levels)-1 (`occupancy_levels`, root first)."""
    coder = constriction.stream.stack.AnsCoder()
    for index in reversed(range(len(levels))):  # ANS is a stack: encode last level first
        model = _level_model(levels[index - 1] if index else None)
        coder.encode_reverse(levels[index].astype(np.int32) - 1, model)
    return coder.get_compressed().astype("<u4").tobytes()


def decode_occupancy(payload: bytes, depth: int, leaf_count: int) -> np.ndarray:
    """Inverse of `arithmetic_encode` of a tree's `occupancy_levels`: (leaf_count, 3) int64 leaf cells in Morton
    order; ContainerError when corrupt."""
    codes = np.zeros(1, dtype=np.int64)
    for occupancy in _arithmetic_decode(payload, depth, leaf_count):
        codes = _children(codes, occupancy)
    if len(codes) != leaf_count:
        raise ContainerError(f"octree: {len(codes)} leaves decoded, {leaf_count} expected")
    return morton_cells(codes)


class OctreeCodec(BaselineCodec):
    """Plain occupancy octree over a cube fitted to the points; setting {"leaf_m": leaf cell edge in metres}."""

    name: ClassVar[str] = "octree"
    entropy_coded: ClassVar[bool] = False

    def settings(self) -> list[Setting]:
        return [{"leaf_m": leaf} for leaf in LEAF_SIZES_M]

    def encode(self, points: np.ndarray, setting: Setting) -> bytes:
        points = validate_points(points)
        leaf = setting_number(setting, "leaf_m", self.name, 1e-6, MAX_ABS_COORDINATE_M)
        origin = points.min(axis=0)
        cells_per_axis = math.floor(float(np.ptp(points, axis=0).max()) / leaf) + 1
        depth = max(1, (cells_per_axis - 1).bit_length())
        if depth > MAX_DEPTH:
            raise BaselineError(
                f"{self.name}: leaf {leaf} m is too small for a {cells_per_axis * leaf:.1f} m wide cloud "
                f"(more than {MAX_DEPTH} octree levels)"
            )
        cells = np.clip(voxel_indices(points, leaf, origin), 0, (1 << depth) - 1)
        leaf_codes = sorted_unique(morton_codes(cells, depth))
        levels = occupancy_levels(leaf_codes, depth)
        if self.entropy_coded:
            payload, coding = arithmetic_encode(levels), _ARITHMETIC
        else:
            payload, coding = np.concatenate(levels).tobytes(), _RAW
        header = _HEADER.pack(
            _MAGIC, _VERSION, coding, depth, len(leaf_codes), zlib.crc32(payload), *origin, leaf * (1 << depth)
        )
        return header + payload

    def decode(self, data: bytes) -> np.ndarray:
        """Leaf cell centres (metres); raises ContainerError on truncated, corrupt or inconsistent data."""
        depth, leaf_count, origin, root_size, coding, payload = _read_header(bytes(data))
        if coding == _RAW:
            levels = _split_raw_levels(payload, depth, leaf_count)
        else:
            levels = _arithmetic_decode(payload, depth, leaf_count)
        codes = np.zeros(1, dtype=np.int64)
        for occupancy in levels:
            codes = _children(codes, occupancy)
        if len(codes) != leaf_count:
            raise ContainerError(f"octree: {len(codes)} leaves decoded, header says {leaf_count}")
        leaf = root_size / (1 << depth)
        return origin + (morton_cells(codes) + 0.5) * leaf


class OctreeAcCodec(OctreeCodec):
    """The plain octree with arithmetic-coded (constriction ANS) occupancy bytes."""

    name: ClassVar[str] = "octree-ac"
    entropy_coded: ClassVar[bool] = True


def _read_header(data: bytes) -> tuple[int, int, np.ndarray, float, int, bytes]:
    if len(data) < _HEADER.size:
        raise ContainerError(f"octree: {len(data)} bytes is shorter than the {_HEADER.size}-byte header")
    magic, version, coding, depth, leaf_count, crc, *corner, root_size = _HEADER.unpack_from(data)
    if magic != _MAGIC:
        raise ContainerError(f"octree: bad magic {magic!r} (expected {_MAGIC!r})")
    if version != _VERSION:
        raise ContainerError(f"octree: unsupported version {version} (this build reads {_VERSION})")
    if coding not in (_RAW, _ARITHMETIC):
        raise ContainerError(f"octree: unknown payload coding {coding}")
    if not 1 <= depth <= MAX_DEPTH:
        raise ContainerError(f"octree: depth {depth} outside 1..{MAX_DEPTH}")
    origin = np.array(corner)
    if not (np.isfinite(origin).all() and np.abs(origin).max() < MAX_ABS_COORDINATE_M):
        raise ContainerError(f"octree: absurd origin {corner}")
    if not (math.isfinite(root_size) and 0 < root_size < MAX_ABS_COORDINATE_M):
        raise ContainerError(f"octree: absurd root cube size {root_size!r} m")
    payload = data[_HEADER.size :]
    if zlib.crc32(payload) != crc:
        raise ContainerError("octree: payload CRC mismatch (corrupt or truncated data)")
    if not 0 < leaf_count <= MAX_LEAVES:
        raise ContainerError(f"octree: leaf count {leaf_count} outside 1..{MAX_LEAVES}")
    return depth, leaf_count, origin, root_size, coding, payload


def _node_count(occupancy: np.ndarray) -> int:
    """Children announced by a level's occupancy bytes; raises on a zero byte (an internal node has children)."""
    if (occupancy == 0).any():
        raise ContainerError("octree: an internal node has no occupied child")
    return int(np.unpackbits(occupancy).sum())


def _split_raw_levels(payload: bytes, depth: int, leaf_count: int) -> list[np.ndarray]:
    occupancy = np.frombuffer(payload, dtype=np.uint8)
    levels, start, nodes = [], 0, 1
    for _ in range(depth):
        if start + nodes > len(occupancy):
            raise ContainerError(f"octree: payload truncated ({len(occupancy)} occupancy bytes)")
        level = occupancy[start : start + nodes]
        levels.append(level)
        start, nodes = start + nodes, _node_count(level)
        if nodes > leaf_count:
            raise ContainerError(f"octree: a level has {nodes} nodes, more than the {leaf_count} leaves")
    if start != len(occupancy):
        raise ContainerError(f"octree: {len(occupancy) - start} stray bytes after the last level")
    return levels


def _arithmetic_decode(payload: bytes, depth: int, leaf_count: int) -> list[np.ndarray]:
    if len(payload) % 4:
        raise ContainerError("octree: arithmetic-coded payload is not a whole number of 32-bit words")
    coder = constriction.stream.stack.AnsCoder(np.frombuffer(payload, dtype="<u4").astype(np.uint32))
    levels, nodes = [], 1
    for index in range(depth):
        try:
            level = (coder.decode(_level_model(levels[index - 1] if index else None), nodes) + 1).astype(np.uint8)
        except (ValueError, RuntimeError) as exc:
            raise ContainerError(f"octree: corrupt arithmetic-coded payload ({exc})") from None
        levels.append(level)
        nodes = _node_count(level)
        if nodes > leaf_count:
            raise ContainerError(f"octree: a level has {nodes} nodes, more than the {leaf_count} leaves")
    if not coder.is_empty():
        raise ContainerError("octree: stray data after the last level")
    return levels
