"""Surface normals by PCA of radius neighbourhoods, as the paper precomputes them for D_perp (Sec. IV-A).

The normal of a point is the eigenvector of the smallest eigenvalue of the covariance of all points within
`radius` metres of it (the point included). Its sign is arbitrary: D_perp uses |n . d|.

All neighbour pairs are found at once with `cKDTree.query_pairs` (each unordered pair once, no cap, so the
neighbourhoods are exactly the paper's); covariances are accumulated from the pair offsets with `np.bincount`
and solved with one batched `np.linalg.eigh`. Memory is about 16 bytes per neighbour pair: ~1 kB per point for
a map voxel-filtered at 10 cm as in the paper (~100 neighbours within 0.5 m), far more for an unfiltered cloud.
"""

from __future__ import annotations

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
    pairs = tree.query_pairs(radius, output_type="ndarray")
    counts = 1 + np.bincount(pairs.ravel(), minlength=n)
    coordinates = np.ascontiguousarray(points.T)  # (3, N): contiguous rows make np.take and bincount fast
    sums = np.zeros((3, n))
    products = np.zeros((3, 3, n))
    for start in range(0, len(pairs), _PAIRS_PER_CHUNK):
        chunk = pairs[start : start + _PAIRS_PER_CHUNK]
        first, second = np.ascontiguousarray(chunk[:, 0]), np.ascontiguousarray(chunk[:, 1])
        offsets = np.take(coordinates, second, axis=1) - np.take(coordinates, first, axis=1)
        for a in range(3):
            sums[a] += np.bincount(first, offsets[a], n) - np.bincount(second, offsets[a], n)
            for b in range(a, 3):
                outer = offsets[a] * offsets[b]
                products[a, b] += np.bincount(first, outer, n) + np.bincount(second, outer, n)
    for a, b in ((1, 0), (2, 0), (2, 1)):
        products[a, b] = products[b, a]
    return counts, sums.T, np.moveaxis(products, -1, 0)


def _nearest_moments(
    points: np.ndarray, tree: cKDTree, which: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The moments of `_neighbourhood_moments` for the points `which`, over their nearest points instead."""
    k = min(FALLBACK_NEIGHBOURHOOD, len(points))
    _, neighbours = tree.query(points[which], k=k, workers=-1)
    offsets = points[neighbours.reshape(len(which), k)] - points[which][:, None, :]
    return np.full(len(which), k), offsets.sum(axis=1), np.einsum("nka,nkb->nab", offsets, offsets)
