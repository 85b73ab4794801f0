"""End-to-end codec speed, memory and rate on a multi-tile map, file to file, on 2 CPU cores.

Run: `.venv/bin/python benchmarks/bench_codec.py --model DIR [--copies 3] [--precision q f16] [--refine 0 20]`
(figures go to BENCHMARKS.md, "## Codec"). The map is copies of the real KITTI submap
(../shared/data/real/submaps/kitti_hdl64_6scans.ply), mirrored four ways, one per tile of a copies x copies grid
at UTM coordinates (optionally cropped so that the copies straddle the tile grid), written as PLY. Compression
and decompression each run in a fresh process (`mapsqueeze.compress_file` / `decompress_file`, what the CLI
calls) pinned to 2 cores, so their peak resident memory (ru_maxrss, including the ~0.4 GB of torch and the
model) is measured separately. D_e compares the decoded map with the input (mapsqueeze.metrics.d_euclidean).
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mapsqueeze.codec.compress import MAX_REFINE_STEPS
from mapsqueeze.shared import real_submaps_dir

KITTI_SUBMAP = real_submaps_dir() / "kitti_hdl64_6scans.ply"
UTM_OFFSET = np.array([500_000.0, 4_000_000.0, 50.0])  # on the 40 x 40 x 15 m tile grid (z tile 45-60 m)
CORES = 2


def build_map(copies: int, crop_m: tuple[float, float]) -> np.ndarray:
    """copies^2 mirrored copies of the KITTI submap at a 40 m pitch at UTM coordinates, minus the first crop_m
    metres in x and y.

    The codec fits its tile grid to the map (as few 40 m tiles as the extent needs, centred on it): uncropped,
    each copy fills one tile like the paper's submaps; a crop moves the grid so that every copy straddles tiles.
    """
    from mapsqueeze.io import read_points

    submap = read_points(KITTI_SUBMAP)
    local = submap - submap.min(axis=0)  # 40.0 x 38.3 x 6.9 m
    extent = local.max(axis=0)
    parts = []
    for i in range(copies):
        for j in range(copies):
            mirrored = local.copy()
            for axis, flip in enumerate(((i + j) % 2, (i // 2 + j) % 2)):  # four variants, so copies differ
                if flip:
                    mirrored[:, axis] = extent[axis] - mirrored[:, axis]
            parts.append(mirrored + [40.0 * i, 40.0 * j, 0.0])
    points = np.concatenate(parts)
    points = points[(points[:, 0] >= crop_m[0]) & (points[:, 1] >= crop_m[1])]
    return points + UTM_OFFSET


BORDER_BAND_M = 1.0


def border_and_interior_d_e(gt: np.ndarray, rec: np.ndarray, tile_size=(40.0, 40.0, 15.0)) -> tuple[float, float]:
    """D_e (m) restricted to points within BORDER_BAND_M of a face between two tiles, and to the other points.

    Each term of the symmetric mean is assigned by its own point (ground truth or decoded) and the tile grid that
    compression fitted to the map (mapsqueeze.geometry.tiling.fit_grid): a gap or overlap at tile borders shows up as
    a larger border D_e than interior D_e.
    """
    from scipy.spatial import cKDTree

    from mapsqueeze.geometry.tiling import fit_grid

    size = np.asarray(tile_size)
    origin, shape = fit_grid(gt.min(axis=0), gt.max(axis=0), size)

    def near_border(points):
        steps = (points - origin) / size  # faces between tiles at steps 1 .. shape - 1
        nearest_face = np.clip(np.round(steps), 1, np.maximum(shape - 1, 1))
        distance = np.where(shape > 1, np.abs(steps - nearest_face) * size, np.inf)
        return (distance < BORDER_BAND_M).any(axis=1)

    gt_terms = cKDTree(rec).query(gt, workers=-1)[0]
    rec_terms = cKDTree(gt).query(rec, workers=-1)[0]
    gt_border, rec_border = near_border(gt), near_border(rec)
    border = 0.5 * gt_terms[gt_border].mean() + 0.5 * rec_terms[rec_border].mean()
    interior = 0.5 * gt_terms[~gt_border].mean() + 0.5 * rec_terms[~rec_border].mean()
    return float(border), float(interior)


def _stage(args) -> None:
    """Child process: one compress or decompress, timed; prints JSON."""
    os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:CORES])
    import mapsqueeze
    from mapsqueeze.geometry.threads import set_threads

    set_threads(CORES)

    start = time.perf_counter()
    if args.stage == "compress":
        summary = mapsqueeze.compress_file(args.input, args.output, model=args.model, precision=args.precision,
                                           refine_steps=args.refine)
        result = {"bytes": summary.file_bytes, "tiles": summary.n_tiles, "raw_tiles": summary.n_raw_tiles,
                  "points": summary.n_points}
    else:
        result = {"points": mapsqueeze.decompress_file(args.input, args.output, model=args.model)}
    result["seconds"] = time.perf_counter() - start
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(result))


def _run_stage(stage: str, source: Path, target: Path, model: str, precision: str, refine: int) -> dict:
    command = [sys.executable, __file__, "--stage", stage, "--input", str(source), "--output", str(target),
               "--model", model, "--precision", precision, "--refine", str(refine)]
    done = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="model name or directory (e.g. an imported e1)")
    parser.add_argument("--copies", type=int, default=3, help="map of copies x copies KITTI submaps")
    parser.add_argument("--crop", type=float, nargs=2, default=(0.0, 0.0), metavar=("DX", "DY"),
                        help="drop the map's first DX, DY metres so that copies straddle the tile grid")
    parser.add_argument("--precision", nargs="+", default=["q", "f16"])
    parser.add_argument("--refine", type=int, nargs="+", default=[0], help="encode-time refinement steps (each a row)")
    parser.add_argument("--stage", choices=["compress", "decompress"], help=argparse.SUPPRESS)
    parser.add_argument("--input", help=argparse.SUPPRESS)
    parser.add_argument("--output", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if not all(0 <= steps <= MAX_REFINE_STEPS for steps in args.refine):
        parser.error(f"--refine: step counts from 0 to {MAX_REFINE_STEPS}")
    if args.stage:
        args.precision, args.refine = args.precision[0], args.refine[0]
        _stage(args)
        return
    from mapsqueeze.io import read_points, write_points
    from mapsqueeze.metrics import d_euclidean

    points = build_map(args.copies, args.crop)
    print(f"map: {args.copies}x{args.copies} KITTI submap copies cropped by {args.crop} m, {len(points):,} points, "
          f"model {args.model}, {CORES} cores, load average {os.getloadavg()[0]:.1f}")
    print("| precision | tiles (raw) | bytes | bpp | compress s | compress pts/s | compress peak MB "
          f"| decompress s | decompress pts/s | decompress peak MB | D_e (m) "
          f"| D_e within {BORDER_BAND_M:g} m of a tile face / elsewhere (m) |")
    print("|---" * 12 + "|")
    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / "map.ply"
        write_points(source, points)
        for precision, refine in ((p, r) for p in args.precision for r in args.refine):
            msq, decoded_path = Path(tmp) / f"map_{precision}.msq", Path(tmp) / f"decoded_{precision}.npy"
            packed = _run_stage("compress", source, msq, args.model, precision, refine)
            unpacked = _run_stage("decompress", msq, decoded_path, args.model, precision, refine)
            decoded = read_points(decoded_path)
            d_e = d_euclidean(points, decoded)
            border, interior = border_and_interior_d_e(points, decoded)
            label = f"{precision}, refine {refine}" if refine else precision
            print(f"| {label} | {packed['tiles']} ({packed['raw_tiles']}) | {packed['bytes']:,} "
                  f"| {8 * packed['bytes'] / len(points):.4f} | {packed['seconds']:.1f} "
                  f"| {len(points) / packed['seconds']:,.0f} | {packed['peak_rss_mb']:,.0f} "
                  f"| {unpacked['seconds']:.1f} | {unpacked['points'] / unpacked['seconds']:,.0f} "
                  f"| {unpacked['peak_rss_mb']:,.0f} | {d_e:.4f} | {border:.4f} / {interior:.4f} |", flush=True)


if __name__ == "__main__":
    main()
