"""The precisions of the embedding coding and the q lattice (the latent codecs themselves are in `latent`).

q: positions split into their cell of the r_s grid (the embedding points come from grid subsampling at r_s, so
  cells are nearly unique) and an offset from the cell centre quantised with a fixed step; features turned onto
  their map-wide principal axes and quantised with one fitted step (`Quantiser`). Occupied cells are coded as
  gaps between sorted cell indices (x fastest), offsets and features with histograms fitted once per file
  (`QuantModel`, stored in the header), all in one ANS stream per tile. Points come out sorted by cell; the
  decoder is order-independent.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from mapsqueeze.codec.entropy import (
    ByteReader,
    ByteWriter,
    Histogram,
    SymbolReader,
    SymbolWriter,
    decode_gaps,
    encode_gaps,
    fit_gap_buckets,
)
from mapsqueeze.errors import MapsqueezeError


class Precision(enum.IntEnum):
    """How embeddings are stored (the value is the byte in the file header)."""

    f32 = 0
    f16 = 1
    q = 2

    @classmethod
    def parse(cls, name: str) -> "Precision":
        try:
            return cls[name]
        except KeyError:
            choices = ", ".join(p.name for p in cls)
            raise MapsqueezeError(f"unknown precision {name!r}; choose one of {choices}") from None


DEFAULT_POSITION_STEP_RS = 0.02
"""q: quantisation step of the offset of an embedding point from its cell centre, as a fraction of r_s, at most
DEFAULT_POSITION_STEP_MAX_M (2 cm for e3, 2.4 cm for e2, 4 cm for e1 and e0): the coarser grids tolerate coarser
positions for the same relative D_e loss. With DEFAULT_FEATURE_STEP_STD, the steps that moved the real and
simulated submaps' rate points furthest towards the classical front in D_e and IoU (BENCHMARKS.md, "Quantiser
steps")."""

DEFAULT_POSITION_STEP_MAX_M = 0.04
"""q: the largest default position step (metres): e0 (r_s 3 m) at 6 cm lost IoU against the front on 6 of 9
submaps, at 4 cm on 2."""

DEFAULT_FEATURE_STEP_STD = 0.3
"""q: quantisation step of the (decorrelated) features, as a fraction of their typical standard deviation."""


