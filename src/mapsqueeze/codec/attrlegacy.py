"""Attribute streams of container versions 1 and 2, read only: the tile's input points binned into voxels, the
occupied voxels' Morton codes gap coded, and per attribute one value per voxel coded as differences along the
Morton order (docs/format.md, "Attributes", older versions)."""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from mapsqueeze.codec.attributes import CATEGORICAL, AttributeSchema, read_palette, restore
from mapsqueeze.codec.entropy import ByteReader, Histogram, SymbolReader, decode_gaps
from mapsqueeze.codec.rawtile import axis_bits
from mapsqueeze.geometry.morton import morton_cells


def decode_legacy_tile_attributes(stream: bytes, points_local: np.ndarray, schema: AttributeSchema,
                                  tile_size: np.ndarray, what: str) -> dict[str, np.ndarray]:
    """Attributes of decoded points (metres, tile frame): each point takes its nearest coded voxel's values."""
    bits = axis_bits(tile_size, schema.voxel_m)
    reader = ByteReader(stream, what)
    n_voxels = reader.varint(limit=2 ** min(3 * bits, 40))
    if n_voxels == 0:
        raise reader.fail("attribute stream without voxels")
    buckets = Histogram.read(reader)
    tables = []
    for spec in schema.specs:
        palette = read_palette(reader, n_voxels, spec.name) if spec.kind == CATEGORICAL else None
        tables.append((palette, Histogram.read(reader)))
    symbols = SymbolReader(reader.raw(reader.remaining), what)
    codes = np.cumsum(decode_gaps(symbols, n_voxels, buckets))
    if codes.min() < 0 or codes.max() >= 2 ** (3 * bits) or (np.diff(codes) <= 0).any():
        raise reader.fail("attribute voxels out of order or outside the tile")
    per_voxel = []
    for spec, (palette, histogram) in zip(schema.specs, tables):
        values = np.cumsum(symbols.histogram(histogram, n_voxels))
        if palette is not None:
            if values.min() < 0 or values.max() >= len(palette):
                raise reader.fail(f"palette index of {spec.name!r} out of range")
            values = palette[values]
        per_voxel.append(values)
    symbols.finish()
    centres = (morton_cells(codes) + 0.5) * schema.voxel_m
    _, nearest = KDTree(centres).query(np.asarray(points_local, dtype=np.float64), k=1)
    nearest = nearest.astype(np.int64)
    return {spec.name: restore(spec, values[nearest]) for spec, values in zip(schema.specs, per_voxel)}
