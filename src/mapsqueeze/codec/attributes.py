"""Per-point attributes (intensity, colour, labels, ...) coded per tile as a voxel field on the decoded geometry.

The support of a tile's field is the set of voxels (edge `voxel_m`, tile frame) occupied by the tile's default
decoded points (`decompress.decode_payload` at the native count, which encoder and decoder both run), so no voxel
positions are coded. Each support voxel carries one value per attribute, taken from the input points nearest to its
decoded points: continuous attributes (floats, and integer fields such as intensity or colour, `CONTINUOUS_NAMES`)
their median (the value that minimises the mean absolute error), quantised to `step` above the map's minimum;
categorical attributes (other integers: labels, classification, ring, return number) their most frequent value, as
an index into the tile's sorted palette. Values are coded coarse to fine with predictions from already-decoded
voxels (`codec.attrfield`). A decoded point, at any density, takes the values of its nearest support voxel.
An attribute that holds one value over the whole map (bit for bit: LAS fields such as user_data or point_source_id
often do) is stored in the schema as that value (container version 8) and has no part in the tiles' streams.
Layout: docs/format.md, "Attributes"; streams of container versions 1 and 2 are read by `codec.attrlegacy`.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass

import numpy as np
from pykdtree.kdtree import KDTree

from mapsqueeze.codec.attrfield import (
    LevelsOfDetail,
    decode_categories,
    decode_integers,
    encode_categories,
    encode_integers,
    read_category_tables,
    read_integer_tables,
    support_voxels,
)
from mapsqueeze.codec.attrsupport import (
    read_support_check,
    repaired_support,
    support_crc,
    support_matches,
    write_support_check,
)
from mapsqueeze.codec.entropy import ByteReader, ByteWriter, SymbolReader, SymbolWriter
from mapsqueeze.errors import ContainerError, InvalidPointCloudError
from mapsqueeze.geometry.morton import morton_cells

DEFAULT_VOXEL_M = 1.0
"""Edge of the attribute voxels (metres): the spatial resolution of decoded attributes. With DEFAULT_RELATIVE_STEP
the cheapest setting measured that keeps the intensity error at the decoded points within 0.45x the constant
guess's on the real KITTI scan, KITTI map and nuScenes sweep, and proxy labels above 97 % (BENCHMARKS.md)."""
DEFAULT_RELATIVE_STEP = 1 / 32
"""Quantisation step of continuous attributes as a fraction of the attribute's range over the map."""
MIN_RELATIVE_STEP = 1e-6
MIN_VOXEL_M = 0.01
CONTINUOUS_NAMES = frozenset({"intensity", "reflectance", "red", "green", "blue", "nir", "gps_time", "time",
                              "timestamp", "scan_angle", "range",
                              "reflectivity", "signal", "near_ir", "ambient", "t", "offset_time"})
"""Integer attributes with these names (in any case) are continuous (median, quantised); other integers are
categorical. The second line: the integer measurements and per-point times of Ouster and Livox driver PCDs."""
CONTINUOUS, CATEGORICAL, CONSTANT = 0, 1, 2
CONSTANT_VERSION = 8
"""First container version whose schema may hold constant attributes (kind CONSTANT); written only by files that do."""
_MAX_ATTRIBUTES = 255
_MAX_METADATA_BYTES = 1 << 24
MAX_PALETTE = 1 << 20


@dataclass(frozen=True)
class AttributeSpec:
    """One coded attribute: name, numpy dtype (restored on decoding), kind, for continuous ones the quantisation
    origin `low` and `step` (value = low + q * step), for constant ones the `value` every point has (`dtype`'s
    bytes)."""

    name: str
    dtype: np.dtype
    kind: int
    low: float = 0.0
    step: float = 1.0
    value: bytes = b""

    def constant(self, count: int) -> np.ndarray:
        """`count` copies of a constant attribute's value."""
        return np.full(count, np.frombuffer(self.value, dtype=self.dtype)[0], dtype=self.dtype)


