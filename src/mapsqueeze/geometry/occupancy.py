"""The occupancy-grid IoU (as `metrics.iou`) of several decodes of one tile against its points at once: one dense
grid of the voxels marked by a compiled kernel (no sort, no float64 copies), for the encoder's choice of a decode
post-filter."""

from __future__ import annotations

import numpy as np

from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.jit import compiled


_MAX_OCCUPANCY_VOXELS = 1 << 26
"""Largest voxel box `occupancy_ious` holds as a dense occupancy grid (64 MB; a 40 x 40 x 15 m tile spans 6M
voxels)."""


def occupancy_ious(original: np.ndarray, clouds: list[np.ndarray], frame_m: np.ndarray,
                   voxel_m: tuple[float, float, float]) -> list[float] | None:
    """`metrics.iou(original, cloud + frame_m, voxel_m)` of each of at most 7 float32 tile-local clouds (original:
    world metres; voxels floor(p / voxel_m), metres), on one dense occupancy grid (bit 0 the original, bit i + 1
    cloud i); None when their box holds more than _MAX_OCCUPANCY_VOXELS voxels."""
    frame_m = np.asarray(frame_m, dtype=np.float64)
    voxel = np.asarray(voxel_m, dtype=np.float64)
    corners = list(bounding_box(original))
    corners += [corner.astype(np.float64) + frame_m for cloud in clouds if len(cloud) for corner in bounding_box(cloud)]
    low = np.floor(np.min(corners, axis=0) / voxel).astype(np.int64)
    shape = np.floor(np.max(corners, axis=0) / voxel).astype(np.int64) - low + 1
    if np.prod(shape.astype(np.float64)) > _MAX_OCCUPANCY_VOXELS:
        return None
    grid = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    _mark_voxels(np.ascontiguousarray(original, dtype=np.float64), np.zeros(3), voxel, low, shape, 1, grid)
    for bit, cloud in enumerate(clouds, start=1):
        _mark_voxels(np.ascontiguousarray(cloud), frame_m, voxel, low, shape, 1 << bit, grid)
    counts = np.zeros(256, dtype=np.int64)
    _count_values(grid, counts)
    values = np.arange(256)
    shared = [counts[values & values >> bit & 1 == 1].sum() for bit in range(1, len(clouds) + 1)]
    either = [counts[(values | values >> bit) & 1 == 1].sum() for bit in range(1, len(clouds) + 1)]
    return [float(common / max(1, union)) for common, union in zip(shared, either)]


@compiled
def _count_values(grid, counts):
    for value in grid:
        counts[value] += 1


@compiled
def _mark_voxels(points, frame, voxel, low, shape, bit, grid):
    """Set `bit` in the grid cell of each point's IoU voxel floor((point + frame) / voxel) (as `voxel_indices`)."""
    for i in range(points.shape[0]):
        x = np.int64(np.floor((np.float64(points[i, 0]) + frame[0]) / voxel[0])) - low[0]
        y = np.int64(np.floor((np.float64(points[i, 1]) + frame[1]) / voxel[1])) - low[1]
        z = np.int64(np.floor((np.float64(points[i, 2]) + frame[2]) / voxel[2])) - low[2]
        grid[(x * shape[1] + y) * shape[2] + z] |= bit
