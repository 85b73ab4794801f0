"""How many points to decode: D_e, D_perp and IoU of one file decoded to 1x, 2x, 3x, 4x the input's count and to
the decoder's native count (the default of version 2 files), through `mapsqueeze.decompress`; and the native output
thinned where it clumps (at most CAP_POINTS points per CAP_VOXEL_M voxel, an evenly spread subset of each voxel's
points along their Morton order).

bpp is the same in every row (one file per cloud and model); only the decoded count differs.

    .venv/bin/python benchmarks/density.py ../shared/data/real/submaps/*.ply --models e0,e1,e2,e3
"""

import argparse
from pathlib import Path

import numpy as np

import mapsqueeze
from mapsqueeze.geometry.morton import morton_codes
from mapsqueeze.geometry.normals import normals_pca
from mapsqueeze.io import read_points
from mapsqueeze.metrics import evaluate

MULTIPLES = (1, 2, 3, 4)
CAP_VOXEL_M = 0.1
CAP_POINTS = 8


def capped(points: np.ndarray, cap: int = CAP_POINTS, voxel_m: float = CAP_VOXEL_M) -> np.ndarray:
    """At most `cap` points per voxel: each voxel's points in Morton order, every (n / cap)-th kept when n > cap."""
    cells = np.floor((points - points.min(axis=0)) / voxel_m).astype(np.int64)
    codes = morton_codes(cells)
    order = np.argsort(codes, kind="stable")
    starts = np.flatnonzero(np.r_[True, codes[order][1:] != codes[order][:-1]])
    sizes = np.diff(np.r_[starts, len(order)])
    rank = np.arange(len(order)) - np.repeat(starts, sizes)
    n = np.repeat(sizes, sizes)
    return points[np.sort(order[(n <= cap) | ((rank * cap) % n < cap)])]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("clouds", type=Path, nargs="+")
    parser.add_argument("--models", default="e0,e1,e2,e3")
    args = parser.parse_args()
    print("| cloud | model | bpp | decoded | points per input point | D_e (m) | D_perp (m) | IoU |")
    print("|---|---|---|---|---|---|---|---|")
    for path in args.clouds:
        gt = read_points(path)
        normals = normals_pca(gt)
        for model in args.models.split(","):
            data = mapsqueeze.compress(gt, model=model, fallback=False)
            decodes = [(f"{k}x", mapsqueeze.decompress(data, n_points=k * len(gt))) for k in MULTIPLES]
            native = mapsqueeze.decompress(data)
            decodes += [("native (default)", native), (f"native, <= {CAP_POINTS} per {CAP_VOXEL_M:g} m voxel",
                                                       capped(native))]
            for label, rec in decodes:
                m = evaluate(gt, rec, len(data), normals)
                print(f"| {path.stem} | {model} | {m.bpp:.3f} | {label} | {len(rec) / len(gt):.2f} | {m.d_e:.4f} | "
                      f"{m.d_perp:.4f} | {m.iou:.3f} |", flush=True)


if __name__ == "__main__":
    main()