@dataclass(frozen=True)
class AttributeSchema:
    """The container's attribute section header: voxel edge, attributes, file metadata (JSON)."""

    voxel_m: float
    specs: tuple[AttributeSpec, ...]
    metadata: dict

    @property
    def coded(self) -> tuple[AttributeSpec, ...]:
        """The attributes the tiles' streams code (all but the constant ones), in schema order."""
        return tuple(spec for spec in self.specs if spec.kind != CONSTANT)

    @property
    def version(self) -> int | None:
        """The container version this schema needs beyond the compact layout's (None: any)."""
        return CONSTANT_VERSION if len(self.coded) < len(self.specs) else None

    def serialise(self) -> bytes:
        writer = ByteWriter()
        writer.pack("d", self.voxel_m)
        writer.pack("B", len(self.specs))
        for spec in self.specs:
            name, dtype = spec.name.encode(), spec.dtype.str.encode()
            writer.pack("B", len(name))
            writer.raw(name)
            writer.pack("B", len(dtype))
            writer.raw(dtype)
            if spec.kind == CONSTANT:
                writer.pack("B", spec.kind)
                writer.raw(spec.value)
            else:
                writer.pack("Bdd", spec.kind, spec.low, spec.step)
        metadata = zlib.compress(json.dumps(self.metadata, sort_keys=True).encode(), 9) if self.metadata else b""
        writer.varint(len(metadata))
        writer.raw(metadata)
        return writer.getvalue()

    @classmethod
    def read(cls, reader: ByteReader, constants: bool = False) -> "AttributeSchema":
        """The schema at the reader; constants: constant attributes are allowed (container version 8)."""
        (voxel_m, count) = reader.unpack("dB")
        if not (np.isfinite(voxel_m) and voxel_m >= MIN_VOXEL_M):
            raise reader.fail(f"attribute voxel of {voxel_m} m")
        specs = []
        for _ in range(count):
            try:
                name = reader.raw(reader.unpack("B")[0]).decode()
                dtype = np.dtype(reader.raw(reader.unpack("B")[0]).decode())
            except (UnicodeDecodeError, TypeError, ValueError, SyntaxError):  # numpy parses a comma's parts as Python
                raise reader.fail("bad attribute name or dtype") from None
            (kind,) = reader.unpack("B")
            if dtype.kind not in "iuf" or name in {spec.name for spec in specs} \
                    or kind not in ((CONTINUOUS, CATEGORICAL, CONSTANT) if constants else (CONTINUOUS, CATEGORICAL)):
                raise reader.fail(f"bad attribute {name!r}" + (f" (kind {kind})" if kind == CONSTANT else ""))
            if kind == CONSTANT:
                if dtype.itemsize not in (1, 2, 4, 8):
                    raise reader.fail(f"constant attribute {name!r} of dtype {dtype.str}")
                value = reader.raw(dtype.itemsize)
                if dtype.kind == "f" and not np.isfinite(np.frombuffer(value, dtype=dtype)[0]):
                    raise reader.fail(f"constant attribute {name!r} is not finite")
                specs.append(AttributeSpec(name, dtype, kind, value=value))
                continue
            low, step = reader.unpack("dd")
            if not np.isfinite([low, step]).all() or step <= 0:
                raise reader.fail(f"bad attribute {name!r}")
            specs.append(AttributeSpec(name, dtype, kind, low, step))
        length = reader.varint(limit=_MAX_METADATA_BYTES)
        metadata = {}
        if length:
            try:
                metadata = json.loads(zlib.decompress(reader.raw(length)))
            except (zlib.error, ValueError):
                raise reader.fail("corrupt metadata") from None
            if not isinstance(metadata, dict):
                raise reader.fail("metadata is not a JSON object")
        return cls(voxel_m, tuple(specs), metadata)


def is_continuous(name: str, dtype: np.dtype) -> bool:
    return dtype.kind == "f" or name.lower() in CONTINUOUS_NAMES


def parse_selection(selection: str | list[str] | tuple[str, ...] | None, names: list[str]) -> list[str]:
    """Attribute names to code: "all" (default), "none", or a comma-separated list / sequence of names."""
    if selection is None or selection == "all":
        return list(names)
    if selection == "none":
        return []
    wanted = [part.strip() for part in selection.split(",")] if isinstance(selection, str) else list(selection)
    if not all(wanted):
        raise InvalidPointCloudError(f"attribute list {selection!r} has an empty name (names, comma-separated)")
    unknown = [name for name in wanted if name not in names]
    if unknown:
        raise InvalidPointCloudError(f"no attribute {', '.join(unknown)} in the input (it has: "
                                     f"{', '.join(names) or 'none'})")
    return [name for name in names if name in wanted]


