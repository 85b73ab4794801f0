"""The .msq container: magic + version, a CRC-checked header, a CRC-checked tile table, then tile payloads.

See docs/format.md for the byte layout. Reading checks every length and offset against the file size before
allocating anything, so a truncated or corrupt file raises one ContainerError naming the bad part (and tile).
"""

from __future__ import annotations

import dataclasses
import enum
import io
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapsqueeze.codec.attributes import AttributeSchema
from mapsqueeze.codec.embedding import Precision
from mapsqueeze.codec.entropy import ByteReader, ByteWriter
from mapsqueeze.codec.latent import LATENT_CODECS, LatentCodec, LatentLayout
from mapsqueeze.codec.postfilter import OFF, PATCH, PATCH_CHOICE_VERSION, PATCH_CHOICES, PATCH_VERSION, check_setting
from mapsqueeze.codec.rawtile import axis_bits
from mapsqueeze.errors import ContainerError
from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.validation import MAX_ABS_COORDINATE_M

MAGIC = b"MSQZ"
VERSION = PATCH_CHOICE_VERSION
"""Newest version written (6: post-filter bytes may select patch choices, `codec.postfilter.PATCH_CHOICES`, whose
choice stream starts the tile's payload; written only when a tile has them, else version 5 (post-filter bytes may
select patch planes, `codec.postfilter.PATCH`) when a tile has those, else version 4 (a decode post-filter byte
per tile) when a tile has a post-filter, else version 3, the same bytes as before the post-filter existed);
version 3 files (attribute streams coded on the decoded geometry,
`codec.attributes`), version 2 files (attribute streams with their own voxels, `codec.attrlegacy`) and version 1
files (also no default-count field, network and raw tiles only) still read."""
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6)
ATTRIBUTES_ON_DECODED_GEOMETRY = 3
"""First version whose attribute streams are coded on the tiles' decoded geometry."""
POST_FILTER_VERSION = 4
"""First version whose tile table entries carry a post-filter byte."""
_VERSION_WITHOUT_POST_FILTER = 3
SUPPORT_CRC_VERSION = PATCH_VERSION
"""First version whose attribute streams all carry their support's CRC; versions 3 and 4 were written without it
and, later, with it (docs/format.md, "Attributes"), and are read in both layouts."""
_PREAMBLE = struct.Struct("<4sHHI")  # magic, version, reserved flags, header body length
_CRC = struct.Struct("<I")
_TABLE_LENGTH = struct.Struct("<I")
_MIN_ENTRY_BYTES = 3 + 1 + 12 + 1 + 1 + 1 + 4  # a tile table entry holds at least this many bytes
_MAX_INDEX = 2**31
MAX_HEADER_BYTES = 1 << 24
MAX_POINTS_PER_TILE = 1 << 26
"""Largest point count a tile may hold (the format's bound; the compressor refuses larger tiles)."""
DEFAULT_MAX_TILE_POINTS = 1 << 23
"""Points decoded per tile at most unless the caller allows more (`max_tile_points`, CLI --max-tile-points): a
file of a few hundred bytes may claim millions of points, and decoding 2^23 points takes about 1 GB."""
MAX_TILE_SIZE_M = 10_000.0
"""Largest tile side a header may state (metres); shipped models use 40 x 40 x 15 m."""
BOUNDS_STEPS = 65535
"""Tile bounds are stored as uint16 fractions of the tile size (0.6 mm for a 40 m tile), rounded outwards."""
ATTRIBUTES_FLAG = 1
"""Preamble flag: an attribute section (schema, file metadata, one attribute stream per tile) follows the payloads."""


class TileCoding(enum.IntEnum):
    """How a tile's points are stored."""

    network = 0  # the model's embedding, decoded by the network
    raw = 1  # sparse tile: points quantised relative to the tile frame (codec.rawtile)
    octree = 2  # classical fallback: occupancy octree over the tile frame (codec.octreetile; version 2)


class DefaultCount(enum.IntEnum):
    """How many points a tile decodes to when the reader asks for no count or density."""

    input = 0  # the tile's input point count (every version 1 file)
    native = 1  # everything the tile's coding gives inside its box: the network's whole output, the octree's leaves


