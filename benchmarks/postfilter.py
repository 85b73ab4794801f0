"""The decode post-filter (codec/postfilter.py) on real clouds: one file per cloud, model and post-filter mode
(off: the paper's decode; patch: the default; auto: neighbour planes), each decoded by default through
`mapsqueeze.compress` / `mapsqueeze.decompress` on one worker. Per row: bpp, the tiles' settings, decoded points,
D_e, IoU, the IoU voxels (`metrics.IOU_VOXEL_M`, world-anchored) the decode misses (occupied in the original,
empty in the decode) and adds (empty in the original), and the CPU seconds of compress and decompress (median of
--repeats runs, the modes alternating).

    .venv/bin/python benchmarks/postfilter.py ../shared/data/real/submaps/kitti_hdl64_6scans.ply \
        ../shared/data/real/submaps/ouster_os2_128_1scan.ply --models e0,e1,e2,e3 --repeats 3
"""

import argparse
import time
from pathlib import Path

import numpy as np

import mapsqueeze
from mapsqueeze.codec.container import open_container
from mapsqueeze.codec.modes import POST_FILTER_MODES
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
    parser.add_argument("--repeats", type=int, default=1, help="runs per row; CPU seconds: their median")
    parser.add_argument("--modes", default=",".join(POST_FILTER_MODES[::-1]), help="post-filter modes to run")
    args = parser.parse_args()
    print("| cloud | model | post-filter | bpp | settings | decoded | D_e (m) | IoU | missed voxels | false voxels |"
          " compress CPU s | decompress CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    modes = args.modes.split(",")
    for path in args.clouds:
        gt = read_points(path)
        for model in args.models.split(","):
            compress_s, decompress_s = {mode: [] for mode in modes}, {mode: [] for mode in modes}
            outputs = {}
            for _ in range(args.repeats):  # the modes alternate, so each sees the same machine load
                for post_filter in modes:
                    start = time.process_time()
                    data = mapsqueeze.compress(gt, model=model, post_filter=post_filter, workers=1)
                    compress_s[post_filter].append(time.process_time() - start)
                    start = time.process_time()
                    rec = mapsqueeze.decompress(data, workers=1)
                    decompress_s[post_filter].append(time.process_time() - start)
                    outputs[post_filter] = data, rec
            for post_filter in modes:
                data, rec = outputs[post_filter]
                reader, stream = open_container(data)
                with stream:
                    settings = ",".join(str(entry.post_filter) for entry in reader.entries)
                missed, false, iou = missed_and_false(gt, rec)
                print(f"| {path.stem} | {model} | {post_filter} | {8 * len(data) / len(gt):.4f} | "
                      f"{settings} | {len(rec):,} | {d_euclidean(gt, rec):.4f} | {iou:.3f} | {missed:,} | {false:,} | "
                      f"{np.median(compress_s[post_filter]):.2f} | {np.median(decompress_s[post_filter]):.3f} |",
                      flush=True)

if __name__ == "__main__":
    main()
