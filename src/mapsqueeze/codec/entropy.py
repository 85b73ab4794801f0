"""Byte-level building blocks of the .msq format: bounds-checked reader/writer, integer histograms, ANS streams.

Entropy models are integer tables stored in the file (`Histogram`), turned into constriction `Categorical`
models the same way on both sides, so decoding never depends on floating-point network outputs or libm.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import constriction
import numpy as np

from mapsqueeze.errors import ContainerError

_MAX_VARINT_BYTES = 10


class ByteWriter:
    """Little-endian fixed-size fields and LEB128 varints appended to a growing buffer."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def raw(self, data: bytes) -> None:
        self._buffer += data

    def pack(self, fmt: str, *values) -> None:
        self._buffer += struct.pack("<" + fmt, *values)

    def varint(self, value: int) -> None:
        """Unsigned LEB128 (7 bits a byte, low bits first)."""
        if value < 0:
            raise ValueError(f"varint must be >= 0, got {value}")
        while True:
            byte = value & 0x7F
            value >>= 7
            self._buffer.append(byte | (0x80 if value else 0))
            if not value:
                return

    def svarint(self, value: int) -> None:
        """Signed integer as a zigzag varint (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...)."""
        self.varint(2 * value if value >= 0 else -2 * value - 1)

    def getvalue(self) -> bytes:
        return bytes(self._buffer)


class ByteReader:
    """Reads what ByteWriter wrote; any overrun or malformed field raises ContainerError prefixed with `what`."""

    def __init__(self, data: bytes | memoryview, what: str) -> None:
        self._data = memoryview(data)
        self._pos = 0
        self.what = what

    def fail(self, message: str) -> ContainerError:
        return ContainerError(f"{self.what}: {message}")

    @property
    def remaining(self) -> int:
        return len(self._data) - self._pos

    def raw(self, n: int) -> bytes:
        if n < 0 or n > self.remaining:
            raise self.fail(f"truncated (needs {n} bytes at offset {self._pos}, {self.remaining} left)")
        out = bytes(self._data[self._pos:self._pos + n])
        self._pos += n
        return out

    def unpack(self, fmt: str) -> tuple:
        return struct.unpack("<" + fmt, self.raw(struct.calcsize("<" + fmt)))

    def varint(self, limit: int = 2**63) -> int:
        """An unsigned varint, refused if it is >= `limit` (callers pass the largest sane value + 1) or written with
        more bytes than it needs (a last byte of 0 after the first: the writer never does, so a file has one form)."""
        value = 0
        for shift in range(0, 7 * _MAX_VARINT_BYTES, 7):
            byte = self.raw(1)[0]
            value |= (byte & 0x7F) << shift
            if not byte & 0x80:
                if byte == 0 and shift:
                    raise self.fail("overlong varint")
                if value >= limit:
                    raise self.fail(f"value {value} out of range (limit {limit - 1})")
                return value
        raise self.fail("malformed varint")

    def svarint(self, limit: int = 2**62) -> int:
        value = self.varint(2 * limit)
        return value // 2 if value % 2 == 0 else -(value + 1) // 2

    def expect_end(self) -> None:
        if self.remaining:
            raise self.fail(f"{self.remaining} unexpected trailing bytes")


# --- histograms -------------------------------------------------------------------------------------------------

