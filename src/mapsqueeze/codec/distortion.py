"""The D_e of a tile's candidate codings (`codec.modes`): estimated on a fixed sample of each cloud's points, and
computed exactly wherever two candidates' estimates are close enough for the estimate to decide between them.

The estimate is eq. 9's symmetric mean over at most SAMPLE_POINTS points of the tile and SAMPLE_POINTS decoded
points (a network tile decodes to ~250k points), their nearest distances searched on grids of cells
(`geometry.nearest`: a k-d tree search's distances in about half its time). The sample is a jittered systematic one: the points cut into SAMPLE_POINTS runs of consecutive indices, one
point drawn from each with a fixed seed (a plain stride aliases with the decoder's children, which come in blocks of
the upsampling factors). Measured on the 484 candidates of the 70 tiles of the real submaps, six KITTI scans and
two KITTI-copy maps (BENCHMARKS.md "Throughput"), 234 of them sampled: relative error at most 1.4 % (0.5 % rms) for
the network's, 0.5 % for the classical ones, so estimates more than CLOSE apart order the candidates as exact
values do.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mapsqueeze.metrics import d_euclidean, nearest_tree

SAMPLE_POINTS = 8192
"""Points of each cloud (the tile's, a candidate's decoded ones) whose nearest-neighbour distances estimate D_e."""

CLOSE = 0.05
"""Estimates whose ratio is within 1 +- CLOSE are replaced by exact D_e (the estimates' error is under 1.5 %)."""

SAMPLE_SEED = 0

TREE_LEAF_POINTS = 64
"""Points per leaf of the tile's k-d tree for exact D_e (pykdtree's default: 16; distances do not depend on it), built
when the first exact value is asked for. The estimates search grids of cells instead (`geometry.nearest`: the same
distances; building one over a decoded network tile, ~250k points, and searching the samples takes about half a
tree's time)."""

OwnDistances = Callable[[np.ndarray], np.ndarray]
"""Tile points (n, 3) -> (n,) distances to their nearest decoded point where known cheaply, NaN elsewhere (the
octree's own-leaf distances, `octreetile.own_leaf_distances`)."""


def sample_indices(n: int, size: int = SAMPLE_POINTS) -> np.ndarray:
    """Ascending int64 indices of min(n, size) of n points: all of them when n <= size, else one drawn (fixed seed)
    from each of `size` runs of consecutive indices of near-equal length."""
    if n <= size:
        return np.arange(n, dtype=np.int64)
    bounds = np.arange(size + 1, dtype=np.int64) * n // size
    offsets = np.random.default_rng(SAMPLE_SEED).random(size) * np.diff(bounds)
    return bounds[:-1] + offsets.astype(np.int64)


def _grid(points: np.ndarray, compiled: bool = True):
    if not compiled:  # the same distances from a k-d tree, without numba (small maps)
        from mapsqueeze.geometry.nearestnumpy import NearestTree

        return NearestTree(points)
    from mapsqueeze.geometry.nearest import NearestGrid  # numba: imported here, the CLI starts without it

    return NearestGrid(points)


class CandidateDistortion:
    """The D_e (metres) of each decoded candidate of one tile against the tile's points: `add` each candidate's
    decoded points, then `settle` gives their D_e in the order added (exact throughout when `exact`). compiled=False
    searches k-d trees instead of the compiled grids (the same distances without numba)."""

    def __init__(self, points: np.ndarray, exact: bool = False, compiled: bool = True):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.exact = exact
        self.compiled = compiled
        self._tree = None
        self._grid = None if exact else _grid(self.points, compiled)
        self._sample = self.points[sample_indices(len(self.points))]
        self._decoded: list[tuple[np.ndarray, OwnDistances | None] | None] = []
        self._values: list[float] = []

    def add(self, decoded: Callable[[], np.ndarray] | np.ndarray, own: OwnDistances | None = None,
            competing: bool = True) -> None:
        """A candidate's decoded (K, 3) points, tile-local like the tile's (or a function giving them); `own` where
        some nearest distances are known without a search. competing=False: the mode decision cannot pick the
        candidate (e.g. larger than the network's payload, `modes.choose`), so its D_e decides nothing: NaN, with
        no search and no decoded points made."""
        if not competing:
            self._decoded.append(None)
            self._values.append(np.nan)
            return
        decoded = decoded() if callable(decoded) else decoded
        self._decoded.append((decoded, own))
        self._values.append(self._exact(decoded, own) if self.exact else self._estimate(decoded, own))

    def settle(self) -> list[float]:
        """Each added candidate's D_e: NaN for those added as not competing; for the others, the estimate, or the
        exact value where another competing candidate's estimate is within CLOSE."""
        values = list(self._values)
        if not self.exact:
            for i, value in enumerate(self._values):
                if self._decoded[i] is not None and any(
                        j != i and self._decoded[j] is not None and abs(value - other) <= CLOSE * min(value, other)
                        for j, other in enumerate(self._values)):
                    values[i] = self._exact(*self._decoded[i])
        return values

    def _exact(self, decoded: np.ndarray, own: OwnDistances | None) -> float:
        if self._tree is None:
            self._tree = nearest_tree(self.points, TREE_LEAF_POINTS)
        return d_euclidean(self.points, decoded, self._tree, None if own is None else own(self.points))

    def _estimate(self, decoded: np.ndarray, own: OwnDistances | None) -> float:
        points = self._sample
        to_decoded = np.full(len(points), np.nan) if own is None else own(points)
        unknown = np.isnan(to_decoded)
        if unknown.any():
            to_decoded[unknown] = _grid(decoded, self.compiled).distances(points[unknown])
        to_tile = self._grid.distances(decoded[sample_indices(len(decoded))])
        return float(to_decoded.mean() / 2 + to_tile.mean() / 2)
