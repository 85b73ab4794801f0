"""Encoder-signalled decode post-filter of network tiles (like a video codec's adaptive loop filter).

The decoder's native output gathers in clumps around the embedding points, spread a few centimetres across the
surfaces, with stray points between them: it leaves occupied space empty and fills empty space (the paper's IoU).
The post-filter reworks a decoded tile with local surface operations (`geometry.surface`):
- snap: each point projected onto the PCA plane of its k nearest decoded points;
- spread: extra points on small disks of those planes around each point (fills the gaps between clumps);
- isolated: points with fewer than ISOLATED_MIN_NEIGHBOURS others within ISOLATED_RADIUS_M dropped.
The encoder, which has the tile's points, decodes the tile, tries the settings of CANDIDATES on it, and stores the
one that gives the highest IoU without raising D_e by more than MAX_D_E_INCREASE (one byte per tile, the tile
table's post-filter field, docs/format.md); the decoder applies it. Setting 0 is the paper's decode.

The byte: bits 0-1 snap (0 off, else SNAP_NEIGHBOURS[bits] nearest points), bits 2-3 spread (SPREAD[bits]:
extra points per point and disk radius in metres), bit 4 isolated-point removal; bits 5-7 zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapsqueeze.errors import ContainerError
from mapsqueeze.geometry.surface import disk_samples, keep_supported, local_planes, project_to_planes
from mapsqueeze.metrics import d_euclidean, iou, nearest_tree

OFF = 0
"""The setting that leaves the decoded tile as the network gives it (the paper's decode; files before version 3)."""

SNAP_NEIGHBOURS = (0, 16, 32, 48)
"""Neighbourhood size of the snapping planes per value of bits 0-1 (0: no snapping)."""

SPREAD = ((0, 0.0), (1, 0.05), (1, 0.10), (2, 0.10))
"""(extra points per decoded point, disk radius in metres) per value of bits 2-3."""

ISOLATED_RADIUS_M = 0.2
ISOLATED_MIN_NEIGHBOURS = 4
"""Bit 4 drops the points with fewer than this many other decoded points within ISOLATED_RADIUS_M."""

_ISOLATED_BIT = 1 << 4
_KNOWN_BITS = 0b11111

PLANE_NEIGHBOURS = 48
"""The planes of the spread when it comes without snapping, and the snapping planes of CANDIDATES: each point's 48
nearest decoded points (about a 15-30 cm disk at the decoder's native density)."""

PLANE_ANCHOR_EVERY = 2
"""Planes are fitted at every second decoded point (`local_planes`); the others take their nearest one's: 40 % less
filter time than a plane per point, for about 0.003 less IoU on the real KITTI and Ouster submaps."""


def setting_byte(snap: int = 0, spread: int = 0, isolated: bool = False) -> int:
    """The post-filter byte of field values (snap and spread: indices into SNAP_NEIGHBOURS and SPREAD)."""
    return snap | spread << 2 | (_ISOLATED_BIT if isolated else 0)


CANDIDATES = (
    OFF,
    setting_byte(snap=3, spread=1),
    setting_byte(snap=3, spread=3),
    setting_byte(snap=3, spread=1, isolated=True),
    setting_byte(snap=3, spread=3, isolated=True),
)
"""Settings the encoder tries on each network tile (all share one plane fit): of a grid of 11 settings tried on
the real KITTI and Ouster submaps with e0..e3, those that were the best for some model under the rule of
`choose_post_filter`."""

MAX_D_E_INCREASE = 0.05
"""A setting is chosen only if the tile's D_e stays within this fraction above the unfiltered decode's."""


@dataclass(frozen=True)
class PostFilter:
    """A decoded post-filter byte."""

    snap_neighbours: int
    spread_copies: int
    spread_radius_m: float
    isolated: bool

    @classmethod
    def parse(cls, byte: int, label: str = "tile") -> "PostFilter":
        """ContainerError for a byte with unknown bits."""
        if not 0 <= byte <= 255 or byte & ~_KNOWN_BITS:
            raise ContainerError(f"{label}: unknown post-filter setting 0x{byte:02x}")
        copies, radius = SPREAD[byte >> 2 & 3]
        return cls(SNAP_NEIGHBOURS[byte & 3], copies, radius, bool(byte & _ISOLATED_BIT))


def check_setting(byte: int, label: str = "tile") -> int:
    """The byte, after ContainerError for unknown bits."""
    PostFilter.parse(byte, label)
    return byte


def apply_post_filter(cloud: np.ndarray, byte: int, planes: tuple[np.ndarray, np.ndarray] | None = None
                      ) -> np.ndarray:
    """A decoded (K, 3) float32 tile cloud (tile-local metres) after the post-filter `byte`, float32; byte 0 and
    clouds of fewer than 3 points are returned as they are. `planes`: `local_planes(cloud, k)` already computed for
    the byte's k, to share them between settings. The result may leave the tile's box (the caller crops it)."""
    setting = PostFilter.parse(byte)
    if byte == OFF or len(cloud) < 3:
        return cloud
    points = np.asarray(cloud, dtype=np.float64)
    if setting.snap_neighbours or setting.spread_copies:
        k = setting.snap_neighbours or PLANE_NEIGHBOURS
        centroids, normals = planes if planes is not None else local_planes(points, k, PLANE_ANCHOR_EVERY)
        if setting.snap_neighbours:
            points = project_to_planes(points, centroids, normals)
        if setting.spread_copies:
            points = np.concatenate([points, disk_samples(points, normals, setting.spread_radius_m,
                                                          setting.spread_copies)])
    if setting.isolated:
        keep = keep_supported(points, ISOLATED_RADIUS_M, ISOLATED_MIN_NEIGHBOURS)
        if keep.any():
            points = points[keep]
    return points.astype(np.float32)


def choose_post_filter(original: np.ndarray, decoded: np.ndarray, frame_m: np.ndarray, crop) -> tuple[int, float]:
    """(setting byte, D_e in metres of the filtered decode) for one network tile: of CANDIDATES whose D_e is at most
    (1 + MAX_D_E_INCREASE) x the unfiltered decode's, the one with the highest IoU (on the metric's world-anchored
    grid, `metrics.iou`); ties go to the earlier candidate, so OFF unless a setting gains.

    original: the tile's (N, 3) points and decoded: its (K, 3) decoded points, both tile-local metres relative to
    the world point `frame_m`; crop(cloud) -> the cloud's points the decoder keeps (inside the tile's box).
    """
    original = np.asarray(original, dtype=np.float64)
    original_tree = nearest_tree(original)
    world = original + frame_m
    planes = (local_planes(np.asarray(decoded, dtype=np.float64), PLANE_NEIGHBOURS, PLANE_ANCHOR_EVERY)
              if len(decoded) >= 3 else None)
    best = limit = None
    for byte in CANDIDATES:
        filtered = crop(apply_post_filter(decoded, byte, planes))
        d_e = d_euclidean(original, filtered, original_tree)
        if limit is None:
            limit = d_e * (1 + MAX_D_E_INCREASE)
        elif d_e > limit:
            continue
        overlap = iou(world, filtered.astype(np.float64) + frame_m)
        if best is None or overlap > best[0]:
            best = (overlap, byte, d_e)
    return best[1], best[2]