@dataclass(frozen=True)
class Header:
    """File-wide fields. The tile grid: tile (i, j, k) has its lower corner at origin + (i, j, k) * tile_size."""

    model_id: str
    weights_sha256: str  # hex
    precision: Precision
    subsampling_dist_m: float  # r_s of the model (metres)
    tile_size: tuple[float, float, float]  # metres
    origin: tuple[float, float, float]  # float64 world metres
    n_points: int  # points of the compressed map
    n_tiles: int
    n_features: int  # embedding feature channels
    raw_step_m: float  # quantisation step of raw tiles (metres)
    latent: LatentCodec | None = None  # the precision's latent codec with its map-wide state (q: the histograms)
    default_count: DefaultCount = DefaultCount.native

    @property
    def layout(self) -> LatentLayout:
        return LatentLayout(self.subsampling_dist_m, self.tile_size, self.n_features)

    def serialise(self) -> bytes:
        writer = ByteWriter()
        name = self.model_id.encode()
        if len(name) > 255:
            raise ValueError("model id longer than 255 bytes")
        writer.pack("B", len(name))
        writer.raw(name)
        writer.raw(bytes.fromhex(self.weights_sha256))
        writer.pack("Bd3d3dQIBdB", self.precision, self.subsampling_dist_m, *self.tile_size, *self.origin,
                    self.n_points, self.n_tiles, self.n_features, self.raw_step_m, self.default_count)
        self.latent.write(writer)
        return writer.getvalue()

    @classmethod
    def parse(cls, body: bytes, version: int = VERSION) -> "Header":
        reader = ByteReader(body, "header")
        (name_length,) = reader.unpack("B")
        try:
            model_id = reader.raw(name_length).decode()
        except UnicodeDecodeError:
            raise reader.fail("model id is not UTF-8") from None
        sha = reader.raw(32).hex()
        precision_byte, r_s, *rest = reader.unpack("Bd3d3dQIBd")
        tile_size, origin = tuple(rest[0:3]), tuple(rest[3:6])
        n_points, n_tiles, n_features, raw_step = rest[6:]
        default_count = DefaultCount.input
        if version >= 2:
            (count_byte,) = reader.unpack("B")
            try:
                default_count = DefaultCount(count_byte)
            except ValueError:
                raise reader.fail(f"unknown default count rule {count_byte}") from None
        try:
            precision = Precision(precision_byte)
        except ValueError:
            raise reader.fail(f"unknown precision {precision_byte}") from None
        values = np.array([r_s, *tile_size, raw_step])
        if not (np.isfinite(values).all() and (values > 0).all() and np.isfinite(origin).all()):
            raise reader.fail("grid sizes must be positive and the origin finite")
        if max(r_s, *tile_size) > MAX_TILE_SIZE_M:
            raise reader.fail(f"tile size {tile_size} or r_s {r_s} beyond {MAX_TILE_SIZE_M:g} m")
        if np.abs(origin).max() >= MAX_ABS_COORDINATE_M:
            raise reader.fail(f"absurd origin {origin} (limit {MAX_ABS_COORDINATE_M:.0e} m from 0)")
        try:
            axis_bits(np.asarray(tile_size), raw_step)
        except ValueError as exc:
            raise reader.fail(str(exc)) from None
        if not 1 <= n_features <= 64:
            raise reader.fail(f"{n_features} embedding channels")
        header = cls(model_id, sha, precision, r_s, tile_size, origin, n_points, n_tiles, n_features, raw_step,
                     default_count=default_count)
        header = dataclasses.replace(header, latent=LATENT_CODECS[precision].read(reader, header.layout))
        reader.expect_end()
        return header


@dataclass(frozen=True)
class TileEntry:
    """One row of the tile table."""

    index: tuple[int, int, int]
    n_points: int  # points of the input map in this tile (the default decoded count)
    bounds_lo: tuple[int, int, int]  # tight box of the tile's points in units of tile_size / BOUNDS_STEPS
    bounds_hi: tuple[int, int, int]
    coding: TileCoding
    offset: int  # byte offset of the payload in the file (stored relative to the first payload)
    length: int  # payload bytes
    crc32: int
    post_filter: int = OFF  # decode post-filter setting of a network tile (`codec.postfilter`; version 4)

    def label(self, position: int) -> str:
        return f"tile {position} (index {self.index[0]},{self.index[1]},{self.index[2]})"

    def bounds_m(self, tile_size: np.ndarray) -> np.ndarray:
        """(2, 3) float64 tile-local lower and upper corner (metres) of the tile's points."""
        return np.stack([np.asarray(self.bounds_lo) * _bounds_unit(tile_size),
                         np.asarray(self.bounds_hi) * _bounds_unit(tile_size)])

    def frame_extent_m(self, tile_size: np.ndarray) -> np.ndarray:
        """(3,) size of the tile's points box: coded coordinates lie in [0, extent] (see `frame_origin`)."""
        return np.subtract(self.bounds_hi, self.bounds_lo) * _bounds_unit(tile_size)


