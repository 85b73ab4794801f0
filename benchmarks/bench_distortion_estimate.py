"""How far the mode decision's sampled D_e estimates (`codec.distortion`) are from the exact D_e, on real tiles.

    .venv/bin/python benchmarks/bench_distortion_estimate.py -o results/distortion_estimate

Maps: the real submaps of ../shared/data/real/submaps, the KITTI scans of ../shared/data/real/kitti_seq00_scans
(one map each) and two maps of KITTI-submap copies (`bench_codec.build_map`: 2 x 2, and 3 x 3 cropped by (13, 7) m
so that tiles cut the copies). Every tile is tiled and framed as the compressor does; its candidates are the raw
coding, the octree at each leaf of OCTREE_LEAVES_M and the shipped e1's decode of its embedding (the last two only
where the tile is dense enough for the network). Per candidate: the estimate (`CandidateDistortion` with that one
candidate) and the exact D_e; per tile: whether two exact values lie within CLOSE of each other (where the
compressor computes exact values). Writes rows.json and prints the relative errors of the sampled candidates.
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_codec import build_map  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"


def maps() -> dict[str, np.ndarray]:
    from mapsqueeze.io import read_points

    found = {path.name: read_points(path) for path in sorted((SHARED / "submaps").glob("*.ply"))}
    found.update({f"kitti scan {path.stem}": read_points(path)
                  for path in sorted((SHARED / "kitti_seq00_scans").glob("*.bin"))})
    found["2 x 2 copies"] = build_map(2, (0.0, 0.0))
    found["3 x 3 copies cropped (13, 7) m"] = build_map(3, (13.0, 7.0))
    return found


def tile_candidates(local: np.ndarray, extent: np.ndarray, tile_size: np.ndarray, model):
    """(label, decoded points, own-distance function or None) of each candidate of a tile, as the compressor has."""
    from mapsqueeze.codec.compress import RAW_POINTS_PER_EMBEDDING
    from mapsqueeze.codec.octreetile import OCTREE_LEAVES_M, encode_octree_tiles, own_leaf_distances
    from mapsqueeze.codec.rawtile import decode_raw_tile, encode_raw_tile
    from mapsqueeze.codec.tilepoints import network_points, octree_points

    embedding = model.encode(local)
    yield "raw", decode_raw_tile(encode_raw_tile(local, tile_size), tile_size, len(local), "raw"), None
    if len(local) <= RAW_POINTS_PER_EMBEDDING * len(embedding.points):
        return
    for leaf, _, centres in encode_octree_tiles(local, tile_size, OCTREE_LEAVES_M):
        yield (f"octree {leaf:g} m", octree_points(centres, extent, None),
               lambda points, leaf=leaf: own_leaf_distances(points, tile_size, leaf, extent))
    yield "network", network_points(model, embedding.points, embedding.features, extent, None), None


def main() -> None:
    from mapsqueeze.codec.container import BOUNDS_STEPS, frame_origin, quantise_bounds
    from mapsqueeze.codec.distortion import CLOSE, SAMPLE_POINTS, CandidateDistortion
    from mapsqueeze.geometry.bounds import bounding_box
    from mapsqueeze.geometry.tiling import fit_grid, tile_map, to_local
    from mapsqueeze.model import load_model

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--out", type=Path, required=True, help="folder for rows.json")
    args = parser.parse_args()
    model = load_model("e1")
    tile_size = np.asarray(model.config.tile_size, dtype=np.float64)
    rows, close_tiles, n_tiles = [], 0, 0
    for name, points in maps().items():
        origin, shape = fit_grid(*bounding_box(points), tile_size)
        for tile in tile_map(points, tile_size, origin=origin, shape=shape):
            tile_origin = origin + np.asarray(tile.index) * tile_size
            world = points[tile.point_indices]
            lo, hi = quantise_bounds(world - tile_origin, tile_size)
            local = to_local(world, frame_origin(tile_origin, lo, tile_size), tile_size)
            extent = np.subtract(hi, lo) * tile_size / BOUNDS_STEPS
            exact_values = []
            for label, decoded, own in tile_candidates(local, extent, tile_size, model):
                estimate, exact = CandidateDistortion(local), CandidateDistortion(local, exact=True)
                estimate.add(decoded, own)
                exact.add(decoded, own)
                rows.append({"map": name, "tile": list(tile.index), "points": len(local), "decoded": len(decoded),
                             "candidate": label, "estimate_m": estimate.settle()[0], "exact_m": exact.settle()[0]})
                exact_values.append(rows[-1]["exact_m"])
            n_tiles += 1
            close_tiles += any(i != j and abs(a - b) <= CLOSE * min(a, b)
                               for i, a in enumerate(exact_values) for j, b in enumerate(exact_values))
            print(name, tile.index, len(local), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "rows.json").write_text(json.dumps(rows, indent=1))
    sampled = [r for r in rows if max(r["points"], r["decoded"]) > SAMPLE_POINTS]
    print(f"{len(rows)} candidates of {n_tiles} tiles, {len(sampled)} sampled; {close_tiles} tiles with two exact "
          f"D_e within {CLOSE:.0%}")
    for group, keep in (("network", lambda r: r["candidate"] == "network"),
                        ("raw and octree", lambda r: r["candidate"] != "network")):
        errors = np.array([r["estimate_m"] / r["exact_m"] - 1 for r in sampled if keep(r)])
        print(f"{group}: {len(errors)} sampled, relative error max {np.abs(errors).max():.4f}, "
              f"rms {np.sqrt(np.mean(errors ** 2)):.4f}, mean {errors.mean():+.4f}")


if __name__ == "__main__":
    main()
