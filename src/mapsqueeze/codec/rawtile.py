"""Near-exact coding of sparse tiles: points quantised to a fixed step relative to the tile frame, entropy coded.

Layout of a raw payload: varint point count, the tile's gap histogram, then one ANS stream holding the gaps
between the sorted Morton codes of the quantised points (bit length entropy coded, lower bits plain).
Decoded points come out in Morton order, each within step / 2 per axis of its input (duplicates kept).
"""

from __future__ import annotations

import numpy as np

from mapsqueeze.codec.entropy import (
    ByteReader,
    ByteWriter,
    Histogram,
    SymbolReader,
    SymbolWriter,
    bit_length,
    decode_gaps,
    encode_gaps,
    fit_gap_buckets,
)
from mapsqueeze.geometry.morton import MAX_BITS, morton_cells, morton_codes

RAW_STEP_M = 0.01
"""Quantisation step of raw tiles (metres): at most 5 mm error per axis."""


def axis_bits(tile_size: np.ndarray, step_m: float) -> int:
    """Bits per axis of the quantised coordinates of a tile (the same for all three axes)."""
    bits = int(bit_length(np.ceil(np.asarray(tile_size) / step_m).astype(np.int64)).max())
    if bits > MAX_BITS:
        raise ValueError(f"raw coding of a {tile_size} m tile at {step_m} m needs {bits} bits per axis")
    return bits


def encode_raw_tile(points_local: np.ndarray, tile_size: np.ndarray, step_m: float = RAW_STEP_M) -> bytes:
    """Points (N, 3) metres relative to the tile frame, in [0, tile_size) -> raw payload."""
    bits = axis_bits(tile_size, step_m)
    cells = np.clip(np.round(np.asarray(points_local, dtype=np.float64) / step_m), 0, 2**bits - 1)
    codes = np.sort(morton_codes(cells.astype(np.int64), bits))
    gaps = np.diff(codes, prepend=0)
    buckets = fit_gap_buckets(gaps)
    writer = ByteWriter()
    writer.varint(len(codes))
    buckets.write(writer)
    symbols = SymbolWriter()
    encode_gaps(symbols, gaps, buckets)
    writer.raw(symbols.getvalue())
    return writer.getvalue()


def decode_raw_tile(payload: bytes, tile_size: np.ndarray, n_points: int, what: str,
                    step_m: float = RAW_STEP_M) -> np.ndarray:
    """Raw payload -> points (N, 3) float32 metres relative to the tile frame; N must equal the table's `n_points`
    (checked before anything is allocated)."""
    bits = axis_bits(tile_size, step_m)
    reader = ByteReader(payload, what)
    count = reader.varint(limit=2**63)
    if count != n_points or count == 0:
        raise reader.fail(f"raw payload holds {count} points, the tile table says {n_points}")
    buckets = Histogram.read(reader)
    symbols = SymbolReader(reader.raw(reader.remaining), what)
    codes = np.cumsum(decode_gaps(symbols, count, buckets))
    symbols.finish()
    if codes.min() < 0 or codes.max() >= 2 ** (3 * bits):
        raise reader.fail("raw point outside the tile")
    return (morton_cells(codes) * step_m).astype(np.float32)
