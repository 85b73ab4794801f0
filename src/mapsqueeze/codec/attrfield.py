"""Values on a voxel support, coded coarse to fine: the predictive levels-of-detail coding of attribute streams.

The support is a tile's set of occupied voxels (sorted Morton codes), known to encoder and decoder alike, so no
positions are coded. Levels of detail: a voxel belongs to level l when it is the first voxel (in Morton order) of
its cell of edge 2^l voxels but not of its cell of edge 2^(l+1); level 0 holds the voxels that share their 2x2x2
cell with an earlier one (about three quarters of a surface's voxels). Levels are coded from the coarsest down, each
in Morton order; every voxel is predicted from its PREDICTORS nearest voxels of the coarser levels (already
decoded), with integer weights 2^20 // squared distance (in voxel units):
- integers (quantised continuous values): prediction = the weighted mean, rounded down; the residual
  value - prediction is coded with one histogram per level group (level 0, level 1, coarser);
- categories (palette indices, K of them): prediction = the category of largest total weight (the smallest index on
  ties); the symbol (index - prediction) mod K is coded with one histogram for voxels whose predictors all agree and
  one for the others.
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from mapsqueeze.codec.entropy import ByteReader, ByteWriter, Histogram, SymbolReader, SymbolWriter, bit_length
from mapsqueeze.codec.rawtile import axis_bits
from mapsqueeze.geometry.morton import morton_cells, morton_codes

PREDICTORS = 3
"""Coarser-level voxels each voxel is predicted from."""
_WEIGHT_ONE = 1 << 20
_LEVEL_GROUPS = 3  # residual histograms of integer values: level 0, level 1, levels >= 2


def support_voxels(points_local: np.ndarray, tile_size: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique Morton codes of the voxels (edge voxel_m, tile frame) holding the points, and each point's
    position in them."""
    bits = axis_bits(tile_size, voxel_m)
    cells = np.clip(np.floor(np.asarray(points_local, dtype=np.float64) / voxel_m), 0, 2**bits - 1)
    return np.unique(morton_codes(cells.astype(np.int64), bits), return_inverse=True)


