"""The .msq container: magic + version, a CRC-checked header (`codec.header`) and tile table, then tile payloads.

See docs/format.md for the byte layout. Reading checks every length and offset against the file size before
allocating anything, so a truncated or corrupt file raises one ContainerError naming the bad part (and tile).
"""

from __future__ import annotations

import enum
import io
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapsqueeze.codec.attributes import CONSTANT_VERSION, AttributeSchema
from mapsqueeze.codec.entropy import ByteReader, ByteWriter
from mapsqueeze.codec.header import COMPACT_VERSION, Header
from mapsqueeze.codec.postfilter import OFF, PATCH_VERSION, check_setting
from mapsqueeze.errors import ContainerError
from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.validation import MAX_ABS_COORDINATE_M

MAGIC = b"MSQZ"
VERSION = COMPACT_VERSION
"""The version written, or CONSTANT_VERSION (8: the same layout, its attribute schema may hold attributes stored
as one constant value, `codec.attributes.CONSTANT`) by a file whose schema holds one, so that every other file keeps
its bytes. Readable besides: 6 (post-filter bytes may select patch choices,
`codec.postfilter.PATCH_CHOICES`), 5 (patch planes, `codec.postfilter.PATCH`), 4 (a decode post-filter byte per
tile), 3 (attribute streams coded on the decoded geometry, `codec.attributes`), 2 (attribute streams with their
own voxels, `codec.attrlegacy`) and 1 (also no default-count field, network and raw tiles only)."""
READABLE_VERSIONS = (1, 2, 3, 4, 5, 6, 7, 8)
ATTRIBUTES_ON_DECODED_GEOMETRY = 3
"""First version whose attribute streams are coded on the tiles' decoded geometry."""
POST_FILTER_VERSION = 4
"""First version whose tile table entries carry a post-filter byte."""
SUPPORT_CRC_VERSION = PATCH_VERSION
"""First version whose attribute streams all carry their support's CRC; versions 3 and 4 were written without it
and, later, with it (docs/format.md, "Attributes"), and are read in both layouts."""
_PREAMBLE = struct.Struct("<4sHHI")  # magic, version, reserved flags, header body length (versions 1 to 6)
_MAGIC_VERSION = struct.Struct("<4sH")
_CRC = struct.Struct("<I")
_TABLE_LENGTH = struct.Struct("<I")
_MIN_ENTRY_BYTES = 3 + 1 + 12 + 1 + 1 + 1 + 4  # a tile table entry holds at least this many bytes (versions 1-6)
_MIN_COMPACT_ENTRY_BYTES = 3 + 1 + 1 + 1 + 4  # version 7
_FULL_FACES_SHIFT = 2  # version 7 table: coding byte bits 2-7, bounds at the tile's faces (lo 0 / hi 65535) omitted
_MAX_INDEX = 2**31
MAX_HEADER_BYTES = 1 << 24
MAX_POINTS_PER_TILE = 1 << 26
"""Largest point count a tile may hold (the format's bound; the compressor refuses larger tiles)."""
DEFAULT_MAX_TILE_POINTS = 1 << 23
"""Points decoded per tile at most unless the caller allows more (`max_tile_points`, CLI --max-tile-points): a
file of a few hundred bytes may claim millions of points, and decoding 2^23 points takes about 1 GB."""
BOUNDS_STEPS = 65535
"""Tile bounds are stored as uint16 fractions of the tile size (0.6 mm for a 40 m tile), rounded outwards."""
ATTRIBUTES_FLAG = 1
"""Preamble flag: an attribute section (schema, file metadata, one attribute stream per tile) follows the payloads."""


class TileCoding(enum.IntEnum):
    """How a tile's points are stored."""

    network = 0  # the model's embedding, decoded by the network
    raw = 1  # sparse tile: points quantised relative to the tile frame (codec.rawtile)
    octree = 2  # classical fallback: occupancy octree over the tile frame (codec.octreetile; version 2)