@dataclass(frozen=True)
class ValueRange:
    """An attribute's values over (part of) a map: dtype, minimum, maximum, and the value's bytes when every value
    is the same bit for bit (else None)."""

    dtype: np.dtype
    low: float
    high: float
    constant: bytes | None

    @classmethod
    def of(cls, values: np.ndarray) -> "ValueRange":
        values = np.asarray(values)
        constant = None
        if len(values) and values.dtype.itemsize in (1, 2, 4, 8):
            bits = values.view(f"u{values.dtype.itemsize}")
            if bits.min() == bits.max():
                constant = values[:1].tobytes()
        return cls(values.dtype, float(values.min()), float(values.max()), constant)

    def merge(self, other: "ValueRange") -> "ValueRange":
        """The range of both parts' values."""
        same = self.constant == other.constant and self.dtype == other.dtype
        return ValueRange(other.dtype, min(self.low, other.low), max(self.high, other.high),
                          self.constant if same else None)


def check_resolution(voxel_m: float, relative_step: float) -> None:
    """Raise InvalidPointCloudError unless voxel_m (metres) >= MIN_VOXEL_M and MIN_RELATIVE_STEP <= relative_step
    (a fraction of each attribute's range) <= 1, both finite."""
    if not (np.isfinite(voxel_m) and voxel_m >= MIN_VOXEL_M):
        raise InvalidPointCloudError(f"attribute voxel must be at least {MIN_VOXEL_M} m, got {voxel_m}")
    if not (np.isfinite(relative_step) and MIN_RELATIVE_STEP <= relative_step <= 1):
        raise InvalidPointCloudError(f"attribute step must be a fraction of the range from {MIN_RELATIVE_STEP:g} to "
                                     f"1, got {relative_step}")


def build_schema(ranges: dict[str, ValueRange], voxel_m: float, relative_step: float,
                 metadata: dict) -> AttributeSchema:
    """The schema for attributes with their map-wide value ranges: an attribute with one value (bit for bit) is
    stored as that constant, the others coded per tile."""
    check_resolution(voxel_m, relative_step)
    if len(ranges) > _MAX_ATTRIBUTES:
        raise InvalidPointCloudError(f"{len(ranges)} attributes; at most {_MAX_ATTRIBUTES} can be coded")
    specs = []
    for name, value_range in ranges.items():
        dtype, low, high = value_range.dtype, value_range.low, value_range.high
        if not np.isfinite([low, high]).all():
            raise InvalidPointCloudError(f"attribute {name!r} has NaN or infinite values")
        if value_range.constant is not None:
            specs.append(AttributeSpec(name, dtype, CONSTANT, value=value_range.constant))
        elif is_continuous(name, dtype):
            step = max((high - low) * relative_step, 1.0 if dtype.kind in "iu" else 0.0)
            specs.append(AttributeSpec(name, dtype, CONTINUOUS, float(low), float(step) if step > 0 else 1.0))
        else:
            specs.append(AttributeSpec(name, dtype, CATEGORICAL))
    return AttributeSchema(float(voxel_m), tuple(specs), metadata)


