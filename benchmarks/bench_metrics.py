"""Time PCA normals and `evaluate()` (all metrics) on a 400k-point synthetic map, on the real KITTI submap and on an
unfiltered dense patch (more neighbour pairs than normals hold at once: the blockwise path, timed once).

Run: `.venv/bin/python benchmarks/bench_metrics.py [--repeats 3]` (figures go to BENCHMARKS.md, "## Metrics").
Wall and CPU seconds are the median over the repeats; CPU counts every core (cKDTree queries use all of them).
"""

import argparse
import os
import time

import numpy as np

from mapsqueeze.geometry.normals import normals_pca
from mapsqueeze.io import read_points
from mapsqueeze.metrics import evaluate
from mapsqueeze.shared import real_submaps_dir

KITTI_SUBMAP = real_submaps_dir() / "kitti_hdl64_6scans.ply"
SPACING_M = 0.1  # the paper's 10 cm voxel-filtered map density
NOISE_M = 0.01


def _grid(width_m: float, height_m: float) -> np.ndarray:
    """(M, 2) grid points at SPACING_M over a width x height rectangle."""
    u, v = np.meshgrid(np.arange(0, width_m, SPACING_M), np.arange(0, height_m, SPACING_M), indexing="ij")
    return np.column_stack([u.ravel(), v.ravel()])


def synthetic_map(rng: np.random.Generator) -> np.ndarray:
    """400,000 points: a 60 x 40 m ground grid, four 6 m walls around it and 40,000 clutter points, 1 cm noise."""
    ground = _grid(60, 40)
    long_wall, short_wall = _grid(60, 6), _grid(40, 6)
    parts = [
        np.column_stack([ground, np.zeros(len(ground))]),
        np.column_stack([long_wall[:, 0], np.zeros(len(long_wall)), long_wall[:, 1]]),
        np.column_stack([long_wall[:, 0], np.full(len(long_wall), 40.0), long_wall[:, 1]]),
        np.column_stack([np.zeros(len(short_wall)), short_wall]),
        np.column_stack([np.full(len(short_wall), 60.0), short_wall]),
        rng.uniform([10, 10, 0], [50, 30, 3], size=(40_000, 3)),  # trees, cars, poles: volumetric clutter
    ]
    points = np.concatenate(parts)
    return points + rng.normal(0, NOISE_M, points.shape) + np.array([456_789.0, 5_432_101.0, 42.0])


def _timed(function, repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of `function()`."""
    wall, cpu = [], []
    for _ in range(repeats):
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        function()
        wall.append(time.perf_counter() - wall_start)
        cpu.append(time.process_time() - cpu_start)
    return float(np.median(wall)), float(np.median(cpu))


def bench(name: str, gt: np.ndarray, rec: np.ndarray, repeats: int) -> None:
    normals_wall, normals_cpu = _timed(lambda: normals_pca(gt), repeats)
    evaluate_wall, evaluate_cpu = _timed(lambda: evaluate(gt, rec, n_bytes=len(gt) // 8), repeats)
    metrics = evaluate(gt, rec)
    print(
        f"| {name} | {len(gt):,} | {len(rec):,} | {normals_wall:.2f} / {normals_cpu:.2f} "
        f"| {evaluate_wall:.2f} / {evaluate_cpu:.2f} | {metrics.d_e:.4f} | {metrics.d_perp:.4f} | {metrics.iou:.3f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    print(f"cores available: {len(os.sched_getaffinity(0))}")
    print(
        "| cloud | GT points | rec points | normals wall / CPU (s) | evaluate() wall / CPU (s) "
        "| D_e (m) | D_perp (m) | IoU |"
    )
    print("|---|---|---|---|---|---|---|---|")
    gt = synthetic_map(rng)
    bench("synthetic map vs itself + 3 cm noise", gt, gt + rng.normal(0, 0.03, gt.shape), args.repeats)
    if KITTI_SUBMAP.exists():
        kitti = read_points(KITTI_SUBMAP)
        bench("KITTI submap vs itself + 3 cm noise", kitti, kitti + rng.normal(0, 0.03, kitti.shape), args.repeats)
    else:
        print(f"(KITTI submap not found at {KITTI_SUBMAP}: skipped)")
    patch = np.column_stack([rng.uniform(0, 10, (200_000, 2)), rng.normal(0, NOISE_M, 200_000)])
    patch += np.array([456_789.0, 5_432_101.0, 42.0])
    bench("unfiltered patch (200k points on 10 x 10 m) vs itself + 3 cm noise", patch,
          patch + rng.normal(0, 0.03, patch.shape), 1)


if __name__ == "__main__":
    main()