@dataclass(frozen=True)
class TileEntry:
    """One row of the tile table."""

    index: tuple[int, int, int]
    n_points: int  # points of the input map in this tile (the default decoded count of an input-count header)
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
    streams: list[bytes]  # table order; empty when the schema codes no attribute per tile (metadata, constants)

    def serialise(self) -> bytes:
        index = ByteWriter()
        index.raw(self.schema.serialise())
        for stream in self.streams:
            index.varint(len(stream))
            index.pack("I", zlib.crc32(stream))
        body = index.getvalue()
        return b"".join([_TABLE_LENGTH.pack(len(body)), body, _CRC.pack(zlib.crc32(body)), *self.streams])


def serialise_container(header: Header, tiles: list[TileRecord], attributes: AttributeSection | None = None) -> bytes:
    """The complete version 7 file (version 8 when the attribute schema holds a constant attribute): magic, version,
    flags and the header and table lengths, the header, the tile table, their CRC, the payloads in table order, then
    the attribute section when `attributes` is given (without it the bytes are those of a geometry-only file)."""
    body = header.serialise()
    table = ByteWriter()
    for tile in tiles:
        for value in tile.index:
            table.svarint(value)
        table.varint(tile.n_points)
        low_faces = [value == 0 for value in tile.bounds_lo]
        high_faces = [value == BOUNDS_STEPS for value in tile.bounds_hi]
        faces = sum(1 << bit for bit, full in enumerate(low_faces + high_faces) if full)
        table.pack("B", tile.coding | faces << _FULL_FACES_SHIFT)
        for value, full in zip((*tile.bounds_lo, *tile.bounds_hi), low_faces + high_faces):
            if not full:
                table.pack("H", value)
        if tile.coding == TileCoding.network:
            table.pack("B", tile.post_filter)
        elif tile.post_filter != OFF:
            raise ValueError("a post-filter on a tile without a network coding")
        table.varint(len(tile.payload))
        table.pack("I", zlib.crc32(tile.payload))
    entries = table.getvalue()
    head = ByteWriter()
    version = (attributes.schema.version if attributes else None) or VERSION
    head.raw(_MAGIC_VERSION.pack(MAGIC, version))
    head.varint(0 if attributes is None else ATTRIBUTES_FLAG)
    head.varint(len(body))
    head.varint(len(entries))
    head.raw(body + entries)
    head = head.getvalue()
    return b"".join([head, _CRC.pack(zlib.crc32(head)), *(tile.payload for tile in tiles),
                     attributes.serialise() if attributes else b""])