def _voxel_medians(values: np.ndarray, voxel: np.ndarray, n_voxels: int) -> np.ndarray:
    """Median (lower middle) of each voxel's values."""
    order = np.lexsort((values, voxel))
    counts = np.bincount(voxel, minlength=n_voxels)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return values[order][starts + (counts - 1) // 2]


def _voxel_modes(symbols: np.ndarray, voxel: np.ndarray, n_voxels: int) -> np.ndarray:
    """Most frequent symbol of each voxel (the smallest one on ties); every voxel has at least one symbol. Memory
    grows with the number of (voxel, symbol) pairs, not with voxels x symbols."""
    pairs, counts = np.unique(voxel.astype(np.int64) * (int(symbols.max()) + 1) + symbols, return_counts=True)
    pair_voxel, pair_symbol = np.divmod(pairs, int(symbols.max()) + 1)
    best = np.lexsort((-counts, pair_voxel))  # stable: within a voxel, the largest count, then the smallest symbol
    first = np.concatenate([[True], np.diff(pair_voxel[best]) != 0])
    modes = np.empty(n_voxels, dtype=np.int64)
    modes[pair_voxel[best][first]] = pair_symbol[best][first]
    return modes


def encode_tile_attributes(support: np.ndarray, points_local: np.ndarray, attributes: dict[str, np.ndarray],
                           schema: AttributeSchema, tile_size: np.ndarray) -> bytes:
    """A tile's attribute stream: values for the voxels of `support` (the tile's default decoded points, metres,
    tile frame) from its input points (same frame) and their attribute values. A voxel's value is the median
    (continuous) or most frequent value (categorical) of the values of the input points nearest to its decoded
    points together with those of the input points whose nearest decoded point lies in it (so it suits both the
    decoded points and the input positions)."""
    codes, voxel = support_voxels(support, tile_size, schema.voxel_m)
    original, support64 = np.asarray(points_local, dtype=np.float64), np.asarray(support, dtype=np.float64)
    nearest = KDTree(original).query(support64, k=1)[1].astype(np.int64)
    assigned = KDTree(support64).query(original, k=1)[1].astype(np.int64)
    members = np.concatenate([voxel.ravel(), voxel.ravel()[assigned]])  # the voxel of each value below
    lod = LevelsOfDetail(codes)
    writer, symbols = ByteWriter(), SymbolWriter()
    write_support_check(writer, codes)
    for spec in schema.coded:
        own = np.asarray(attributes[spec.name], dtype=np.float64)
        values = np.concatenate([own[nearest], own])
        if spec.kind == CONTINUOUS:
            quantised = np.round((values - spec.low) / spec.step).astype(np.int64)
            encode_integers(writer, symbols, lod, _voxel_medians(quantised, members, len(codes)))
        else:
            values, symbol = np.unique(values, return_inverse=True)
            used, modes = np.unique(_voxel_modes(symbol.ravel(), members, len(codes)), return_inverse=True)
            palette = values[used].astype(np.int64)  # the values some voxel takes: at most one per voxel
            if len(palette) > MAX_PALETTE:
                raise InvalidPointCloudError(f"attribute {spec.name!r} takes {len(palette):,} distinct values over "
                                             f"one tile's voxels, more than the {MAX_PALETTE:,} a categorical "
                                             f"attribute may (a coarser --attribute-voxel has fewer)")
            writer.varint(len(palette))
            writer.svarint(int(palette[0]))
            for gap in np.diff(palette):
                writer.varint(int(gap))
            encode_categories(writer, symbols, lod, modes.ravel(), len(palette))
    writer.raw(symbols.getvalue())
    return writer.getvalue()


def decode_tile_attributes(stream: bytes, support: np.ndarray, points_local: np.ndarray | None,
                           schema: AttributeSchema, tile_size: np.ndarray, what: str,
                           crc_optional: bool = False) -> dict[str, np.ndarray]:
    """Attributes of decoded points (metres, tile frame; None: the support itself) from a tile's attribute stream
    and its default decoded points `support`: each point takes the values of its nearest support voxel.
    crc_optional: the stream may also have the layout without the support's CRC (container versions 3 and 4,
    docs/format.md), which is read when the CRC does not match, and kept only if it parses exactly on the decoded
    tile's support."""
    codes, voxel, per_voxel = _support_values(stream, support, schema, tile_size, what, crc_optional)
    if points_local is None:
        nearest = voxel.ravel()
    else:
        centres = (morton_cells(codes) + 0.5) * schema.voxel_m
        nearest = KDTree(centres).query(np.asarray(points_local, dtype=np.float64), k=1)[1].astype(np.int64)
    return with_constants(schema, {spec.name: restore(spec, values[nearest])
                                   for spec, values in zip(schema.coded, per_voxel)}, len(nearest))


def with_constants(schema: AttributeSchema, coded: dict[str, np.ndarray], count: int) -> dict[str, np.ndarray]:
    """Every attribute of `count` decoded points in schema order: the coded ones' values and the constants."""
    return {spec.name: spec.constant(count) if spec.kind == CONSTANT else coded[spec.name] for spec in schema.specs}


def _support_values(stream: bytes, support: np.ndarray, schema: AttributeSchema, tile_size: np.ndarray, what: str,
                    crc_optional: bool) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """The support's codes, each support point's voxel and each attribute's values per voxel: the stream's support
    as stated by its count and CRC (repaired, `attrsupport.repaired_support`) or, with crc_optional and a CRC that
    matches no repair, the decoded tile's support when the stream parses exactly without the CRC."""
    codes, voxel = support_voxels(support, tile_size, schema.voxel_m)
    reader = ByteReader(stream, what)
    n_voxels, crc = read_support_check(reader)
    if support_matches(codes, n_voxels, crc):
        return codes, voxel, _voxel_values(reader, codes, schema)
    repaired = repaired_support(support, n_voxels, crc, tile_size, schema.voxel_m)
    if repaired is not None:  # first: a stream with the CRC matches a repaired support only by a 2^-32 chance
        return *repaired, _voxel_values(reader, repaired[0], schema)
    without_crc = ""
    if crc_optional:  # such a stream has 4 bytes after its count too: every histogram takes at least 4
        legacy = ByteReader(stream, what)
        try:
            if legacy.varint(limit=2**40) != len(codes):
                raise legacy.fail(f"its voxel count is not the decoded tile's {len(codes)}")
            return codes, voxel, _voxel_values(legacy, codes, schema)
        except (ContainerError, ValueError, IndexError, OverflowError) as error:
            without_crc = (", and read without the CRC (versions 3 and 4 written before it) "
                           + str(error).removeprefix(f"{what}: "))
    raise reader.fail(f"attribute stream's support ({n_voxels} voxels, CRC {crc:08x}) does not match the decoded "
                      f"tile's ({len(codes)} voxels, CRC {support_crc(codes):08x}) even after moving points on voxel "
                      f"faces{without_crc} (decompress --no-attributes decodes the geometry alone)")


def _voxel_values(reader: ByteReader, codes: np.ndarray, schema: AttributeSchema) -> list[np.ndarray]:
    """Each attribute's values per support voxel from the rest of the stream (tables, then one ANS stream consumed
    exactly)."""
    tables = []
    for spec in schema.coded:
        if spec.kind == CATEGORICAL:
            tables.append((read_palette(reader, len(codes), spec.name), read_category_tables(reader)))
        else:
            tables.append((None, read_integer_tables(reader)))
    symbols = SymbolReader(reader.raw(reader.remaining), reader.what)
    lod = LevelsOfDetail(codes)
    per_voxel = []
    for spec, (palette, histograms) in zip(schema.coded, tables):
        if palette is None:
            per_voxel.append(decode_integers(symbols, lod, histograms))
            continue
        try:
            per_voxel.append(palette[decode_categories(symbols, lod, histograms, len(palette))])
        except ValueError:
            raise reader.fail(f"palette index of {spec.name!r} out of range") from None
    symbols.finish()
    return per_voxel


def read_palette(reader: ByteReader, n_voxels: int, name: str) -> np.ndarray:
    """A categorical attribute's sorted palette of a tile: `varint K` (1 <= K <= min(MAX_PALETTE, voxels)),
    `svarint first`, K - 1 `varint` gaps."""
    size = reader.varint(limit=min(MAX_PALETTE, n_voxels) + 1)
    if size == 0:
        raise reader.fail(f"empty palette of {name!r}")
    return np.cumsum([reader.svarint(limit=2**62)] + [reader.varint(limit=2**62) for _ in range(size - 1)])


def restore(spec: AttributeSpec, values: np.ndarray) -> np.ndarray:
    """Decoded integers -> the attribute's dtype (continuous: low + q * step, rounded and clipped for integers)."""
    if spec.kind == CONTINUOUS:
        values = spec.low + values * spec.step
    if spec.dtype.kind in "iu":
        info = np.iinfo(spec.dtype)
        values = np.clip(np.round(values), info.min, info.max)
    return values.astype(spec.dtype)