@dataclass(frozen=True)
class CellGrid:
    """The r_s grid of a tile: cells of edge `cell_m` anchored at the tile frame, linear index x fastest."""

    cell_m: float
    tile_size: tuple[float, float, float]

    @property
    def shape(self) -> np.ndarray:
        return np.ceil(np.asarray(self.tile_size) / self.cell_m).astype(np.int64)

    @property
    def n_cells(self) -> int:
        return int(self.shape.prod())

    def cell_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(linear cell index (M,), cell coordinates (M, 3)) of tile-local points, clipped into the grid."""
        coords = np.clip(np.floor(np.asarray(points, dtype=np.float64) / self.cell_m), 0, self.shape - 1)
        coords = coords.astype(np.int64)
        nx, ny, _ = self.shape
        return (coords[:, 2] * ny + coords[:, 1]) * nx + coords[:, 0], coords

    def cell_coords(self, linear: np.ndarray) -> np.ndarray:
        nx, ny, _ = self.shape
        return np.stack([linear % nx, (linear // nx) % ny, linear // (nx * ny)], axis=1)

    def centres(self, coords: np.ndarray) -> np.ndarray:
        return (coords + 0.5) * self.cell_m


@dataclass
class QuantisedEmbedding:
    """An embedding on the q lattice, sorted by (cell, offset, feature)."""

    cells: np.ndarray  # (M,) int64 linear cell index, ascending
    offsets: np.ndarray  # (M, 3) int64 offset from the cell centre in position steps
    features: np.ndarray  # (M, D) int64 features in feature steps

    def __len__(self) -> int:
        return len(self.cells)

    def compact(self) -> "QuantisedEmbedding":
        """The same embedding with its offsets and features in the smallest signed integer types that hold them
        (what a map-wide fit holds of every tile; `QuantModel.fit` reads them as int64)."""
        return QuantisedEmbedding(self.cells, _narrowest(self.offsets), _narrowest(self.features))


def _narrowest(values: np.ndarray) -> np.ndarray:
    """Integer values as int8, int16 or int32, the first that holds them (unchanged when none does)."""
    if values.size == 0:
        return values
    low, high = values.min(), values.max()
    for dtype in (np.int8, np.int16, np.int32):
        if np.iinfo(dtype).min <= low and high <= np.iinfo(dtype).max:
            return values.astype(dtype)
    return values


@dataclass(frozen=True)
class Quantiser:
    """The q lattice: offsets from cell centres in steps of `position_m` per axis (metres); features centred,
    turned onto their principal axes (a map-wide PCA: decorrelated channels code in fewer bits) and quantised with
    one step on every axis (an orthonormal turn keeps the quantisation error of the original channels)."""

    position_m: tuple[float, float, float]
    feature_step: float
    feature_mean: np.ndarray  # (D,) float16
    feature_basis: np.ndarray  # (D, D) float16, columns are the principal axes

    @classmethod
    def fit(cls, features: np.ndarray, position_step_m: float | tuple[float, float, float],
            feature_step_std: float = DEFAULT_FEATURE_STEP_STD) -> "Quantiser":
        """The quantiser for a map whose embedding features are `features` (M, D); the feature step is
        feature_step_std x the root mean square of the channels' standard deviations."""
        features = np.array(features, dtype=np.float64)  # a copy, centred in place below
        dim = features.shape[1]
        if len(features) < 2:
            mean, basis, rms_std = np.zeros(dim), np.eye(dim), 1.0
        else:
            mean = features.mean(axis=0)
            features -= mean
            covariance = np.atleast_2d(np.cov(features, rowvar=False))
            basis = np.linalg.eigh(covariance)[1][:, ::-1]  # largest variance first
            basis *= np.where(basis[np.abs(basis).argmax(axis=0), np.arange(dim)] < 0, -1.0, 1.0)  # fixed signs
            rms_std = max(float(np.sqrt(np.trace(covariance) / dim)), 1e-3)
        position = np.broadcast_to(np.asarray(position_step_m, dtype=np.float64), (3,))
        # Stored as float32 / float16: round here so that encoder and decoder use the same values.
        return cls(tuple(float(np.float32(v)) for v in position), float(np.float32(feature_step_std * rms_std)),
                   mean.astype(np.float16), basis.astype(np.float16))

    def features_to_lattice(self, features: np.ndarray) -> np.ndarray:
        turned = (np.asarray(features, dtype=np.float64) - self.feature_mean) @ self.feature_basis.astype(np.float64)
        return np.round(turned / self.feature_step).astype(np.int64)

    def lattice_to_features(self, lattice: np.ndarray) -> np.ndarray:
        """float32 features of lattice points; elementwise float64 arithmetic in a fixed order (platform-stable)."""
        turned = lattice * self.feature_step
        basis = self.feature_basis.astype(np.float64)
        features = np.broadcast_to(self.feature_mean.astype(np.float64), turned.shape).copy()
        for axis in range(turned.shape[1]):
            features += turned[:, axis:axis + 1] * basis[:, axis]
        return features.astype(np.float32)

    def write(self, writer: ByteWriter, compact: bool = True) -> None:
        """compact (format version 7): no channel count (the header's), one position step when x, y and z share it;
        else varint D and the three steps."""
        if compact:
            position = self.position_m[:1] if len(set(self.position_m)) == 1 else self.position_m
            writer.pack("B", len(position))
            writer.pack(f"{len(position) + 1}f", *position, self.feature_step)
        else:
            writer.varint(len(self.feature_mean))
            writer.pack("4f", *self.position_m, self.feature_step)
        writer.raw(self.feature_mean.astype("<f2").tobytes() + self.feature_basis.astype("<f2").tobytes())

    @classmethod
    def read(cls, reader: ByteReader, dim: int | None = None) -> "Quantiser":
        """What `write` wrote; `dim` (the header's channel count) given for the compact form, None for the other."""
        if dim is None:
            dim = reader.varint(limit=65)
            *position, feature_step = reader.unpack("4f")
        else:
            (n_steps,) = reader.unpack("B")
            if n_steps not in (1, 3):
                raise reader.fail(f"{n_steps} position steps (1 or 3)")
            *position, feature_step = reader.unpack(f"{n_steps + 1}f")
            position = position * (3 // n_steps)
        mean = np.frombuffer(reader.raw(2 * dim), dtype="<f2").astype(np.float16)
        basis = np.frombuffer(reader.raw(2 * dim * dim), dtype="<f2").astype(np.float16).reshape(dim, dim)
        if not all(np.isfinite(v) and v > 0 for v in (*position, feature_step)):
            raise reader.fail("quantisation steps must be positive")
        if not (np.isfinite(mean).all() and np.isfinite(basis).all()):
            raise reader.fail("non-finite feature transform")
        return cls(tuple(position), feature_step, mean, basis)


def quantise(points: np.ndarray, features: np.ndarray, grid: CellGrid, quantiser: Quantiser) -> QuantisedEmbedding:
    """Embedding (M, 3) metres tile-local + (M, D) features -> its q lattice representation."""
    cells, coords = grid.cell_index(points)
    offsets = np.round((np.asarray(points, dtype=np.float64) - grid.centres(coords)) / np.asarray(quantiser.position_m))
    offsets, lattice = offsets.astype(np.int64), quantiser.features_to_lattice(features)
    order = np.lexsort(np.column_stack([cells, offsets, lattice])[:, ::-1].T)
    return QuantisedEmbedding(cells[order], offsets[order], lattice[order])


def dequantise(q: QuantisedEmbedding, grid: CellGrid, quantiser: Quantiser) -> tuple[np.ndarray, np.ndarray]:
    """q lattice -> (points (M, 3) float32 metres tile-local, features (M, D) float32)."""
    points = grid.centres(grid.cell_coords(q.cells)) + q.offsets * np.asarray(quantiser.position_m)
    return points.astype(np.float32), quantiser.lattice_to_features(q.features)


def _cell_gaps(cells: np.ndarray) -> np.ndarray:
    """Gaps between consecutive sorted cell indices, the first from -1 (so every gap of a unique cell is >= 1)."""
    return np.diff(cells, prepend=-1)


@dataclass(frozen=True)
class QuantModel:
    """Everything q decoding needs beyond a tile's payload: the grid, the quantiser and the fitted histograms."""

    grid: CellGrid
    quantiser: Quantiser
    gaps: Histogram
    offsets: tuple[Histogram, Histogram]  # x and y offsets share one (the grid is the same along them), z
    features: tuple[Histogram, ...]

    @classmethod
    def fit(cls, tiles: list[QuantisedEmbedding], grid: CellGrid, quantiser: Quantiser) -> "QuantModel":
        """Histograms fitted to all tiles of a map at once (their cost is paid once, in the header); each one's
        values gathered from the tiles in turn (memory: one channel of the map, not all of them at once)."""

        def channel(values_of, empty_shape=(0,)) -> np.ndarray:
            return np.concatenate([values_of(t) for t in tiles] or [np.zeros(empty_shape, np.int64)])

        return cls(grid, quantiser, fit_gap_buckets(channel(lambda t: _cell_gaps(t.cells))),
                   (Histogram.fit(channel(lambda t: t.offsets[:, :2], (0, 2))),
                    Histogram.fit(channel(lambda t: t.offsets[:, 2]))),
                   tuple(Histogram.fit(channel(lambda t, c=c: t.features[:, c]))
                         for c in range(len(quantiser.feature_mean))))

    def write(self, writer: ByteWriter, compact: bool = True) -> None:
        self.quantiser.write(writer, compact)
        for histogram in (self.gaps, *self.offsets, *self.features):
            histogram.write(writer)

    @classmethod
    def read(cls, reader: ByteReader, grid: CellGrid, dim: int | None = None) -> "QuantModel":
        """What `write` wrote: `dim` given for the compact form (see `Quantiser.read`)."""
        quantiser = Quantiser.read(reader, dim)
        gaps = Histogram.read(reader)
        offsets = (Histogram.read(reader), Histogram.read(reader))
        features = tuple(Histogram.read(reader) for _ in range(len(quantiser.feature_mean)))
        return cls(grid, quantiser, gaps, offsets, features)

    def _offset_histograms(self) -> tuple[Histogram, Histogram, Histogram]:
        return self.offsets[0], self.offsets[0], self.offsets[1]

    def encode(self, q: QuantisedEmbedding) -> bytes:
        """One tile's payload: varint M, then the ANS stream of cell gaps, offsets and features."""
        symbols = SymbolWriter()
        encode_gaps(symbols, _cell_gaps(q.cells), self.gaps)
        for axis, histogram in enumerate(self._offset_histograms()):
            symbols.histogram(q.offsets[:, axis], histogram)
        for channel, histogram in enumerate(self.features):
            symbols.histogram(q.features[:, channel], histogram)
        writer = ByteWriter()
        writer.varint(len(q))
        writer.raw(symbols.getvalue())
        return writer.getvalue()

    def decode(self, payload: bytes, max_points: int, what: str) -> QuantisedEmbedding:
        reader = ByteReader(payload, what)
        count = reader.varint(limit=max_points + 1)
        symbols = SymbolReader(reader.raw(reader.remaining), what)
        cells = np.cumsum(decode_gaps(symbols, count, self.gaps)) - 1
        offsets = np.stack([symbols.histogram(h, count) for h in self._offset_histograms()], axis=1)
        features = np.stack([symbols.histogram(h, count) for h in self.features], axis=1)
        symbols.finish()
        if count and not (cells[0] >= 0 and cells[-1] < self.grid.n_cells):
            raise reader.fail("embedding cell outside the tile grid")
        return QuantisedEmbedding(cells, offsets, features)