class ContainerReader:
    """Random access to a .msq file or buffer: header and table are read and checked on open, payloads on demand."""

    def __init__(self, stream: io.BufferedIOBase, name: str = "container") -> None:
        self._stream = stream
        self.name = name
        stream.seek(0, os.SEEK_END)
        self.file_size = stream.tell()
        magic, version = _MAGIC_VERSION.unpack(
            self._read_at(0, _MAGIC_VERSION.size, "file is too short to be a .msq container"))
        if magic != MAGIC:
            raise self._error("not a .msq container (bad magic bytes)")
        if version not in READABLE_VERSIONS:
            raise self._error(f"unsupported .msq version {version} (this mapsqueeze reads versions "
                              f"{', '.join(map(str, READABLE_VERSIONS))})")
        self.version = version
        flags, body, table, payload_start = (self._read_compact_head() if version >= COMPACT_VERSION
                                             else self._read_head())
        try:
            self.header = Header.parse(body, version)
        except ContainerError as exc:
            raise self._error(str(exc)) from None
        self.entries = self._parse_table(table, payload_start)
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
        self.attribute_schema = AttributeSchema.read(reader, constants=self.version >= CONSTANT_VERSION)
        offset = start + size + _CRC.size
        if self.attribute_schema.coded:
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

    def _check_flags(self, flags: int) -> None:
        """Refused before any CRC: a file of a newer writer names the feature this reader lacks."""
        if flags & ~ATTRIBUTES_FLAG:
            raise self._error(f"reserved flags 0x{flags & ~ATTRIBUTES_FLAG:04x} set (written by a newer mapsqueeze?)")

    def _read_head(self) -> tuple[int, bytes, bytes, int]:
        """(flags, header body, tile table bytes, first payload byte) of a version 1 to 6 file, CRCs checked."""
        preamble = self._read_at(0, _PREAMBLE.size, "file is too short to be a .msq container")
        _, _, flags, body_length = _PREAMBLE.unpack(preamble)
        self._check_flags(flags)
        if body_length > MAX_HEADER_BYTES or _PREAMBLE.size + body_length + _CRC.size > self.file_size:
            raise self._error(f"header of {body_length} bytes does not fit in the file (truncated?)")
        body = self._read_at(_PREAMBLE.size, body_length + _CRC.size, "header truncated")
        if zlib.crc32(preamble + body[:-_CRC.size]) != _CRC.unpack(body[-_CRC.size:])[0]:
            raise self._error("header CRC mismatch (corrupt header)")
        start = _PREAMBLE.size + body_length + _CRC.size
        (table_size,) = _TABLE_LENGTH.unpack(self._read_at(start, _TABLE_LENGTH.size, "tile table truncated"))
        start += _TABLE_LENGTH.size
        if start + table_size + _CRC.size > self.file_size:
            raise self._error(f"tile table of {table_size} bytes does not fit (truncated?)")
        raw = self._read_at(start, table_size + _CRC.size, "tile table truncated")
        if zlib.crc32(raw[:table_size]) != _CRC.unpack(raw[table_size:])[0]:
            raise self._error("tile table CRC mismatch (corrupt tile table)")
        return flags, body[:-_CRC.size], raw[:table_size], start + table_size + _CRC.size

    def _read_compact_head(self) -> tuple[int, bytes, bytes, int]:
        """(flags, header body, tile table bytes, first payload byte) of a version 7 file, the CRC checked."""
        lead = self._read_at(0, min(self.file_size, _MAGIC_VERSION.size + 3 * 10), "file truncated")
        reader = ByteReader(lead, f"{self.name}: preamble")
        reader.raw(_MAGIC_VERSION.size)
        try:
            flags = reader.varint(limit=1 << 16)
            body_length = reader.varint(limit=MAX_HEADER_BYTES + 1)
            table_size = reader.varint(limit=2**32)
        except ContainerError:
            raise self._error("preamble truncated or malformed (truncated?)") from None
        self._check_flags(flags)
        start = len(lead) - reader.remaining
        end = start + body_length + table_size
        if end + _CRC.size > self.file_size:
            raise self._error(f"header of {body_length} and tile table of {table_size} bytes do not fit in the "
                              "file (truncated?)")
        head = self._read_at(0, end + _CRC.size, "header truncated")
        if zlib.crc32(head[:end]) != _CRC.unpack(head[end:])[0]:
            raise self._error("header CRC mismatch (corrupt header or tile table)")
        return flags, head[start:start + body_length], head[start + body_length:end], end + _CRC.size

    def _parse_table(self, table: bytes, payload_start: int) -> list[TileEntry]:
        n_tiles = self.header.n_tiles
        if n_tiles == 0:
            raise self._error("the container holds no tiles")
        compact = self.version >= COMPACT_VERSION
        if len(table) < n_tiles * (_MIN_COMPACT_ENTRY_BYTES if compact else _MIN_ENTRY_BYTES):
            raise self._error(f"tile table of {len(table)} bytes for {n_tiles} tiles does not fit (truncated?)")
        reader = ByteReader(table, f"{self.name}: tile table")
        entries = []
        expected_offset = payload_start
        previous_index = None
        for position in range(n_tiles):
            index = tuple(reader.svarint(limit=_MAX_INDEX) for _ in range(3))
            n_points = reader.varint(limit=2**32)
            if compact:
                (byte,) = reader.unpack("B")
                coding, faces = byte & ((1 << _FULL_FACES_SHIFT) - 1), byte >> _FULL_FACES_SHIFT
                bounds = [(0 if bit < 3 else BOUNDS_STEPS) if faces >> bit & 1 else reader.unpack("H")[0]
                          for bit in range(6)]
                post_filter = reader.unpack("B")[0] if coding == TileCoding.network else OFF
                offset = expected_offset
            else:
                *bounds, coding = reader.unpack("6HB")
                post_filter = reader.unpack("B")[0] if self.version >= POST_FILTER_VERSION else OFF
                offset = payload_start + reader.varint(limit=2**63)
            lo, hi = tuple(bounds[:3]), tuple(bounds[3:])
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
