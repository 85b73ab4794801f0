"""Reconstruction metrics of the paper (Wiesmann et al. 2021): Chamfer (eq. 6-7), D_e and D_perp (eq. 9-10),
occupancy IoU (eq. 11) and bits per point.

D_e, D_perp and Chamfer are symmetric: half the mean over the ground-truth points of the distance to their
nearest reconstructed point, plus half the mean the other way round (each direction averaged over its own
cloud). Nearest neighbours are Euclidean in both directions; D_perp measures the offset to the matched point
along the ground-truth normal (PCA over 50 cm, `geometry.normals`): for a ground-truth point its own normal,
for a reconstructed point the normal of its matched ground-truth point.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from mapsqueeze.errors import InvalidPointCloudError, MapsqueezeError
from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.normals import normals_pca
from mapsqueeze.geometry.validation import validate_points

if TYPE_CHECKING:
    from pykdtree.kdtree import KDTree
    from scipy.spatial import cKDTree
from mapsqueeze.geometry.voxel import pack_indices, voxel_indices

IOU_VOXEL_M = (0.2, 0.2, 0.1)
"""Occupancy-grid resolution of the paper's IoU, x, y, z in metres (20 x 20 x 10 cm, after Huang et al.)."""


@dataclass(frozen=True)
class Metrics:
    """All reconstruction metrics of one ground-truth / reconstruction pair."""

    d_e: float
    """Symmetric mean Euclidean nearest-neighbour distance (metres)."""
    d_perp: float
    """Symmetric mean point-to-plane distance along the ground-truth normals (metres)."""
    iou: float
    """Intersection over union of the occupied IOU_VOXEL_M voxels (0..1)."""
    chamfer: float
    """Symmetric mean squared nearest-neighbour distance (square metres)."""
    bpp: float | None
    """Compressed size in bits per ground-truth point; None when the size is not given."""
    n_gt: int
    n_rec: int


@dataclass(frozen=True)
class _Matching:
    """Nearest neighbours both ways: distances (metres) and indices into the other cloud."""

    gt_to_rec_distance: np.ndarray
    gt_to_rec_index: np.ndarray
    rec_to_gt_distance: np.ndarray
    rec_to_gt_index: np.ndarray


def _kdtree(points: np.ndarray) -> cKDTree:
    """scipy's k-d tree of (N, 3) points (scipy is imported here: the command line starts without it)."""
    from scipy.spatial import cKDTree

    return cKDTree(points)


def _match(gt: np.ndarray, rec: np.ndarray, gt_tree: cKDTree) -> _Matching:
    """One cKDTree per cloud, each queried once."""
    gt_to_rec_distance, gt_to_rec_index = _kdtree(rec).query(gt, k=1, workers=-1)
    rec_to_gt_distance, rec_to_gt_index = gt_tree.query(rec, k=1, workers=-1)
    return _Matching(gt_to_rec_distance, gt_to_rec_index, rec_to_gt_distance, rec_to_gt_index)


def _symmetric_mean(gt_terms: np.ndarray, rec_terms: np.ndarray) -> float:
    """Eq. 9: half the mean over the ground-truth points plus half the mean over the reconstructed points."""
    return float(gt_terms.mean() / 2 + rec_terms.mean() / 2)


def _chamfer(matching: _Matching) -> float:
    return _symmetric_mean(matching.gt_to_rec_distance**2, matching.rec_to_gt_distance**2)


def _d_euclidean(matching: _Matching) -> float:
    return _symmetric_mean(matching.gt_to_rec_distance, matching.rec_to_gt_distance)


def _d_point_to_plane(gt: np.ndarray, rec: np.ndarray, gt_normals: np.ndarray, matching: _Matching) -> float:
    gt_offsets = gt - rec[matching.gt_to_rec_index]
    rec_offsets = rec - gt[matching.rec_to_gt_index]
    gt_terms = np.abs(np.einsum("ij,ij->i", gt_offsets, gt_normals))
    rec_terms = np.abs(np.einsum("ij,ij->i", rec_offsets, gt_normals[matching.rec_to_gt_index]))
    return _symmetric_mean(gt_terms, rec_terms)


def _checked_normals(gt_normals: np.ndarray | None, gt: np.ndarray, gt_tree: cKDTree) -> np.ndarray:
    """The given ground-truth normals after a shape/finiteness check, or PCA normals computed on `gt`."""
    if gt_normals is None:
        return normals_pca(gt, tree=gt_tree)
    normals = np.asarray(gt_normals, dtype=np.float64)
    if normals.shape != gt.shape or not np.isfinite(normals).all():
        raise InvalidPointCloudError(
            f"gt_normals: expected {gt.shape} finite values (one normal per ground-truth point), "
            f"got shape {normals.shape}"
        )
    return normals


