"""Where D_e comes from: its two directions, how the decoded points are thinned, what a point count would buy.

D_e (eq. 9) is half the mean distance from each ground-truth point to the reconstruction (coverage: parts of the
map the decoder misses or thins out) plus half the mean from each reconstructed point to the ground truth
(precision: points grown where there is no surface). Rows per cloud, each a way to bring the decoder's native
output down to the input's point count:
- "random subset": uniformly random;
- "spread subset (codec)": every (K / n)-th point along a Morton order, which keeps the decoder's density;
- "voxel subset": one point per voxel, the edge bisected to keep the count (the most even subset, density-blind);
- "oracle, ...": each embedding point decoded with as many points as the input had nearest to it (exact, or rounded
  to powers of 2 ** 0.5 or 2, with the order-0 entropy those counts would cost): what a count per embedding point
  in the bitstream could bring, before its rate.
Embeddings are f32 (no quantisation), so only the point allocation differs between rows.

    .venv/bin/python benchmarks/error_split.py --model e1 ../shared/data/real/submaps/*.ply
"""

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mapsqueeze.geometry.resample import resample_to_count
from mapsqueeze.geometry.tiling import fit_grid, tile_map
from mapsqueeze.io import read_points
from mapsqueeze.model import load_model


def directions(gt: np.ndarray, rec: np.ndarray) -> tuple[float, float]:
    """(mean ground truth -> reconstruction, mean reconstruction -> ground truth) nearest distance, metres."""
    return float(cKDTree(rec).query(gt)[0].mean()), float(cKDTree(gt).query(rec)[0].mean())


def allocate(weights: np.ndarray, n_points: int) -> np.ndarray:
    """Integer counts summing to n_points, proportional to weights (largest remainders)."""
    share = weights / weights.sum() * n_points
    counts = np.floor(share).astype(np.int64)
    counts[np.argsort(-(share - counts), kind="stable")[: n_points - counts.sum()]] += 1
    return counts


def voxel_subset(points: np.ndarray, count: int) -> np.ndarray:
    """`count` points, one per voxel (the first of each), at the voxel edge (bisected) keeping at least that many."""
    small, large = 1e-3, float(np.ptp(points, axis=0).max())  # metres: at least count voxels / one voxel
    for _ in range(30):
        edge = (small * large) ** 0.5
        n_voxels = len(np.unique(np.floor(points / edge).astype(np.int64), axis=0))
        small, large = (edge, large) if n_voxels >= count else (small, edge)
    _, first = np.unique(np.floor(points / small).astype(np.int64), axis=0, return_index=True)
    first = np.sort(first)
    assert len(first) >= count, "fewer distinct 1 mm voxels than points to keep"
    return points[first[(np.arange(count) * len(first)) // count]]


def entropy_bytes(symbols: np.ndarray) -> float:
    """Static (order-0) entropy of the symbols in bytes, histogram not counted."""
    p = np.bincount(symbols) / len(symbols)
    p = p[p > 0]
    return float(-(p * np.log2(p)).sum() * len(symbols) / 8)


ALLOCATIONS = {  # name -> None (whole tile), or (weights from the true counts, quantised symbol per embedding point)
    "random subset": None,
    "spread subset (codec)": None,
    "voxel subset": None,
    "oracle, exact counts": (lambda c: c.astype(float), None),
    "oracle, counts to 2^0.5": (lambda c: 2.0 ** (np.round(np.log2(c + 1) * 2) / 2),
                                lambda c: np.round(np.log2(c + 1) * 2).astype(np.int64)),
    "oracle, counts to 2^1": (lambda c: 2.0 ** np.round(np.log2(c + 1)),
                              lambda c: np.round(np.log2(c + 1)).astype(np.int64)),
}


def split(points: np.ndarray, model) -> dict[str, tuple[float, float, float]]:
    """Allocation name -> (gt->rec m, rec->gt m, count bytes) over all tiles of the map."""
    size = np.asarray(model.config.tile_size)
    origin, shape = fit_grid(points.min(0), points.max(0), size)
    recs = {name: [] for name in ALLOCATIONS}
    gts, count_bytes = [], dict.fromkeys(ALLOCATIONS, 0.0)
    for tile in tile_map(points, size, origin, shape):
        local = tile.local_points(points)
        emb = model.encode(local)
        native = model.decode(emb.points, emb.features)
        per_point = len(native) // len(emb.points)
        counts = np.bincount(cKDTree(emb.points).query(local)[1], minlength=len(emb.points))
        gts.append(local + tile.origin)
        for name, rule in ALLOCATIONS.items():
            if name == "random subset" and len(local) < len(native):
                rec = native[np.random.default_rng(0).choice(len(native), len(local), replace=False)]
            elif name == "voxel subset" and len(local) < len(native):
                rec = voxel_subset(native, len(local))
            elif rule is None:
                rec = resample_to_count(native, len(local))
            else:
                weights, symbols = rule
                n = allocate(weights(counts), len(local))
                rec = np.concatenate([resample_to_count(native[i * per_point:(i + 1) * per_point], int(n[i]))
                                      for i in range(len(n))])
                count_bytes[name] += entropy_bytes(symbols(counts)) if symbols else 0.0
            recs[name].append(rec + tile.origin)
    gt = np.concatenate(gts)
    return {name: (*directions(gt, np.concatenate(r)), count_bytes[name]) for name, r in recs.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("files", nargs="+", type=Path)
    ap.add_argument("--model", default="e1")
    args = ap.parse_args()
    model = load_model(args.model)
    print("| cloud | allocation | D_e (m) | gt -> rec (m) | rec -> gt (m) | count bytes (entropy) |")
    print("|---|---|---|---|---|---|")
    for path in args.files:
        for name, (g2r, r2g, n_bytes) in split(read_points(path), model).items():
            cost = f"{n_bytes:.0f}" if name.startswith("oracle, counts") else ""
            print(f"| {path.stem} | {name} | {(g2r + r2g) / 2:.4f} | {g2r:.4f} | {r2g:.4f} | {cost} |")


if __name__ == "__main__":
    main()
