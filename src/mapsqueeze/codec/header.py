"""The .msq header: the file-wide fields, in the layout of format version 7 (written) and of versions 1 to 6.

See docs/format.md ("Header body", "Version 7: the compact layout"). Parsing checks every field; a version 7 header
naming a shipped model takes that model's digest and grid from the package (`shipped_layout`).
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.embedding import Precision
from mapsqueeze.codec.entropy import ByteReader, ByteWriter
from mapsqueeze.codec.latent import LATENT_CODECS, LatentCodec, LatentLayout
from mapsqueeze.codec.rawtile import axis_bits
from mapsqueeze.geometry.validation import MAX_ABS_COORDINATE_M

COMPACT_VERSION = 7
"""The compact layout (docs/format.md): varint lengths, one CRC over header and table, a shipped model named by
its id and an 8-byte weights digest prefix with its grid taken from its config, varint counts, no payload offsets,
the latent codec's compact state."""
_SHIPPED_DIGEST_BYTES = 8
"""Weights digest bytes of a version 7 file naming a shipped model (a SHA-256 prefix: enough to tell builds of a
shipped model apart; files of other models hold all 32)."""
DEFAULT_RAW_STEP_M = 0.01
"""The raw step a version 7 header leaves out (any other is stored)."""
_BODY_PRECISION_BITS = 0b11  # version 7 header flags: bits 0-1 precision
_BODY_NATIVE_COUNT = 1 << 2  # default count native
_BODY_SHIPPED = 1 << 3  # a shipped model: 8-byte digest prefix, grid and channels from its config
_BODY_RAW_STEP = 1 << 4  # the raw step is stored (else DEFAULT_RAW_STEP_M)
_BODY_FLAGS = _BODY_PRECISION_BITS | _BODY_NATIVE_COUNT | _BODY_SHIPPED | _BODY_RAW_STEP
MAX_TILE_SIZE_M = 10_000.0
"""Largest tile side a header may state (metres); shipped models use 40 x 40 x 15 m."""


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
        """The version 7 header body."""
        writer = ByteWriter()
        name = self.model_id.encode()
        if len(name) > 255:
            raise ValueError("model id longer than 255 bytes")
        layout = shipped_layout(self.model_id)
        shipped = layout is not None and layout[1:] == (self.subsampling_dist_m, tuple(self.tile_size),
                                                        self.n_features) and (
            layout[0] == self.weights_sha256 or len(self.weights_sha256) == 2 * _SHIPPED_DIGEST_BYTES)
        raw_step = self.raw_step_m != DEFAULT_RAW_STEP_M
        writer.pack("BB", self.precision | (_BODY_NATIVE_COUNT if self.default_count is DefaultCount.native else 0)
                    | (_BODY_SHIPPED if shipped else 0) | (_BODY_RAW_STEP if raw_step else 0), len(name))
        writer.raw(name)
        digest = bytes.fromhex(self.weights_sha256)
        if len(digest) != 32 and not (shipped and len(digest) == _SHIPPED_DIGEST_BYTES):
            raise ValueError("weights digest must be a SHA-256 (or a shipped model's prefix)")
        writer.raw(digest[:_SHIPPED_DIGEST_BYTES] if shipped else digest)
        if not shipped:
            writer.pack("d3dB", self.subsampling_dist_m, *self.tile_size, self.n_features)
        writer.pack("3d", *self.origin)
        writer.varint(self.n_points)
        writer.varint(self.n_tiles)
        if raw_step:
            writer.pack("d", self.raw_step_m)
        self.latent.write(writer)
        return writer.getvalue()

    @classmethod
    def parse(cls, body: bytes, version: int = COMPACT_VERSION) -> "Header":
        reader = ByteReader(body, "header")
        if version >= COMPACT_VERSION:
            return cls._parse_compact(reader)
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
        return cls._checked(reader, model_id, sha, precision_byte, r_s, tile_size, origin, n_points, n_tiles,
                            n_features, raw_step, default_count, compact=False)

    @classmethod
    def _parse_compact(cls, reader: ByteReader) -> "Header":
        flags, name_length = reader.unpack("BB")
        if flags & ~_BODY_FLAGS:
            raise reader.fail(f"reserved header flags 0x{flags & ~_BODY_FLAGS:02x} set")
        try:
            model_id = reader.raw(name_length).decode()
        except UnicodeDecodeError:
            raise reader.fail("model id is not UTF-8") from None
        if flags & _BODY_SHIPPED:
            prefix = reader.raw(_SHIPPED_DIGEST_BYTES).hex()
            shipped = shipped_layout(model_id)
            if shipped is None:
                raise reader.fail(f"names shipped model {model_id!r}, which this mapsqueeze does not ship")
            sha, r_s, tile_size, n_features = shipped
            if not sha.startswith(prefix):  # another build's weights of this rate point: only the prefix is known,
                sha = prefix                # and decoding needs a model whose digest starts with it (check_model)
        else:
            sha = reader.raw(32).hex()
            r_s, *tile_size, n_features = reader.unpack("d3dB")
        origin = reader.unpack("3d")
        n_points = reader.varint(limit=2**64)
        n_tiles = reader.varint(limit=2**32)
        raw_step = reader.unpack("d")[0] if flags & _BODY_RAW_STEP else DEFAULT_RAW_STEP_M
        default_count = DefaultCount.native if flags & _BODY_NATIVE_COUNT else DefaultCount.input
        return cls._checked(reader, model_id, sha, flags & _BODY_PRECISION_BITS, r_s, tuple(tile_size), origin,
                            n_points, n_tiles, n_features, raw_step, default_count, compact=True)

    @classmethod
    def _checked(cls, reader: ByteReader, model_id: str, sha: str, precision_byte: int, r_s: float,
                 tile_size: tuple, origin: tuple, n_points: int, n_tiles: int, n_features: int, raw_step: float,
                 default_count: DefaultCount, compact: bool) -> "Header":
        """The header of these fields after checking them, with the latent codec's state read from `reader`."""
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
        header = dataclasses.replace(header, latent=LATENT_CODECS[precision].read(reader, header.layout, compact))
        reader.expect_end()
        return header


@functools.lru_cache(maxsize=16)  # keyed by a name read from the file: bounded for a long-running decoder
def shipped_layout(model_id: str) -> tuple[str, float, tuple[float, float, float], int] | None:
    """(weights SHA-256 hex, r_s, tile size, embedding channels) of the shipped model `model_id`, or None when no
    shipped model has that name: what a version 7 header naming a shipped model leaves out."""
    from mapsqueeze.model.config import ModelConfig
    from mapsqueeze.model.shipped import CONFIG_FILE, SHIPPED_DIR, shipped_weights_sha256

    sha = shipped_weights_sha256(model_id)
    if sha is None:
        return None
    config = ModelConfig.load(SHIPPED_DIR / model_id / CONFIG_FILE)
    return sha, float(config.subsampling_dist), tuple(float(v) for v in config.tile_size), int(config.embedding_dim)
