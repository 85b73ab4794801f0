"""Latent codecs: how the embeddings (points + features) of a map's network tiles become payloads and back.

One class per precision (the header's precision byte names it, `LATENT_CODECS`), behind one interface:
`fit` makes the codec for a map's embeddings (q fits its map-wide quantiser and histograms there), `write` / `read`
put its map-wide state into / out of the header, `encode` / `decode` code one tile. A new precision or entropy
model is one class registered here; the container, compressor and decompressor do not change.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from mapsqueeze.codec.embedding import (
    DEFAULT_FEATURE_STEP_STD,
    DEFAULT_POSITION_STEP_MAX_M,
    DEFAULT_POSITION_STEP_RS,
    CellGrid,
    Precision,
    QuantModel,
    Quantiser,
    dequantise,
    quantise,
)
from mapsqueeze.codec.entropy import ByteReader, ByteWriter

Embedding = tuple[np.ndarray, np.ndarray]
"""(points (M, 3) float32 metres tile-local, features (M, D) float32) of one tile."""


@dataclass(frozen=True)
class LatentLayout:
    """What every latent codec knows from the header: the model's grid r_s, the tile size and the feature count."""

    subsampling_dist_m: float
    tile_size: tuple[float, float, float]
    n_features: int


class LatentCodec(ABC):
    """Codes the embeddings of one map's network tiles at one precision."""

    precision: ClassVar[Precision]

    def __init__(self, layout: LatentLayout):
        self.layout = layout

    @classmethod
    def fit(cls, embeddings: Sequence[Embedding], layout: LatentLayout, *, position_step_m: float | None = None,
            feature_step_std: float = DEFAULT_FEATURE_STEP_STD) -> LatentCodec:
        """The codec for a map whose network tiles have these embeddings (the q steps matter to q only)."""
        return cls(layout)

    def refit(self, embeddings: Sequence[Embedding]) -> LatentCodec:
        """The codec for a subset of the map's embeddings with the same quantisation, so the same decoded points
        (q: histograms refitted, quantiser kept); a stateless codec returns itself."""
        return self

    def write(self, writer: ByteWriter, compact: bool = True) -> None:
        """Append the codec's map-wide state to the header (nothing for a stateless codec); compact: the form of
        format version 7 (fields the layout gives left out), else that of versions 1 to 6."""

    @classmethod
    def read(cls, reader: ByteReader, layout: LatentLayout, compact: bool = True) -> LatentCodec:
        """The codec whose state `write` put at the reader's position."""
        return cls(layout)

    @abstractmethod
    def encode(self, points: np.ndarray, features: np.ndarray) -> bytes:
        """One tile's payload."""

    @abstractmethod
    def decode(self, payload: bytes, max_points: int, what: str) -> Embedding:
        """One tile's embedding; ContainerError naming `what` when the payload is corrupt or holds > max_points."""


class _FloatCodec(LatentCodec):
    """varint M, then M rows of (x, y, z, features) little-endian floats; positions divided by `position_unit`."""

    dtype: ClassVar[np.dtype]

    def _position_unit(self) -> np.ndarray:
        return np.ones(3)

    def encode(self, points: np.ndarray, features: np.ndarray) -> bytes:
        writer = ByteWriter()
        writer.varint(len(points))
        rows = np.column_stack([np.asarray(points, np.float64) / self._position_unit(), features]).astype(self.dtype)
        writer.raw(rows.tobytes())
        return writer.getvalue()

    def decode(self, payload: bytes, max_points: int, what: str) -> Embedding:
        reader = ByteReader(payload, what)
        count = reader.varint(limit=max_points + 1)
        width = 3 + self.layout.n_features
        rows = np.frombuffer(reader.raw(count * width * self.dtype.itemsize), dtype=self.dtype)
        reader.expect_end()
        rows = rows.reshape(count, width).astype(np.float32)
        if not np.isfinite(rows).all():
            raise reader.fail("non-finite embedding value")
        points = (rows[:, :3] * self._position_unit()).astype(np.float32)
        return np.ascontiguousarray(points), np.ascontiguousarray(rows[:, 3:])


