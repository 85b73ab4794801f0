"""The decode post-filter (codec/postfilter.py) on real clouds: one file per cloud and model with the post-filter
off (the paper's decode) and on (the default), both decoded by default through `mapsqueeze.compress` /
`mapsqueeze.decompress` on one worker. Per row: bpp, the tiles' settings, decoded points, D_e, IoU, the IoU voxels
(`metrics.IOU_VOXEL_M`, world-anchored) the decode misses (occupied in the original, empty in the decode) and
adds (empty in the original), and the CPU seconds of compress and decompress.

    .venv/bin/python benchmarks/postfilter.py ../shared/data/real/submaps/kitti_hdl64_6scans.ply \
        ../shared/data/real/submaps/ouster_os2_128_1scan.ply --models e0,e1,e2,e3
"""

import argparse
import time
from pathlib import Path

import numpy as np

import mapsqueeze
from mapsqueeze.codec.container import open_container
from mapsqueeze.geometry.voxel import pack_indices, voxel_indices
from mapsqueeze.io import read_points
from mapsqueeze.metrics import IOU_VOXEL_M, d_euclidean


def missed_and_false(gt: np.ndarray, rec: np.ndarray) -> tuple[int, int, float]:
    """(voxels occupied by gt only, voxels occupied by rec only, IoU) on the metric's grid."""
    keys = pack_indices(voxel_indices(np.concatenate([gt, rec]), IOU_VOXEL_M))
    gt_keys, rec_keys = np.unique(keys[:len(gt)]), np.unique(keys[len(gt):])
    common = len(np.intersect1d(gt_keys, rec_keys, assume_unique=True))
    return len(gt_keys) - common, len(rec_keys) - common, common / (len(gt_keys) + len(rec_keys) - common)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("clouds", type=Path, nargs="+")
    parser.add_argument("--models", default="e0,e1,e2,e3")
    args = parser.parse_args()
    print("| cloud | model | post-filter | bpp | settings | decoded | D_e (m) | IoU | missed voxels | false voxels |"
          " compress CPU s | decompress CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for path in args.clouds:
        gt = read_points(path)
        for model in args.models.split(","):
            for post_filter in (False, True):
                start = time.process_time()
                data = mapsqueeze.compress(gt, model=model, post_filter=post_filter, workers=1)
                compress_s = time.process_time() - start
                start = time.process_time()
                rec = mapsqueeze.decompress(data, workers=1)
                decompress_s = time.process_time() - start
                reader, stream = open_container(data)
                with stream:
                    settings = ",".join(str(entry.post_filter) for entry in reader.entries)
                missed, false, iou = missed_and_false(gt, rec)
                print(f"| {path.stem} | {model} | {'on' if post_filter else 'off'} | {8 * len(data) / len(gt):.4f} | "
                      f"{settings} | {len(rec):,} | {d_euclidean(gt, rec):.4f} | {iou:.3f} | {missed:,} | {false:,} | "
                      f"{compress_s:.1f} | {decompress_s:.1f} |", flush=True)


if __name__ == "__main__":
    main()
