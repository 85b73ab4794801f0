"""Local surface operations on a decoded cloud: PCA planes of k-nearest-neighbour neighbourhoods, projection onto
them, even resampling on small disks of them, and removal of isolated points (the decode post-filter's steps,
`codec.postfilter`). Deterministic: exact neighbour queries, fixed sample pattern, no random numbers."""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

from mapsqueeze.geometry.morton import spread_subset

_CHUNK = 1 << 15
"""Points whose neighbourhood covariances are formed at once (bounds the (chunk, k, 3) temporaries)."""

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))
GOLDEN_FRACTION = (np.sqrt(5.0) - 1.0) / 2.0
"""The disk samples' spiral: sample s at angle s x GOLDEN_ANGLE, radius r sqrt(frac(s x GOLDEN_FRACTION))."""


def _neighbours(tree: KDTree, points: np.ndarray, k: int) -> np.ndarray:
    """(len(points), k) indices of each point's k nearest points in `tree`."""
    _, index = tree.query(points, k=k)
    return np.asarray(index, dtype=np.int64).reshape(len(points), k)


def local_planes(points: np.ndarray, k: int, anchor_every: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """PCA plane of each point's k nearest points ((N, 3) float64 metres): (N, 3) centroids and (N, 3) unit
    normals (eigenvector of the smallest covariance eigenvalue, its largest component made positive).

    anchor_every > 1 fits the planes at every anchor_every-th point along the Morton order (`spread_subset`)
    only, each over its k nearest points of the whole cloud, and gives every point the plane of its nearest
    anchor (anchor_every times fewer neighbour searches and eigenproblems)."""
    tree = KDTree(points)
    k = min(k, len(points))
    anchors = points if anchor_every <= 1 else points[spread_subset(points, -(-len(points) // anchor_every))]
    centroids = np.empty_like(anchors)
    normals = np.empty_like(anchors)
    for start in range(0, len(anchors), _CHUNK):
        neighbourhood = points[_neighbours(tree, anchors[start:start + _CHUNK], k)]
        centre = neighbourhood.mean(axis=1)
        offsets = neighbourhood - centre[:, None, :]
        _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", offsets, offsets))
        normal = vectors[:, :, 0]
        largest = np.abs(normal).argmax(axis=1)
        normal *= np.where(normal[np.arange(len(normal)), largest] < 0, -1.0, 1.0)[:, None]
        centroids[start:start + _CHUNK], normals[start:start + _CHUNK] = centre, normal
    if anchors is points:
        return centroids, normals
    nearest = _neighbours(KDTree(anchors), points, 1)[:, 0]
    return centroids[nearest], normals[nearest]


def project_to_planes(points: np.ndarray, centroids: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Each point moved along its plane's normal onto the plane (removes the spread across a surface)."""
    offset = np.einsum("ij,ij->i", points - centroids, normals)
    return points - offset[:, None] * normals


def _tangents(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning each normal's plane, fixed by the normal alone (no eigenvector signs)."""
    axis = np.zeros_like(normals)
    axis[np.arange(len(normals)), np.abs(normals).argmin(axis=1)] = 1.0
    first = np.cross(normals, axis)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return first, np.cross(normals, first)


def disk_samples(points: np.ndarray, normals: np.ndarray, radius_m: float, copies: int) -> np.ndarray:
    """`copies` extra points per point on the disk of `radius_m` metres around it in its plane, evenly spread over
    the disk area along a golden-angle spiral indexed by point (fills the gaps between decoded clumps):
    (N * copies, 3), the copies of point i at rows i * copies ... i * copies + copies - 1."""
    first, second = _tangents(normals)
    sample = np.arange(len(points) * copies, dtype=np.float64)
    radius = radius_m * np.sqrt((sample * GOLDEN_FRACTION) % 1.0)
    angle = sample * GOLDEN_ANGLE
    owner = np.repeat(np.arange(len(points)), copies)
    return (points[owner] + (radius * np.cos(angle))[:, None] * first[owner]
            + (radius * np.sin(angle))[:, None] * second[owner])


def keep_supported(points: np.ndarray, radius_m: float, min_neighbours: int) -> np.ndarray:
    """Boolean mask of the points with at least `min_neighbours` other points within `radius_m` metres (False
    marks isolated points, which occupy space where the surface is not)."""
    if len(points) <= min_neighbours:
        return np.zeros(len(points), dtype=bool)
    distance, _ = KDTree(points).query(points, k=min_neighbours + 1)
    return np.asarray(distance).reshape(len(points), -1)[:, -1] <= radius_m