def nearest_distances(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N,) distance (metres) from each of `points` to its nearest neighbour in `reference` (the terms of D_e)."""
    points, reference = validate_points(points, "points"), validate_points(reference, "reference")
    return _kdtree(reference).query(points, k=1, workers=-1)[0]


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Chamfer distance D_CD (eq. 6-7) in square metres: symmetric mean squared nearest-neighbour distance."""
    a, b = validate_points(a, "a"), validate_points(b, "b")
    return _chamfer(_match(a, b, _kdtree(a)))


def nearest_tree(points: np.ndarray, leaf_points: int = 16) -> KDTree:
    """A k-d tree of (N, 3) float64 points for `d_euclidean`'s `gt_tree` (pykdtree: the distances of scipy's
    cKDTree, faster), with at most `leaf_points` points a leaf (its speed only, not its distances)."""
    from pykdtree.kdtree import KDTree

    return KDTree(np.ascontiguousarray(points, dtype=np.float64), leafsize=leaf_points)


def d_euclidean(gt: np.ndarray, rec: np.ndarray, gt_tree: KDTree | None = None,
                gt_to_rec: np.ndarray | None = None) -> float:
    """D_e (eq. 9-10, d = ||x_i - x_j||_2) in metres: symmetric mean nearest-neighbour distance.

    `gt_tree`: `nearest_tree(gt)`, to reuse it across several reconstructions of the same cloud. `gt_to_rec`: the
    (N_gt,) distances from the gt points to their nearest rec point where the caller knows them (computed as the
    search does: the square root of ((dx^2 + dy^2) + dz^2) in float64), NaN where they are to be searched.
    """
    gt, rec = validate_points(gt, "gt"), validate_points(rec, "rec")
    gt, rec = np.ascontiguousarray(gt), np.ascontiguousarray(rec)
    if gt_to_rec is None:
        gt_to_rec = nearest_tree(rec).query(gt, k=1)[0]
    else:
        unknown = np.isnan(gt_to_rec)
        gt_to_rec = gt_to_rec.copy()
        if unknown.any():
            gt_to_rec[unknown] = nearest_tree(rec).query(gt[unknown], k=1)[0]
    rec_to_gt = (nearest_tree(gt) if gt_tree is None else gt_tree).query(rec, k=1)[0]
    return _symmetric_mean(gt_to_rec, rec_to_gt)


def d_point_to_plane(gt: np.ndarray, rec: np.ndarray, gt_normals: np.ndarray | None = None) -> float:
    """D_perp (eq. 9-10, d = |n^T (x_i - x_j)|) in metres, n the ground-truth normal (see module docstring).

    `gt_normals`: (N_gt, 3) normals of `gt`, to reuse them; by default `normals_pca(gt)` (50 cm radius).
    """
    gt, rec = validate_points(gt, "gt"), validate_points(rec, "rec")
    gt_tree = _kdtree(gt)
    normals = _checked_normals(gt_normals, gt, gt_tree)
    return _d_point_to_plane(gt, rec, normals, _match(gt, rec, gt_tree))


def iou(gt: np.ndarray, rec: np.ndarray, voxel: tuple[float, float, float] = IOU_VOXEL_M) -> float:
    """Occupancy-grid IoU (eq. 11): |G_gt n G_rec| / |G_gt u G_rec| over voxels of size `voxel` (x, y, z metres).

    Both grids are anchored at the world origin (voxel index floor(p / voxel)), so they align and neither
    depends on where the other cloud's points lie.
    """
    return _iou(validate_points(gt, "gt"), validate_points(rec, "rec"), voxel)


def _iou(gt: np.ndarray, rec: np.ndarray, voxel: tuple[float, float, float]) -> float:
    keys = pack_indices(voxel_indices(np.concatenate([gt, rec]), voxel))
    gt_voxels, rec_voxels = np.unique(keys[: len(gt)]), np.unique(keys[len(gt) :])
    shared = len(np.intersect1d(gt_voxels, rec_voxels, assume_unique=True))
    return shared / (len(gt_voxels) + len(rec_voxels) - shared)


def bits_per_point(n_bytes: int, n_gt_points: int) -> float:
    """Compressed size in bits per point of the original (ground-truth) cloud: 8 * n_bytes / n_gt_points."""
    if n_bytes < 0:
        raise MapsqueezeError(f"compressed size must be >= 0 bytes, got {n_bytes}")
    if n_gt_points <= 0:
        raise InvalidPointCloudError(f"bits per point needs at least one ground-truth point, got {n_gt_points}")
    return 8 * n_bytes / n_gt_points


EVALUATION_STAGES = ("normals", "matching", "IoU")
"""The stages `evaluate` reports to its progress callback, in order."""