class LevelsOfDetail:
    """The coding order of a support and every voxel's predictors (computed identically by encoder and decoder).

    order: voxel indices (into the sorted codes) in coding order; starts: the first coding position of each level
    (coarsest first, plus the end); neighbours / weights: (V, PREDICTORS) coding positions of each voxel's predictors
    and their integer weights (weight 0 pads voxels with fewer predictors; the first voxel has none).
    """

    def __init__(self, codes: np.ndarray):
        codes = np.asarray(codes, dtype=np.int64)
        n = len(codes)
        changed = np.concatenate([[np.int64(1) << 62], codes[1:] ^ codes[:-1]]) if n else codes
        level = (bit_length(changed) - 1) // 3
        self.order = np.lexsort((np.arange(n), -level))
        self.levels = level[self.order]
        boundaries = np.flatnonzero(np.diff(self.levels)) + 1
        self.starts = np.concatenate([[0], boundaries, [n]]).astype(np.int64)
        cells = morton_cells(codes[self.order]).astype(np.float64)
        self.neighbours = np.zeros((n, PREDICTORS), dtype=np.int64)
        self.weights = np.zeros((n, PREDICTORS), dtype=np.int64)
        for start, end in zip(self.starts[1:-1], self.starts[2:]):
            k = min(PREDICTORS, int(start))
            distance, index = KDTree(cells[:start]).query(cells[start:end], k=k)
            distance, index = distance.reshape(end - start, k), index.reshape(end - start, k).astype(np.int64)
            squared = np.maximum(np.rint(distance * distance).astype(np.int64), 1)
            self.neighbours[start:end, :k] = index
            self.weights[start:end, :k] = _WEIGHT_ONE // squared

    def __len__(self) -> int:
        return len(self.order)

    def blocks(self):
        """(start, end, level group) of each level in coding order."""
        for start, end in zip(self.starts[:-1], self.starts[1:]):
            yield int(start), int(end), min(int(self.levels[start]), _LEVEL_GROUPS - 1)

    def predict_integers(self, values: np.ndarray, start: int, end: int) -> np.ndarray:
        """Weighted mean (rounded down) of the predictors' values (coding order) for positions start..end."""
        weights = self.weights[start:end]
        total = weights.sum(axis=1)
        weighted = (weights * values[self.neighbours[start:end]]).sum(axis=1)
        return np.where(total > 0, (weighted + total // 2) // np.maximum(total, 1), 0)

    def predict_categories(self, values: np.ndarray, start: int, end: int) -> tuple[np.ndarray, np.ndarray]:
        """(predicted category, whether every predictor agrees) for positions start..end (coding order)."""
        weights = self.weights[start:end]
        labels = values[self.neighbours[start:end]]
        score = ((labels[:, :, None] == labels[:, None, :]) * weights[:, None, :]).sum(axis=2)
        score = np.where(weights > 0, score * (1 << 21) - labels, np.iinfo(np.int64).min)
        prediction = labels[np.arange(end - start), score.argmax(axis=1)]
        agree = ((labels == labels[:, :1]) | (weights == 0)).all(axis=1)
        return np.where(weights[:, 0] > 0, prediction, 0), agree


def encode_integers(writer: ByteWriter, symbols: SymbolWriter, lod: LevelsOfDetail, values: np.ndarray) -> None:
    """Integer values (one per voxel, Morton order): histograms to `writer`, residuals to `symbols`."""
    ordered = np.asarray(values, dtype=np.int64)[lod.order]
    residuals = [(block, ordered[block[0]:block[1]] - lod.predict_integers(ordered, *block[:2]))
                 for block in lod.blocks()]
    histograms = [Histogram.fit(np.concatenate([r for (_, _, g), r in residuals if g == group] or [[0]]))
                  for group in range(_LEVEL_GROUPS)]
    for histogram in histograms:
        histogram.write(writer)
    for (_, _, group), residual in residuals:
        symbols.histogram(residual, histograms[group])


def read_integer_tables(reader: ByteReader) -> list[Histogram]:
    return [Histogram.read(reader) for _ in range(_LEVEL_GROUPS)]


def decode_integers(symbols: SymbolReader, lod: LevelsOfDetail, histograms: list[Histogram]) -> np.ndarray:
    """The integer values (Morton order) `encode_integers` coded."""
    ordered = np.zeros(len(lod), dtype=np.int64)
    for start, end, group in lod.blocks():
        ordered[start:end] = lod.predict_integers(ordered, start, end) + symbols.histogram(histograms[group],
                                                                                           end - start)
    values = np.empty_like(ordered)
    values[lod.order] = ordered
    return values


def encode_categories(writer: ByteWriter, symbols: SymbolWriter, lod: LevelsOfDetail, values: np.ndarray,
                      n_categories: int) -> None:
    """Category indices 0 .. n_categories - 1 (one per voxel, Morton order): the two histograms to `writer`, the
    symbols to `symbols`."""
    ordered = np.asarray(values, dtype=np.int64)[lod.order]
    coded = []
    for start, end, _ in lod.blocks():
        prediction, agree = lod.predict_categories(ordered, start, end)
        symbol = (ordered[start:end] - prediction) % n_categories
        coded.append((symbol[agree], symbol[~agree]))
    histograms = [Histogram.fit(np.concatenate([c[context] for c in coded])) for context in (0, 1)]
    for histogram in histograms:
        histogram.write(writer)
    for pair in coded:
        for context in (0, 1):
            symbols.histogram(pair[context], histograms[context])


def read_category_tables(reader: ByteReader) -> list[Histogram]:
    return [Histogram.read(reader) for _ in range(2)]


def decode_categories(symbols: SymbolReader, lod: LevelsOfDetail, histograms: list[Histogram],
                      n_categories: int) -> np.ndarray:
    """The category indices (Morton order) `encode_categories` coded; ValueError when one is out of range."""
    ordered = np.zeros(len(lod), dtype=np.int64)
    for start, end, _ in lod.blocks():
        prediction, agree = lod.predict_categories(ordered, start, end)
        symbol = np.empty(end - start, dtype=np.int64)
        symbol[agree] = symbols.histogram(histograms[0], int(agree.sum()))
        symbol[~agree] = symbols.histogram(histograms[1], int((~agree).sum()))
        if len(symbol) and (symbol.min() < 0 or symbol.max() >= n_categories):
            raise ValueError("category symbol out of range")
        ordered[start:end] = (prediction + symbol) % n_categories
    values = np.empty_like(ordered)
    values[lod.order] = ordered
    return values

