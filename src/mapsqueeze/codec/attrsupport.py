"""The attribute field's support (voxels occupied by a tile's default decoded points), checked and repaired.

Encoder and decoder compute the support from decoded points that another device, CPU or BLAS build can round
differently in the last bits (~1e-5 m), which may move a point lying on a voxel face into the neighbouring voxel
and change the occupied set. The stream therefore stores the support's voxel count and a CRC32 of its Morton
codes; on a mismatch the decoder moves back across their face, one or two at a time, the decoded points within
REPAIR_TOLERANCE_M of a face whose move changes the occupied set, nearest to a face first, until count and CRC
match, and fails cleanly otherwise.
"""

from __future__ import annotations

import itertools
import zlib

import numpy as np

from mapsqueeze.codec.attrfield import support_voxels
from mapsqueeze.codec.entropy import ByteReader, ByteWriter

REPAIR_TOLERANCE_M = 1e-3
"""Decoded points this close to a voxel face (metres) may be moved across it to match the encoder's support."""
MAX_REPAIR_CANDIDATES = 16
"""Points tried (nearest to a face first); every single move and every pair of moves among them."""


def support_crc(codes: np.ndarray) -> int:
    """CRC32 of the support's sorted Morton codes (little-endian int64)."""
    return zlib.crc32(np.ascontiguousarray(codes, dtype="<i8").tobytes())


def write_support_check(writer: ByteWriter, codes: np.ndarray) -> None:
    writer.varint(len(codes))
    writer.pack("I", support_crc(codes))


def read_support_check(reader: ByteReader) -> tuple[int, int]:
    """The support's voxel count and CRC32 that start an attribute stream."""
    n_voxels = reader.varint(limit=2**40)
    (crc,) = reader.unpack("I")
    return n_voxels, crc


def support_matches(codes: np.ndarray, n_voxels: int, crc: int) -> bool:
    return len(codes) == n_voxels and support_crc(codes) == crc


def repaired_support(support: np.ndarray, n_voxels: int, crc: int, tile_size: np.ndarray, voxel_m: float
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """The support's codes and each point's voxel (`support_voxels`) after the first allowed move of points on voxel
    faces that gives the count and CRC the stream states; None when none does."""
    points = np.asarray(support, dtype=np.float64)
    codes, voxel = support_voxels(points, tile_size, voxel_m)
    if abs(len(codes) - n_voxels) > 2:  # each of at most two moves changes the count by at most one
        return None
    for moved in _candidate_moves(points, codes, voxel.ravel(), tile_size, voxel_m):
        codes, voxel = support_voxels(moved, tile_size, voxel_m)
        if support_matches(codes, n_voxels, crc):
            return codes, voxel
    return None


def _candidate_moves(points: np.ndarray, codes: np.ndarray, voxel: np.ndarray, tile_size: np.ndarray,
                     voxel_m: float):
    """Copies of `points` with one or two near-face points moved just across their nearest face, among the points
    whose move changes the occupied set (it empties their voxel or enters an empty one), nearest to a face first."""
    scaled = points / voxel_m
    frac = scaled - np.floor(scaled)
    to_face = np.minimum(frac, 1 - frac)  # (N, 3) distance to the nearer face per axis, voxel edges
    axis = to_face.argmin(axis=1)
    distance = to_face[np.arange(len(points)), axis]
    near = np.nonzero(distance * voxel_m < REPAIR_TOLERANCE_M)[0]
    step = 0.5 * REPAIR_TOLERANCE_M / voxel_m
    faces = np.round(scaled[near, axis[near]])
    targets = points[near].copy()
    targets[np.arange(len(near)), axis[near]] = np.where(scaled[near, axis[near]] >= faces, faces - step,
                                                         faces + step) * voxel_m
    if not len(near):
        return
    entered, position = support_voxels(targets, tile_size, voxel_m)
    target_codes = entered[position.ravel()]
    critical = (np.bincount(voxel)[voxel[near]] == 1) | ~np.isin(target_codes, codes)
    chosen = np.nonzero(critical)[0]
    chosen = chosen[np.argsort(distance[near[chosen]], kind="stable")][:MAX_REPAIR_CANDIDATES]
    moves = {int(near[i]): targets[i] for i in chosen}
    for size in (1, 2):
        for chosen in itertools.combinations(moves, size):
            moved = points.copy()
            for index in chosen:
                moved[index] = moves[index]
            yield moved
