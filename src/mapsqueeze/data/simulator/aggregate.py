"""Aggregation of simulated scans with their per-point attributes into one voxel-filtered map.

The geometry is exactly `mapping.aggregate_map`'s (2-20 m range filter, 10 cm centroid voxel filter on the
world grid); each voxel's attributes come from the same points: the mean intensity and the most frequent
(label, instance) pair.
"""

from collections.abc import Iterable

import numpy as np

from mapsqueeze.data.mapping import VOXEL_SIZE_M, range_mask, transform
from mapsqueeze.geometry.voxel import VoxelAccumulator, pack_indices, voxel_indices

_AXIS_BITS = 21
_Run = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]  # voxel keys, (label, instance) pairs, sums, counts


class LabelledVoxels:
    """Per-voxel attributes of points that arrive scan by scan, on the world-anchored grid of
    `geometry.voxel.VoxelAccumulator` (the same voxels, in the same order as its centroids)."""

    def __init__(self, voxel_size: float = VOXEL_SIZE_M):
        self.voxel_size = voxel_size
        self._base: np.ndarray | None = None
        self._runs: list[_Run] = []

    def add(self, points: np.ndarray, intensity: np.ndarray, label: np.ndarray, instance: np.ndarray) -> None:
        """Add (N, 3) world points (metres) with their intensity, label and instance id (uint16 each)."""
        if len(points) == 0:
            return
        indices = voxel_indices(points, self.voxel_size)
        if self._base is None:
            self._base = indices.min(axis=0) - (1 << (_AXIS_BITS - 1))
        keys = pack_indices(indices, self._base, _AXIS_BITS)
        pairs = (np.asarray(label, dtype=np.int64) << 16) | np.asarray(instance, dtype=np.int64)
        self._runs.append(_reduce(keys, pairs, np.asarray(intensity, dtype=np.float64), np.ones(len(keys), np.int64)))
        while len(self._runs) >= 2 and len(self._runs[-1][0]) >= len(self._runs[-2][0]):
            last = self._runs.pop()
            self._runs[-1] = _reduce(*(np.concatenate(pair) for pair in zip(self._runs[-1], last)))

    def values(self) -> dict[str, np.ndarray]:
        """Per voxel, sorted by voxel index: `intensity` (float32 mean), `label` and `instance` (uint16, the most
        frequent pair; the smallest pair on ties)."""
        while len(self._runs) >= 2:
            last = self._runs.pop()
            self._runs[-1] = _reduce(*(np.concatenate(pair) for pair in zip(self._runs[-1], last)))
        if not self._runs:
            return {"intensity": np.empty(0, np.float32), "label": np.empty(0, np.uint16),
                    "instance": np.empty(0, np.uint16)}
        keys, pairs, sums, counts = self._runs[0]
        starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
        voxel = np.cumsum(np.r_[True, keys[1:] != keys[:-1]]) - 1
        mean = np.add.reduceat(sums, starts) / np.add.reduceat(counts, starts)
        best = pairs[np.lexsort((pairs, -counts, voxel))[starts]]
        return {"intensity": mean.astype(np.float32), "label": (best >> 16).astype(np.uint16),
                "instance": (best & 0xFFFF).astype(np.uint16)}


def _reduce(keys: np.ndarray, pairs: np.ndarray, sums: np.ndarray, counts: np.ndarray) -> _Run:
    """Add up intensity sums and counts per (voxel key, pair): the rows sorted by key, then pair."""
    order = np.lexsort((pairs, keys))
    keys, pairs = keys[order], pairs[order]
    starts = np.flatnonzero(np.r_[True, (keys[1:] != keys[:-1]) | (pairs[1:] != pairs[:-1])])
    return keys[starts], pairs[starts], np.add.reduceat(sums[order], starts), np.add.reduceat(counts[order], starts)


def aggregate_labelled_map(scans: Iterable[tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]]
                           ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(world map (M, 3) float64 = `mapping.aggregate_map` of the same scans, its attributes (name -> (M,)))
    from (sensor-frame points (N, 3), their intensity / label / instance, sensor-to-world pose) triples."""
    geometry, attributes = VoxelAccumulator(VOXEL_SIZE_M), LabelledVoxels(VOXEL_SIZE_M)
    for points, values, pose in scans:
        keep = range_mask(points)
        world = transform(points[keep], pose)
        geometry.add(world)
        attributes.add(world, values["intensity"][keep], values["label"][keep], values["instance"][keep])
    return geometry.centroids(), attributes.values()