class Float32Codec(_FloatCodec):
    """f32: raw little-endian float32, 24 bytes per embedding point (3-D features)."""

    precision = Precision.f32
    dtype = np.dtype("<f4")


class Float16Codec(_FloatCodec):
    """f16: the paper's float16 storage, 12 bytes per point; positions as fractions of the tile size, which float16
    resolves to 1-2 cm (metres in float16 would only resolve 3 cm near 40 m)."""

    precision = Precision.f16
    dtype = np.dtype("<f2")

    def _position_unit(self) -> np.ndarray:
        return np.asarray(self.layout.tile_size, dtype=np.float64)


class QuantisedCodec(LatentCodec):
    """q: cells of the r_s grid plus quantised offsets and PCA-turned features, entropy coded with histograms
    fitted once per map (`embedding.QuantModel`, stored in the header)."""

    precision = Precision.q

    def __init__(self, layout: LatentLayout, model: QuantModel):
        super().__init__(layout)
        self.model = model

    @staticmethod
    def grid(layout: LatentLayout) -> CellGrid:
        return CellGrid(layout.subsampling_dist_m, tuple(layout.tile_size))

    @classmethod
    def fit(cls, embeddings: Sequence[Embedding], layout: LatentLayout, *, position_step_m: float | None = None,
            feature_step_std: float = DEFAULT_FEATURE_STEP_STD) -> QuantisedCodec:
        """A map-wide quantiser (position step default: DEFAULT_POSITION_STEP_RS x r_s, at most
        DEFAULT_POSITION_STEP_MAX_M) and histograms."""
        if position_step_m is None:
            position_step_m = min(DEFAULT_POSITION_STEP_RS * layout.subsampling_dist_m, DEFAULT_POSITION_STEP_MAX_M)
        quantiser = Quantiser.fit(np.concatenate([f for _, f in embeddings]
                                                 or [np.zeros((0, layout.n_features), np.float32)]),
                                  position_step_m, feature_step_std)
        grid = cls.grid(layout)
        return cls(layout, QuantModel.fit(_quantised(embeddings, grid, quantiser), grid, quantiser))

    def refit(self, embeddings: Sequence[Embedding]) -> QuantisedCodec:
        """Histograms refitted over these embeddings with the same grid and quantiser."""
        grid, quantiser = self.model.grid, self.model.quantiser
        return QuantisedCodec(self.layout, QuantModel.fit(_quantised(embeddings, grid, quantiser), grid, quantiser))

    def write(self, writer: ByteWriter, compact: bool = True) -> None:
        self.model.write(writer, compact)

    @classmethod
    def read(cls, reader: ByteReader, layout: LatentLayout, compact: bool = True) -> QuantisedCodec:
        model = QuantModel.read(reader, cls.grid(layout), layout.n_features if compact else None)
        if len(model.features) != layout.n_features:
            raise reader.fail("quantiser channel count differs from the embedding's")
        return cls(layout, model)

    def encode(self, points: np.ndarray, features: np.ndarray) -> bytes:
        return self.model.encode(quantise(points, features, self.model.grid, self.model.quantiser))

    def decode(self, payload: bytes, max_points: int, what: str) -> Embedding:
        return dequantise(self.model.decode(payload, max_points, what), self.model.grid, self.model.quantiser)


def _quantised(embeddings: Sequence[Embedding], grid: CellGrid, quantiser: Quantiser) -> list:
    """Every embedding on the q lattice, compact (`QuantisedEmbedding.compact`: a map-wide fit holds them all)."""
    return [quantise(points, features, grid, quantiser).compact() for points, features in embeddings]


LATENT_CODECS: dict[Precision, type[LatentCodec]] = {
    codec.precision: codec for codec in (Float32Codec, Float16Codec, QuantisedCodec)
}
"""The latent codec of each precision byte."""
