"""Seams at tile faces: how a multi-tile map decodes next to the faces between its tiles.

For each model: compress the map and decompress it by default (the `mapsqueeze compress` / `decompress` code path),
then report
- the densest 5 mm slab: the share of all points in the densest 5 mm slice across x, y and z, decoded over
  original (a flat sheet of points on a tile face shows as a spike; target <= 1.5; shares, so that a decode of more
  points than the input is not counted as denser);
- D_e near internal faces over D_e elsewhere: the paper's symmetric D_e (metrics.py) with each direction's terms
  split by whether the point lies within 1 m of a face shared by two occupied tiles (target within 5 %).

    .venv/bin/python benchmarks/seams.py results/kitti_wide/kitti_seq00_scans-00000.ply --models e0,e1,e2,e3 \
        [--post-filter patch|auto|off]
"""

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import mapsqueeze
from mapsqueeze.codec.container import open_container
from mapsqueeze.codec.modes import POST_FILTER_MODES
from mapsqueeze.io import read_points

SLAB_M = 0.005
FACE_BAND_M = 1.0


def densest_slabs(points: np.ndarray, slab_m: float = SLAB_M) -> np.ndarray:
    """(3,) most points in one slab of thickness slab_m (metres) across x, y and z (slabs anchored at 0)."""
    return np.array([np.unique(np.floor(points[:, axis] / slab_m), return_counts=True)[1].max() for axis in range(3)])


def near_internal_face(points: np.ndarray, origin: np.ndarray, size: np.ndarray, occupied: set,
                       band_m: float = FACE_BAND_M) -> np.ndarray:
    """Boolean mask: the point lies within band_m of a face its grid tile shares with another occupied tile."""
    keys = _keys(np.array(sorted(occupied), dtype=np.int64).reshape(-1, 3))
    relative = (points - origin) / size
    index = np.floor(relative).astype(np.int64)
    within = (relative - index) * size  # metres from the tile's lower corner
    near = np.zeros(len(points), dtype=bool)
    for axis in range(3):
        for step, distance in ((-1, within[:, axis]), (1, size[axis] - within[:, axis])):
            neighbour = index.copy()
            neighbour[:, axis] += step
            shared = np.isin(_keys(neighbour), keys) & np.isin(_keys(index), keys)
            near |= shared & (distance < band_m)
    return near


def _keys(index: np.ndarray) -> np.ndarray:
    """One int64 per (i, j, k) tile index (|i|, |j|, |k| < 2**20)."""
    shifted = index + (1 << 20)
    return (shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2]


def split_d_e(gt: np.ndarray, rec: np.ndarray, gt_near: np.ndarray, rec_near: np.ndarray) -> tuple[float, float]:
    """Symmetric D_e (metres) of the points near internal faces and of the others."""
    gt_terms = cKDTree(rec).query(gt, workers=-1)[0]
    rec_terms = cKDTree(gt).query(rec, workers=-1)[0]

    def symmetric(gt_mask: np.ndarray, rec_mask: np.ndarray) -> float:
        return float(gt_terms[gt_mask].mean() / 2 + rec_terms[rec_mask].mean() / 2)

    return symmetric(gt_near, rec_near), symmetric(~gt_near, ~rec_near)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("map", type=Path)
    parser.add_argument("--models", default="e0,e1,e2,e3")
    parser.add_argument("--post-filter", default="patch", choices=POST_FILTER_MODES,
                        help="the decode post-filter to compress with (default: patch, the codec's default)")
    args = parser.parse_args()
    gt = read_points(args.map)
    gt_slabs = densest_slabs(gt)
    print(f"{args.map.name}: {len(gt):,} points, densest 5 mm slab across x, y, z: {gt_slabs.tolist()} points")
    print("| model | tiles | bpp | decoded | densest slab ratio x, y, z | D_e near faces (m) | D_e elsewhere (m) |"
          " ratio | compress s | decompress s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for model in args.models.split(","):
        start = time.perf_counter()
        data = mapsqueeze.compress(gt, model=model, post_filter=args.post_filter)
        compress_s = time.perf_counter() - start
        start = time.perf_counter()
        rec = mapsqueeze.decompress(data)
        decompress_s = time.perf_counter() - start
        reader, stream = open_container(data)
        with stream:
            header, occupied = reader.header, {entry.index for entry in reader.entries}
        origin, size = np.asarray(header.origin), np.asarray(header.tile_size)
        near, elsewhere = split_d_e(gt, rec, near_internal_face(gt, origin, size, occupied),
                                    near_internal_face(rec, origin, size, occupied))
        ratios = (densest_slabs(rec) / len(rec)) / (gt_slabs / len(gt))
        print(f"| {model} | {len(occupied)} | {8 * len(data) / len(gt):.3f} | {len(rec):,} | "
              f"{', '.join(f'{r:.2f}' for r in ratios)} | {near:.4f} | {elsewhere:.4f} | {near / elsewhere:.3f} | "
              f"{compress_s:.1f} | {decompress_s:.1f} |", flush=True)


if __name__ == "__main__":
    main()