_CODE_BITS = 5
_MAX_CODE = 2**_CODE_BITS - 1
# Weight of each 5-bit code: 0 for "never seen", then a geometric ladder with ratio sqrt(2) (integer arithmetic,
# so every platform builds the same probabilities); the ladder spans 2^15 between the rarest and commonest bucket.
_WEIGHTS = np.array([0] + [(1000 if j % 2 == 0 else 1414) << (j // 2) for j in range(_MAX_CODE)], dtype=np.int64)
_MAX_BUCKETS = 256
_MAX_SPAN = 2**24  # largest alphabet a histogram may cover (constriction's Categorical limit is far above)


@dataclass(frozen=True, eq=False)
class Histogram:
    """A piecewise-constant distribution over the integers low .. low + width * len(codes) - 1.

    The alphabet is cut into buckets of `width` consecutive values; bucket b has mass proportional to
    _WEIGHTS[codes[b]], spread evenly over its values. Stored as low, width, bucket count and 5-bit codes.
    """

    low: int
    width: int
    codes: np.ndarray  # uint8, one per bucket, 0 .. _MAX_CODE
    _model: object = field(default=None, repr=False, compare=False)

    @property
    def span(self) -> int:
        return self.width * len(self.codes)

    def probabilities(self) -> np.ndarray:
        """Unnormalised float64 probability of every value of the alphabet (constriction normalises)."""
        return np.repeat(_WEIGHTS[self.codes].astype(np.float64), self.width)

    def __reduce__(self):
        """Pickled without the cached constriction model, which cannot be pickled (Dask ships headers to workers)."""
        return (Histogram, (self.low, self.width, self.codes))

    def model(self):
        if self._model is None:
            probabilities = self.probabilities()
            if probabilities.sum() == 0:  # a corrupt table; keep it decodable, the CRC has already failed
                probabilities = np.ones_like(probabilities)
            try:
                model = constriction.stream.model.Categorical(probabilities, perfect=False)
            except ValueError as exc:  # e.g. an alphabet constriction cannot normalise (a crafted table)
                raise ContainerError(f"entropy table of {len(probabilities):,} values is not usable: {exc}") from None
            object.__setattr__(self, "_model", model)
        return self._model

    def bits(self, values: np.ndarray) -> float:
        """Ideal code length (bits) of `values` under this histogram."""
        probabilities = self.probabilities()
        probabilities /= probabilities.sum()
        return float(-np.log2(np.maximum(probabilities[np.asarray(values) - self.low], 2.0**-24)).sum())

    @classmethod
    def fit(cls, values: np.ndarray) -> "Histogram":
        """The histogram of `values` whose bucket width minimises table + data bits (a small MDL search)."""
        values = np.asarray(values, dtype=np.int64).ravel()
        if len(values) == 0:
            return cls(0, 1, np.array([_MAX_CODE], dtype=np.uint8))
        low = int(values.min())
        span = int(values.max()) - low + 1
        if span > _MAX_SPAN:
            raise ValueError(f"histogram alphabet of {span} values exceeds {_MAX_SPAN}")
        counts = np.bincount(values - low, minlength=span)
        best, best_bits = None, math.inf
        width = max(1, -(-span // _MAX_BUCKETS))
        while True:
            candidate = cls._from_counts(low, width, counts)
            total = candidate.bits(values) + candidate.table_bits()
            if total < best_bits:
                best, best_bits = candidate, total
            if width >= span:
                return best
            width = min(span, max(width + 1, int(width * 1.5)))

    @classmethod
    def _from_counts(cls, low: int, width: int, counts: np.ndarray) -> "Histogram":
        n_buckets = -(-len(counts) // width)
        padded = np.zeros(n_buckets * width, dtype=np.int64)
        padded[:len(counts)] = counts
        bucket_counts = padded.reshape(n_buckets, width).sum(axis=1)
        codes = np.zeros(n_buckets, dtype=np.uint8)
        seen = bucket_counts > 0
        ratio = np.log2(bucket_counts[seen] / bucket_counts.max())
        codes[seen] = np.clip(np.round(2 * ratio) + _MAX_CODE, 1, _MAX_CODE)
        return cls(low, width, codes)

    def table_bits(self) -> int:
        return 8 * (len(self.serialise()))

    def serialise(self) -> bytes:
        writer = ByteWriter()
        self.write(writer)
        return writer.getvalue()

    def write(self, writer: ByteWriter) -> None:
        writer.svarint(self.low)
        writer.varint(self.width)
        writer.varint(len(self.codes))
        bits = np.unpackbits(self.codes[:, None], axis=1)[:, 8 - _CODE_BITS:]
        writer.raw(np.packbits(bits.ravel()).tobytes())

    @classmethod
    def read(cls, reader: ByteReader) -> "Histogram":
        low = reader.svarint(limit=2**40)
        width = reader.varint(limit=_MAX_SPAN + 1)
        n_buckets = reader.varint(limit=_MAX_BUCKETS + 1)
        if width == 0 or n_buckets == 0 or width * n_buckets > _MAX_SPAN:
            raise reader.fail(f"bad histogram shape ({n_buckets} buckets of width {width})")
        packed = np.frombuffer(reader.raw(-(-n_buckets * _CODE_BITS // 8)), dtype=np.uint8)
        bits = np.unpackbits(packed)[:n_buckets * _CODE_BITS].reshape(n_buckets, _CODE_BITS)
        codes = np.packbits(np.pad(bits, ((0, 0), (8 - _CODE_BITS, 0))), axis=1).ravel()
        return cls(low, width, codes)

    def check(self, values: np.ndarray) -> None:
        if len(values) and (values.min() < self.low or values.max() >= self.low + self.span):
            raise ValueError("value outside the histogram's alphabet")


# --- ANS symbol streams -----------------------------------------------------------------------------------------

_BIT_CHUNK = 16


def _bit_chunks(nbits: np.ndarray):
    """(mask, shift, chunk sizes) for splitting values of nbits[i] bits into chunks of at most 16 bits."""
    for shift in range(0, int(nbits.max(initial=0)), _BIT_CHUNK):
        mask = nbits > shift
        yield mask, shift, np.minimum(nbits[mask] - shift, _BIT_CHUNK)


class SymbolWriter:
    """Collects symbol groups in decoding order, then entropy codes them with one ANS stack coder."""

    def __init__(self) -> None:
        self._groups = []

    def histogram(self, values: np.ndarray, histogram: Histogram) -> None:
        values = np.asarray(values, dtype=np.int64).ravel()
        histogram.check(values)
        if len(values) and histogram.span > 1:  # a one-value alphabet needs no bits
            self._groups.append(((values - histogram.low).astype(np.int32), histogram.model(), ()))

    def bits(self, values: np.ndarray, nbits: np.ndarray) -> None:
        """values[i] as nbits[i] equiprobable bits (nbits may be 0)."""
        values = np.asarray(values, dtype=np.uint64)
        nbits = np.asarray(nbits, dtype=np.int64)
        for mask, shift, sizes in _bit_chunks(nbits):
            chunk = (values[mask] >> np.uint64(shift)) & ((np.uint64(1) << sizes.astype(np.uint64)) - np.uint64(1))
            self._groups.append((chunk.astype(np.int32), constriction.stream.model.Uniform(),
                                 ((np.int32(1) << sizes.astype(np.int32)).astype(np.int32),)))

    def getvalue(self) -> bytes:
        coder = constriction.stream.stack.AnsCoder()
        for symbols, model, params in reversed(self._groups):
            coder.encode_reverse(symbols, model, *params)
        return coder.get_compressed().astype("<u4").tobytes()


class SymbolReader:
    """Decodes SymbolWriter output group by group; `finish` checks that exactly all of it was consumed."""

    def __init__(self, data: bytes, what: str) -> None:
        self.what = what
        if len(data) % 4:
            raise ContainerError(f"{what}: entropy-coded stream of {len(data)} bytes is not whole 32-bit words")
        try:
            self._coder = constriction.stream.stack.AnsCoder(np.frombuffer(data, dtype="<u4").astype(np.uint32))
        except ValueError as exc:
            raise ContainerError(f"{what}: invalid entropy-coded stream ({exc})") from None

    def histogram(self, histogram: Histogram, count: int) -> np.ndarray:
        if histogram.span == 1:
            return np.full(count, histogram.low, dtype=np.int64)
        return self._coder.decode(histogram.model(), count).astype(np.int64) + histogram.low

    def bits(self, nbits: np.ndarray) -> np.ndarray:
        nbits = np.asarray(nbits, dtype=np.int64)
        values = np.zeros(len(nbits), dtype=np.uint64)
        for mask, shift, sizes in _bit_chunks(nbits):
            chunk = self._coder.decode(constriction.stream.model.Uniform(), (np.int32(1) << sizes).astype(np.int32))
            values[mask] |= chunk.astype(np.uint64) << np.uint64(shift)
        return values

    def finish(self) -> None:
        if not self._coder.is_empty():
            raise ContainerError(f"{self.what}: entropy-coded stream has data left after the last symbol")


def bit_length(values: np.ndarray) -> np.ndarray:
    """Number of bits of each non-negative int64 (0 for 0), vectorised."""
    values = np.asarray(values, dtype=np.int64)
    out = np.zeros(values.shape, dtype=np.int64)
    rest = values.copy()
    for shift in (32, 16, 8, 4, 2, 1):
        big = rest >= (1 << shift)
        out[big] += shift
        rest[big] >>= shift
    return out + (rest > 0)


def encode_gaps(writer: SymbolWriter, gaps: np.ndarray, buckets: Histogram) -> None:
    """Non-negative gaps as Elias-gamma-like pairs: bit length (entropy coded) + the bits below the top one."""
    lengths = bit_length(gaps)
    writer.histogram(lengths, buckets)
    top = np.where(lengths > 0, np.left_shift(1, np.maximum(lengths - 1, 0)), 0)
    writer.bits(gaps - top, np.maximum(lengths - 1, 0))


def decode_gaps(reader: SymbolReader, count: int, buckets: Histogram) -> np.ndarray:
    lengths = reader.histogram(buckets, count)
    if len(lengths) and (lengths.min() < 0 or lengths.max() > 62):
        raise ContainerError(f"{reader.what}: gap length out of range")
    rest = reader.bits(np.maximum(lengths - 1, 0)).astype(np.int64)
    return np.where(lengths > 0, np.left_shift(1, np.maximum(lengths - 1, 0)), 0) + rest


def fit_gap_buckets(gaps: np.ndarray) -> Histogram:
    return Histogram.fit(bit_length(gaps))