def _bounds_unit(tile_size: np.ndarray) -> np.ndarray:
    return np.asarray(tile_size, dtype=np.float64) / BOUNDS_STEPS


def frame_origin(tile_origin: np.ndarray, bounds_lo: tuple[int, int, int], tile_size: np.ndarray) -> np.ndarray:
    """float64 world origin of a tile's coding frame: the lower corner of its points' box.

    The network sees a tile's points relative to this corner, as the reference normalises each submap by its
    minimum; a fixed grid corner would put the ground anywhere in the 15 m of a tile (25 % worse D_e on the KITTI
    submap with e0 when it sat 5 m up).
    """
    return np.asarray(tile_origin, dtype=np.float64) + np.asarray(bounds_lo) * _bounds_unit(tile_size)


def quantise_bounds(points_local: np.ndarray, tile_size: np.ndarray) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Tight box of tile-local points as uint16 steps of tile_size / BOUNDS_STEPS, rounded outwards."""
    unit = _bounds_unit(tile_size)
    low, high = bounding_box(points_local)
    lo = np.clip(np.floor(low / unit), 0, BOUNDS_STEPS).astype(int)
    hi = np.clip(np.ceil(high / unit), 0, BOUNDS_STEPS).astype(int)
    return tuple(int(v) for v in lo), tuple(int(v) for v in hi)


@dataclass(frozen=True)
class TileRecord:
    """What the writer needs per tile: the table fields other than the layout, and the payload."""

    index: tuple[int, int, int]
    n_points: int
    bounds_lo: tuple[int, int, int]
    bounds_hi: tuple[int, int, int]
    coding: TileCoding
    payload: bytes
    post_filter: int = OFF  # network tiles only


@dataclass(frozen=True)
class AttributeSection:
    """What follows the payloads when ATTRIBUTES_FLAG is set: the schema and one attribute stream per tile."""

    schema: AttributeSchema
    streams: list[bytes]  # table order; empty when the schema codes no attribute (metadata only)

    def serialise(self) -> bytes:
        index = ByteWriter()
        index.raw(self.schema.serialise())
        for stream in self.streams:
            index.varint(len(stream))
            index.pack("I", zlib.crc32(stream))
        body = index.getvalue()
        return b"".join([_TABLE_LENGTH.pack(len(body)), body, _CRC.pack(zlib.crc32(body)), *self.streams])


def serialise_container(header: Header, tiles: list[TileRecord], attributes: AttributeSection | None = None) -> bytes:
    """The complete file: preamble, header, header CRC, tile table (length, entries, CRC), payloads in table order,
    then the attribute section when `attributes` is given (without it the bytes are those of a geometry-only file)."""
    body = header.serialise()
    flags = 0 if attributes is None else ATTRIBUTES_FLAG
    if any(tile.post_filter == PATCH_CHOICES for tile in tiles):
        version = PATCH_CHOICE_VERSION
    elif any(tile.post_filter & PATCH for tile in tiles):
        version = PATCH_VERSION
    elif any(tile.post_filter != OFF for tile in tiles):
        version = POST_FILTER_VERSION
    else:
        version = _VERSION_WITHOUT_POST_FILTER
    head = _PREAMBLE.pack(MAGIC, version, flags, len(body)) + body
    head += _CRC.pack(zlib.crc32(head))
    table = ByteWriter()
    offset = 0
    for tile in tiles:
        for value in tile.index:
            table.svarint(value)
        table.varint(tile.n_points)
        table.pack("6HB", *tile.bounds_lo, *tile.bounds_hi, tile.coding)
        if version >= POST_FILTER_VERSION:
            table.pack("B", tile.post_filter)
        table.varint(offset)
        table.varint(len(tile.payload))
        table.pack("I", zlib.crc32(tile.payload))
        offset += len(tile.payload)
    entries = table.getvalue()
    return b"".join([head, _TABLE_LENGTH.pack(len(entries)), entries, _CRC.pack(zlib.crc32(entries)),
                     *(tile.payload for tile in tiles), attributes.serialise() if attributes else b""])


class ContainerReader:
    """Random access to a .msq file or buffer: header and table are read and checked on open, payloads on demand."""

    def __init__(self, stream: io.BufferedIOBase, name: str = "container") -> None:
        self._stream = stream
        self.name = name
        stream.seek(0, os.SEEK_END)
        self.file_size = stream.tell()
        preamble = self._read_at(0, _PREAMBLE.size, "file is too short to be a .msq container")
        magic, version, flags, body_length = _PREAMBLE.unpack(preamble)
        if magic != MAGIC:
            raise self._error("not a .msq container (bad magic bytes)")
        if version not in READABLE_VERSIONS:
            raise self._error(f"unsupported .msq version {version} (this mapsqueeze reads versions "
                              f"{', '.join(map(str, READABLE_VERSIONS))})")
        self.version = version
        if flags & ~ATTRIBUTES_FLAG:
            raise self._error(f"reserved flags 0x{flags & ~ATTRIBUTES_FLAG:04x} set (written by a newer mapsqueeze?)")
        if body_length > MAX_HEADER_BYTES or _PREAMBLE.size + body_length + _CRC.size > self.file_size:
            raise self._error(f"header of {body_length} bytes does not fit in the file (truncated?)")
        body = self._read_at(_PREAMBLE.size, body_length + _CRC.size, "header truncated")
        if zlib.crc32(preamble + body[:-_CRC.size]) != _CRC.unpack(body[-_CRC.size:])[0]:
            raise self._error("header CRC mismatch (corrupt header)")
        try:
            self.header = Header.parse(body[:-_CRC.size], version)
        except ContainerError as exc:
            raise self._error(str(exc)) from None
        self.entries = self._read_table(_PREAMBLE.size + body_length + _CRC.size)
        self.attribute_schema: AttributeSchema | None = None
        self.attribute_entries: list[tuple[int, int, int]] = []  # (offset, length, crc32) per tile
        payload_end = self.entries[-1].offset + self.entries[-1].length
        if flags & ATTRIBUTES_FLAG:
            self._read_attribute_section(payload_end)
        elif payload_end != self.file_size:
            raise self._error(f"{self.file_size - payload_end} unexpected bytes after the last tile")

    def _read_attribute_section(self, start: int) -> None:
        (size,) = _TABLE_LENGTH.unpack(self._read_at(start, _TABLE_LENGTH.size, "attribute section truncated"))
        start += _TABLE_LENGTH.size
        if size > MAX_HEADER_BYTES or start + size + _CRC.size > self.file_size:
            raise self._error(f"attribute section of {size} bytes does not fit in the file (truncated?)")
        raw = self._read_at(start, size + _CRC.size, "attribute section truncated")
        if zlib.crc32(raw[:size]) != _CRC.unpack(raw[size:])[0]:
            raise self._error("attribute section CRC mismatch (corrupt attribute section)")
        reader = ByteReader(raw[:size], f"{self.name}: attribute section")
        self.attribute_schema = AttributeSchema.read(reader)
        offset = start + size + _CRC.size
        if self.attribute_schema.specs:
            for _ in self.entries:
                length = reader.varint(limit=2**32)
                (crc,) = reader.unpack("I")
                self.attribute_entries.append((offset, length, crc))
                offset += length
        reader.expect_end()
        if offset != self.file_size:
            raise self._error(f"attribute streams end at byte {offset}, the file at {self.file_size} (truncated?)")

    def attribute_stream(self, position: int) -> bytes:
        """The CRC-checked attribute stream of tile `position`."""
        offset, length, crc = self.attribute_entries[position]
        label = self.entries[position].label(position)
        data = self._read_at(offset, length, f"{label}: attribute stream truncated")
        if zlib.crc32(data) != crc:
            raise self._error(f"{label}: attribute stream CRC mismatch (corrupt attributes)")
        return data

    def _error(self, message: str) -> ContainerError:
        return ContainerError(f"{self.name}: {message}")

    def _read_at(self, offset: int, size: int, truncated: str) -> bytes:
        if offset + size > self.file_size:
            raise self._error(truncated)
        self._stream.seek(offset)
        data = self._stream.read(size)
        if len(data) != size:
            raise self._error(truncated)
        return data

    def _read_table(self, start: int) -> list[TileEntry]:
        n_tiles = self.header.n_tiles
        if n_tiles == 0:
            raise self._error("the container holds no tiles")
        (table_size,) = _TABLE_LENGTH.unpack(self._read_at(start, _TABLE_LENGTH.size, "tile table truncated"))
        start += _TABLE_LENGTH.size
        if start + table_size + _CRC.size > self.file_size or table_size < n_tiles * _MIN_ENTRY_BYTES:
            raise self._error(f"tile table of {table_size} bytes for {n_tiles} tiles does not fit (truncated?)")
        raw = self._read_at(start, table_size + _CRC.size, "tile table truncated")
        if zlib.crc32(raw[:table_size]) != _CRC.unpack(raw[table_size:])[0]:
            raise self._error("tile table CRC mismatch (corrupt tile table)")
        reader = ByteReader(raw[:table_size], f"{self.name}: tile table")
        payload_start = start + table_size + _CRC.size
        entries = []
        expected_offset = payload_start
        previous_index = None
        for position in range(n_tiles):
            index = tuple(reader.svarint(limit=_MAX_INDEX) for _ in range(3))
            n_points = reader.varint(limit=2**32)
            *bounds, coding = reader.unpack("6HB")
            lo, hi = tuple(bounds[:3]), tuple(bounds[3:])
            post_filter = reader.unpack("B")[0] if self.version >= POST_FILTER_VERSION else OFF
            offset = payload_start + reader.varint(limit=2**63)
            length = reader.varint(limit=2**32)
            (crc,) = reader.unpack("I")
            label = TileEntry(index, n_points, lo, hi, TileCoding.network, offset, length, crc).label(position)
            if coding not in TileCoding.__members__.values() or (self.version < 2 and coding == TileCoding.octree):
                raise self._error(f"{label}: unknown coding {coding}")
            try:
                check_setting(post_filter, label, self.version)
            except ContainerError as exc:
                raise self._error(str(exc)) from None
            if post_filter != OFF and coding != TileCoding.network:
                raise self._error(f"{label}: a post-filter on a tile without a network coding")
            if not 1 <= n_points <= MAX_POINTS_PER_TILE or any(a > b for a, b in zip(lo, hi)):
                raise self._error(f"{label}: bad point count or bounds")
            tile_low = np.asarray(self.header.origin) + np.asarray(index, dtype=np.float64) * self.header.tile_size
            if np.abs(np.concatenate([tile_low, tile_low + self.header.tile_size])).max() >= MAX_ABS_COORDINATE_M:
                raise self._error(f"{label}: absurd tile position (beyond {MAX_ABS_COORDINATE_M:.0e} m from 0)")
            if previous_index is not None and index <= previous_index:
                raise self._error(f"{label}: tiles out of order or duplicated")
            if offset != expected_offset:
                raise self._error(f"{label}: payload offset {offset} should be {expected_offset}")
            if offset + length > self.file_size:
                raise self._error(f"{label}: payload extends past the end of the file (truncated?)")
            entries.append(TileEntry(index, n_points, lo, hi, TileCoding(coding), offset, length, crc, post_filter))
            expected_offset += length
            previous_index = index
        reader.expect_end()
        if sum(entry.n_points for entry in entries) != self.header.n_points:
            raise self._error("tile point counts do not add up to the header's")
        return entries

    def payload(self, position: int) -> bytes:
        """The CRC-checked payload of tile `position` (seeks to it; other payloads are not read)."""
        entry = self.entries[position]
        data = self._read_at(entry.offset, entry.length, f"{entry.label(position)}: payload truncated")
        if zlib.crc32(data) != entry.crc32:
            raise self._error(f"{entry.label(position)}: payload CRC mismatch (corrupt tile)")
        return data

    def header_bytes(self) -> int:
        """Bytes before the first payload (preamble, header, tile table, CRCs)."""
        return self.entries[0].offset if self.entries else self.file_size


def open_container(source: bytes | str | os.PathLike) -> tuple[ContainerReader, io.BufferedIOBase]:
    """A reader over a buffer or a file, and the stream to close after use."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        stream = io.BytesIO(bytes(source))
        return ContainerReader(stream), stream
    path = Path(source)
    try:
        stream = open(path, "rb")
    except OSError as exc:
        raise ContainerError(f"{path}: cannot open ({exc.strerror or exc})") from None
    try:
        return ContainerReader(stream, str(path)), stream
    except BaseException:
        stream.close()
        raise
