"""Surface normals by PCA of radius neighbourhoods, as the paper precomputes them for D_perp (Sec. IV-A).

The normal of a point is the eigenvector of the smallest eigenvalue of the covariance of all points within `radius`
metres of it (the point included). Its sign is arbitrary: D_perp uses |n . d|.

The neighbourhoods are exactly the paper's (no cap). Each point's neighbours are counted first
(`cKDTree.query_ball_point(return_length=True)`, which stores none). Where the cloud has at most PAIRS_AT_ONCE
neighbour pairs, all are found at once with `cKDTree.query_pairs` (each unordered pair once, 16 bytes a pair: ~1 kB
per point for a map voxel-filtered at 10 cm as in the paper, ~100 neighbours within 0.5 m); a denser cloud (an
unfiltered scan, repeated points) is taken in blocks of consecutive points whose neighbour lists together hold at
most a quarter of PAIRS_AT_ONCE entries (or one point's), so memory stays bounded by the larger of that and the
densest single neighbourhood. Covariances are accumulated from the offsets with `np.bincount` and solved with one
batched `np.linalg.eigh`.
"""

from __future__ import annotations

from itertools import chain
from typing import TYPE_CHECKING

import numpy as np

from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.geometry.validation import validate_points

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

NORMAL_RADIUS_M = 0.5
"""Neighbourhood radius of the paper's normals (50 cm)."""

MIN_NEIGHBOURHOOD = 3
"""Fewest points (the point included) a radius neighbourhood needs to define a plane."""

FALLBACK_NEIGHBOURHOOD = 5
"""A point with fewer than MIN_NEIGHBOURHOOD points within the radius uses its this-many nearest points."""

_PAIRS_PER_CHUNK = 1 << 20  # bounds the temporaries of the covariance accumulation (~50 MB)
PAIRS_AT_ONCE = 1 << 24
"""Most neighbour pairs held in memory at once (16 bytes each: 256 MB)."""


def normals_pca(points: np.ndarray, radius: float = NORMAL_RADIUS_M, tree: cKDTree | None = None) -> np.ndarray:
    """(N, 3) unit normals of `points` ((N, 3) float64, metres) from the covariance of each radius neighbourhood.

    Fallback: an isolated point (fewer than 3 points within `radius`, itself included) takes the normal of its
    FALLBACK_NEIGHBOURHOOD nearest points (itself included; all points when the cloud is smaller), whatever
    their distance. Every point thus gets a finite normal and keeps its term in D_perp, which stays bounded by
    the Euclidean distance of that term (|n . d| <= |d|); no point is silently dropped from the mean.
    `tree`: a cKDTree already built on `points`, to reuse it.
    """
    points = validate_points(points, "points")
    if not radius > 0:
        raise MapsqueezeError(f"normal radius must be positive (metres), got {radius!r}")
    if tree is None:
        from scipy.spatial import cKDTree  # imported here: the command line starts without scipy

        tree = cKDTree(points)
    counts, sums, products = _neighbourhood_moments(points, tree, radius)
    isolated = np.flatnonzero(counts < MIN_NEIGHBOURHOOD)
    if len(isolated):
        counts[isolated], sums[isolated], products[isolated] = _nearest_moments(points, tree, isolated)
    mean = sums / counts[:, None]
    covariance = products / counts[:, None, None] - mean[:, :, None] * mean[:, None, :]
    return np.linalg.eigh(covariance)[1][:, :, 0]


def _neighbourhood_moments(
    points: np.ndarray, tree: cKDTree, radius: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point: neighbour count, sum of offsets d and sum of d d^T, with d = neighbour - point (radius balls).

    Offsets are relative to the query point (|d| <= radius), so no precision is lost for large world
    coordinates. A pair (i, j) adds d to i and -d to j, and the same outer product d d^T to both.
    """
    n = len(points)
    coordinates = np.ascontiguousarray(points.T)  # (3, N): contiguous rows make np.take and bincount fast
    sums = np.zeros((3, n))
    products = np.zeros((3, 3, n))
    lengths = tree.query_ball_point(points, radius, return_length=True, workers=-1).astype(np.int64)
    pair_count = (int(lengths.sum()) - n) // 2
    if pair_count <= PAIRS_AT_ONCE:
        pairs = tree.query_pairs(radius, output_type="ndarray")
        counts = 1 + np.bincount(pairs.ravel(), minlength=n)
        for start in range(0, len(pairs), _PAIRS_PER_CHUNK):
            chunk = pairs[start : start + _PAIRS_PER_CHUNK]
            _accumulate(coordinates, np.ascontiguousarray(chunk[:, 0]), np.ascontiguousarray(chunk[:, 1]), sums,
                        products, both=True)
    else:
        counts = lengths
        ends = np.cumsum(lengths)  # blocks of points whose lists hold at most PAIRS_AT_ONCE / 4 entries (one point
        start = 0                  # at least): a list entry takes ~36 bytes, an array pair 16
        while start < n:
            stop = max(start + 1, int(np.searchsorted(ends, ends[start] - lengths[start] + PAIRS_AT_ONCE // 4,
                                                      side="right")))
            lists = tree.query_ball_point(points[start:stop], radius, workers=-1, return_sorted=False)
            first = np.repeat(np.arange(start, stop), lengths[start:stop])
            second = np.fromiter(chain.from_iterable(lists), dtype=np.int64, count=int(lengths[start:stop].sum()))
            del lists
            start = stop
            for part in range(0, len(first), _PAIRS_PER_CHUNK):
                chosen = slice(part, part + _PAIRS_PER_CHUNK)
                _accumulate(coordinates, first[chosen], second[chosen], sums, products, both=False)
    for a, b in ((1, 0), (2, 0), (2, 1)):
        products[a, b] = products[b, a]
    return counts, sums.T, np.moveaxis(products, -1, 0)


def _accumulate(coordinates: np.ndarray, first: np.ndarray, second: np.ndarray, sums: np.ndarray,
                products: np.ndarray, both: bool) -> None:
    """Add the offsets d = second - first to the sums of point `first` (and, with `both`, -d to those of `second`,
    each unordered pair given once) and d d^T to the products of the same points."""
    n = sums.shape[1]
    offsets = np.take(coordinates, second, axis=1) - np.take(coordinates, first, axis=1)
    for a in range(3):
        sums[a] += np.bincount(first, offsets[a], n) - (np.bincount(second, offsets[a], n) if both else 0)
        for b in range(a, 3):
            outer = offsets[a] * offsets[b]
            products[a, b] += np.bincount(first, outer, n) + (np.bincount(second, outer, n) if both else 0)


def _nearest_moments(
    points: np.ndarray, tree: cKDTree, which: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The moments of `_neighbourhood_moments` for the points `which`, over their nearest points instead."""
    k = min(FALLBACK_NEIGHBOURHOOD, len(points))
    _, neighbours = tree.query(points[which], k=k, workers=-1)
    offsets = points[neighbours.reshape(len(which), k)] - points[which][:, None, :]
    return np.full(len(which), k), offsets.sum(axis=1), np.einsum("nka,nkb->nab", offsets, offsets)