MAX_D_E_SHARE_OF_EXTENT = 0.1
"""`overlap_warning` flags a D_e above this share of the ground truth's bounding-box diagonal."""
OVERLAP_SLACK_M = 1.0
"""`overlap_warning` calls bounding boxes disjoint when a gap between them is wider than this (metres): a flat
ground truth and its decoding, a few millimetres off its plane, share no volume but plainly overlap."""


def evaluate(
    gt: np.ndarray, rec: np.ndarray, n_bytes: int | None = None, gt_normals: np.ndarray | None = None,
    progress: Callable[[str], None] | None = None,
) -> Metrics:
    """Every metric of reconstruction `rec` against ground truth `gt` ((N, 3) metres); bpp when `n_bytes` given.

    `gt_normals`: (N_gt, 3) normals of `gt`, to reuse them across several reconstructions of the same map.
    `progress(stage)` is called as each of EVALUATION_STAGES starts (a 500k-point pair takes tens of seconds).
    """
    report = progress or (lambda stage: None)
    gt, rec = validate_points(gt, "gt"), validate_points(rec, "rec")
    gt_tree = _kdtree(gt)
    report(EVALUATION_STAGES[0])
    normals = _checked_normals(gt_normals, gt, gt_tree)
    report(EVALUATION_STAGES[1])
    matching = _match(gt, rec, gt_tree)
    d_e, d_perp = _d_euclidean(matching), _d_point_to_plane(gt, rec, normals, matching)
    report(EVALUATION_STAGES[2])
    return Metrics(
        d_e=d_e,
        d_perp=d_perp,
        iou=_iou(gt, rec, IOU_VOXEL_M),
        chamfer=_chamfer(matching),
        bpp=None if n_bytes is None else bits_per_point(n_bytes, len(gt)),
        n_gt=len(gt),
        n_rec=len(rec),
    )


def overlap_warning(gt: np.ndarray, rec: np.ndarray, d_e: float) -> str | None:
    """Why the two clouds look like different places (bounding boxes more than OVERLAP_SLACK_M apart, or D_e above
    MAX_D_E_SHARE_OF_EXTENT of the ground truth's extent, when it has one: another frame or offset?), or None."""
    (gt_low, gt_high), (rec_low, rec_high) = bounding_box(gt), bounding_box(rec)
    if (gt_high + OVERLAP_SLACK_M < rec_low).any() or (rec_high + OVERLAP_SLACK_M < gt_low).any():
        return (f"the clouds do not overlap: ground truth spans {np.round(gt_low, 2).tolist()} .. "
                f"{np.round(gt_high, 2).tolist()}, the reconstruction {np.round(rec_low, 2).tolist()} .. "
                f"{np.round(rec_high, 2).tolist()} (different coordinate frames?)")
    extent = float(np.linalg.norm(gt_high - gt_low))
    if extent > 0 and d_e > MAX_D_E_SHARE_OF_EXTENT * extent:
        return (f"D_e {d_e:.3f} m is more than {MAX_D_E_SHARE_OF_EXTENT:.0%} of the ground truth's extent "
                f"({extent:.1f} m diagonal): the clouds barely overlap (different coordinate frames?)")
    return None


def nearest_original_values(gt: np.ndarray, gt_values: np.ndarray, rec: np.ndarray) -> np.ndarray:
    """For each reconstructed point, the attribute value of its nearest ground-truth point."""
    return np.asarray(gt_values)[_kdtree(gt).query(rec, k=1)[1]]


def attribute_error(gt: np.ndarray, gt_values: np.ndarray, rec: np.ndarray, rec_values: np.ndarray) -> float:
    """Mean |decoded value - value of the nearest ground-truth point| over the reconstructed points (attribute
    units): the attribute error of the issue's benchmark."""
    truth = nearest_original_values(gt, gt_values, rec).astype(np.float64)
    return float(np.abs(np.asarray(rec_values, dtype=np.float64) - truth).mean())


def constant_guess_error(gt: np.ndarray, gt_values: np.ndarray, rec: np.ndarray) -> float:
    """`attribute_error` of the best constant guess (the median of the ground-truth values) at the same points."""
    truth = nearest_original_values(gt, gt_values, rec).astype(np.float64)
    return float(np.abs(np.median(np.asarray(gt_values, dtype=np.float64)) - truth).mean())


def label_accuracy(gt: np.ndarray, gt_labels: np.ndarray, rec: np.ndarray, rec_labels: np.ndarray) -> float:
    """Share of reconstructed points whose label equals their nearest ground-truth point's."""
    return float((np.asarray(rec_labels) == nearest_original_values(gt, gt_labels, rec)).mean())
