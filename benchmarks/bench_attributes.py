"""Attribute coding quality on real LiDAR data, against a constant guess and against MPEG G-PCC (tmc3).

    PYTHONPATH=src python benchmarks/bench_attributes.py --out results/attributes [--tmc3 PATH]

Clouds: the KITTI scan 000000.bin (reflectance), a 40 x 40 x 15 m KITTI map of the six scans 000000-000005
placed with their poses (reflectance), and the nuScenes sweep (intensity; ring as a categorical attribute).
Each is compressed with the shipped e1 model through `mapsqueeze.compress` / `decompress_cloud` (what
`compress_file` / `decompress_file` run) at several attribute voxel edges and quantisation steps, coding one
attribute at a time. Measured (mapsqueeze.metrics): attribute error = mean |decoded value - value of the nearest
original point| over the decoded points, the same for the best constant guess (the median), their ratio, and for
categorical attributes the accuracy; the same at the input points (each takes the value of its nearest decoded
point: where the decoded geometry lies off the surfaces, this error includes the offset); attribute bits per input
point = the attribute section's bytes * 8 / N.
G-PCC codes the same cloud's positions on a 1 cm grid (near lossless) and reflectance/intensity (8 bits) with
RAHT and with lifting at several QPs; its attribute bits are the "reflectances bitstream size" it reports. The
LAZ row: the KITTI map written as LAZ (intensity = round(100 x reflectance)) through compress_file/decompress_file.
Writes results.md and results.json under --out.

    PYTHONPATH=src python benchmarks/bench_attributes.py --labels --out results/attributes

codes instead a proxy label on the KITTI map (no real labels are available here): ground (40) where a point lies
within 0.25 m of the lowest point of its 1 m x 1 m column, object (10) up to 2.5 m above it, structure (50) higher;
spatially coherent classes with real boundaries. Writes labels.md.

    PYTHONPATH=src python benchmarks/bench_attributes.py --simulated 4 --out results/attributes

measures instead simulated submaps, which carry real labels: `--simulated N` simulates N submaps (one scene each,
HDL-64E, urban / suburban / rural / highway in turn, seeds 2026, 2027, ...) with `simulate_dataset` (what `mapsqueeze
simulate` runs) into OUT/sim, or reads the submaps already there; per submap, intensity as above (mapsqueeze
and G-PCC RAHT) and the semantic label at the label voxels, and the intensity distribution against KITTI's
reflectance (scan 000000, 2-20 m). Writes simulated.md and simulated.json.
"""

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

import mapsqueeze
from mapsqueeze.codec.compress import AttributeOptions
from mapsqueeze.io import read_point_cloud, write_points
from mapsqueeze.metrics import attribute_error, constant_guess_error, label_accuracy
from mapsqueeze.shared import real_data_dir, tmc3_executable

VOXELS_M = (0.5, 1.0, 2.0)
STEPS = (1 / 16, 1 / 8, 1 / 32)
GPCC_QPS = (22, 28, 34, 40, 46, 51)
GPCC_TRANSFORMS = {"raht": 0, "lifting": 2}
MAP_HALF_EXTENT_M = (20.0, 20.0)
MAP_HEIGHT_M = 15.0


def kitti_map(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The six KITTI scans in the frame of the first, cropped to 40 x 40 m around it and 15 m high."""
    poses = np.loadtxt(folder / "poses_lidar_kissicp.txt").reshape(-1, 3, 4)
    points, reflectance = [], []
    for index, pose in enumerate(poses):
        cloud = read_point_cloud(folder / f"{index:06d}.bin")
        points.append(cloud.points @ pose[:, :3].T + pose[:, 3])
        reflectance.append(cloud.attributes["reflectance"])
    points, reflectance = np.concatenate(points), np.concatenate(reflectance)
    keep = (np.abs(points[:, :2]) <= MAP_HALF_EXTENT_M).all(axis=1)
    keep &= points[:, 2] <= points[keep, 2].min() + MAP_HEIGHT_M
    return points[keep], reflectance[keep]


def clouds(real: Path) -> dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]:
    kitti = read_point_cloud(real / "kitti_seq00_scans" / "000000.bin")
    nuscenes = read_point_cloud(next(real.glob("*.pcd.bin")))
    map_points, map_reflectance = kitti_map(real / "kitti_seq00_scans")
    return {
        "KITTI scan 000000": (kitti.points, {"reflectance": kitti.attributes["reflectance"]}),
        "KITTI 6-scan map": (map_points, {"reflectance": map_reflectance}),
        "nuScenes sweep": (nuscenes.points, {"intensity": nuscenes.attributes["intensity"],
                                             "ring": nuscenes.attributes["ring"]}),  # uint8 (io.tables)
    }


LABEL_VOXELS_M = (0.25, 0.5, 1.0, 2.0)


def proxy_labels(points: np.ndarray) -> np.ndarray:
    """Ground / object / structure by height above the lowest point of each 1 m column (see the docstring)."""
    columns = np.floor(points[:, :2] - points[:, :2].min(axis=0)).astype(np.int64)
    key = columns[:, 0] * (int(columns[:, 1].max()) + 1) + columns[:, 1]
    lowest = np.full(int(key.max()) + 1, np.inf)
    np.minimum.at(lowest, key, points[:, 2])
    height = points[:, 2] - lowest[key]
    return np.where(height < 0.25, 40, np.where(height < 2.5, 10, 50)).astype(np.uint8)


def label_table(real: Path) -> list[str]:
    points, _ = kitti_map(real / "kitti_seq00_scans")
    labels = {"label": proxy_labels(points)}
    rows = [measure(points, labels, "label", voxel, STEPS[0]) for voxel in LABEL_VOXELS_M]
    lines = [f"## Proxy labels on the KITTI 6-scan map ({len(points):,} points)", "",
             "| voxel (m) | extra bpp | accuracy at the decoded points | accuracy at the input points |",
             "|---|---|---|---|"]
    lines += [f"| {row['voxel_m']:g} | {row['attribute_bpp']:.4f} | {row['accuracy']:.4f} | "
              f"{row['input_accuracy']:.4f} |" for row in rows]
    return lines


SIM_PRESETS = ("urban", "suburban", "rural", "highway")


def simulated_clouds(n_submaps: int, folder: Path) -> dict[str, tuple[np.ndarray, dict[str, np.ndarray]]]:
    """N simulated submaps (simulated into `folder` unless its dataset already holds them): name -> (local points,
    intensity and label)."""
    from mapsqueeze.data import read_dataset
    from mapsqueeze.data.simulator import SimulationConfig, simulate_dataset

    for number in range(n_submaps):  # seed 2026 + number, one preset after the other
        if not list(folder.glob(f"sim{2026 + number}-*.ply")):
            simulate_dataset(folder, SimulationConfig(n_submaps=1, sensors=("hdl64",), split="test", seed=2026 + number,
                                                      presets=(SIM_PRESETS[number % len(SIM_PRESETS)],)))
    clouds = {}
    for record in read_dataset(folder).records[:n_submaps]:
        cloud = read_point_cloud(record.path)
        clouds[record.path.stem] = (cloud.points, {name: cloud.attributes[name] for name in ("intensity", "label")})
    return clouds


def simulated_table(n_submaps: int, out: Path, tmc3: str, real: Path) -> tuple[list[str], dict]:
    """Intensity (mapsqueeze, G-PCC RAHT) and label rows per simulated submap; the intensity distribution against
    KITTI's reflectance (scan 000000, 2-20 m)."""
    clouds = simulated_clouds(n_submaps, out / "sim")
    kitti = read_point_cloud(real / "kitti_seq00_scans" / "000000.bin")
    distance = np.linalg.norm(kitti.points, axis=1)
    simulated = np.concatenate([values["intensity"] for _, values in clouds.values()])
    reflectance = kitti.attributes["reflectance"][(distance > 2.0) & (distance < 20.0)]
    spread = {name: f"{' / '.join(f'{v:.2f}' for v in np.percentile(values, (10, 50, 90)))} (mean {values.mean():.2f})"
              for name, values in (("simulated", simulated), ("kitti", reflectance))}
    results, lines = {}, [f"# Attributes of {n_submaps} simulated submaps (benchmarks/bench_attributes.py "
                          f"--simulated {n_submaps})", "",
                          f"Intensity p10 / p50 / p90: simulated submaps {spread['simulated']}; KITTI scan 000000 "
                          f"reflectance at 2-20 m {spread['kitti']}.", ""]
    with tempfile.TemporaryDirectory() as temp:
        for cloud_name, (points, values) in clouds.items():
            rows = [measure(points, values, "intensity", voxel, step) for voxel in VOXELS_M for step in STEPS]
            rows += [measure(points, values, "label", voxel, STEPS[0]) for voxel in LABEL_VOXELS_M]
            raht = [gpcc(tmc3, points, values["intensity"], 255.0, GPCC_TRANSFORMS["raht"], qp, Path(temp))
                    for qp in GPCC_QPS]
            results[cloud_name] = {"n_points": len(points), "rows": rows, "gpcc_raht": raht}
            lines += [f"## {cloud_name} ({len(points):,} points)", "",
                      "| codec | attribute | setting | attribute bpp | error | constant guess | ratio / accuracy |",
                      "|---|---|---|---|---|---|---|"]
            lines += [_simulated_row("mapsqueeze", row) for row in rows]
            lines += [_simulated_row("G-PCC raht", row) for row in raht] + [""]
            print(f"done {cloud_name}", file=sys.stderr, flush=True)
    n_points = sum(result["n_points"] for result in results.values())
    lines += [f"## All {len(results)} submaps ({n_points:,} points): bits over all points, point-weighted quality", "",
              "| codec | attribute | setting | attribute bpp | error | constant guess | ratio / accuracy |",
              "|---|---|---|---|---|---|---|"]
    for codec, key in (("mapsqueeze", "rows"), ("G-PCC raht", "gpcc_raht")):
        for same in zip(*(result[key] for result in results.values())):  # one setting over every submap
            pooled = dict(same[0])
            for name in ("attribute_bpp", "error", "constant_error", "ratio", "accuracy"):
                if name in pooled:
                    pooled[name] = sum(row[name] * result["n_points"] for row, result in zip(same, results.values()))
                    pooled[name] /= n_points
            lines.append(_simulated_row(codec, pooled))
    return lines, results


def _simulated_row(codec: str, row: dict) -> str:
    """A table row of a mapsqueeze or G-PCC measurement (G-PCC rows are intensity)."""
    setting = f"qp {row['qp']}" if "qp" in row else f"voxel {row['voxel_m']:g} m, step 1/{round(1 / row['step'])}"
    quality = f"{row['ratio']:.3f}" if "ratio" in row else f"accuracy {row['accuracy']:.4f}"
    error = f"{row['error']:.4f}" if "error" in row else ""
    constant = f"{row['constant_error']:.4f}" if "constant_error" in row else ""
    return (f"| {codec} | {row.get('attribute', 'intensity')} | {setting} | {row['attribute_bpp']:.3f} | {error} | "
            f"{constant} | {quality} |")


def measure(points, values: dict[str, np.ndarray], name: str, voxel: float, step: float) -> dict:
    data = mapsqueeze.compress(points, attributes=values, attribute_options=AttributeOptions(name, voxel, step))
    decoded = mapsqueeze.decompress_cloud(data)
    row = {"attribute": name, "voxel_m": voxel, "step": step,
           "attribute_bpp": 8 * mapsqueeze.info(data).attribute_bytes / len(points),
           "file_bpp": 8 * len(data) / len(points)}
    if name in ("ring", "label"):
        row["accuracy"] = label_accuracy(points, values[name], decoded.points, decoded.attributes[name])
        row["input_accuracy"] = label_accuracy(decoded.points, decoded.attributes[name], points, values[name])
    else:
        row.update(errors(points, values[name], decoded.points, decoded.attributes[name]))
    return row


def errors(points: np.ndarray, values: np.ndarray, decoded_points: np.ndarray, decoded_values: np.ndarray) -> dict:
    """Attribute error at the decoded points (against the nearest input point's value) and at the input points
    (each takes its nearest decoded point's value), each with its ratio to the constant guess's error there."""
    row = {"error": attribute_error(points, values, decoded_points, decoded_values),
           "constant_error": constant_guess_error(points, values, decoded_points),
           "input_error": attribute_error(decoded_points, decoded_values, points, values)}
    row["ratio"] = row["error"] / row["constant_error"]
    row["input_ratio"] = row["input_error"] / float(np.abs(np.median(values) - values).mean())
    return row


def gpcc(tmc3: str, points: np.ndarray, values: np.ndarray, scale: float, transform: int, qp: int,
         work: Path) -> dict:
    """tmc3 on positions rounded to 1 cm and round(values * scale) as 8-bit reflectance; error in value units."""
    origin = points.min(axis=0)
    grid = np.round((points - origin) / 0.01)
    table = np.empty(len(grid), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("reflectance", "<u2")])
    table["x"], table["y"], table["z"] = grid.T
    table["reflectance"] = np.clip(np.round(values * scale), 0, 255)
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(table)}\nproperty float64 x\n"
              "property float64 y\nproperty float64 z\nproperty uint16 reflectance\nend_header\n")
    (work / "in.ply").write_bytes(header.encode() + table.tobytes())
    log = subprocess.run([tmc3, "--mode=0", f"--uncompressedDataPath={work / 'in.ply'}",
                          f"--compressedStreamPath={work / 'out.bin'}", "--mergeDuplicatedPoints=0",
                          f"--transformType={transform}", f"--qp={qp}", "--bitdepth=8", "--attribute=reflectance"],
                         capture_output=True, text=True, check=True).stdout
    attribute_bytes = int(re.search(r"reflectances bitstream size (\d+) B", log).group(1))
    subprocess.run([tmc3, "--mode=1", f"--compressedStreamPath={work / 'out.bin'}",
                    f"--reconstructedDataPath={work / 'rec.ply'}", "--outputBinaryPly=1"],
                   capture_output=True, text=True, check=True)
    decoded = read_point_cloud(work / "rec.ply")
    decoded_points = decoded.points * 0.01 + origin
    decoded_values = decoded.attributes[next(iter(decoded.attributes))].astype(np.float64) / scale
    return {"qp": qp, "attribute_bpp": 8 * attribute_bytes / len(points),
            **errors(points, values, decoded_points, decoded_values)}


def laz_route(points: np.ndarray, reflectance: np.ndarray, work: Path) -> dict:
    intensity = np.round(reflectance * 100).astype(np.uint16)
    write_points(work / "map.laz", points, attributes={"intensity": intensity})
    info = mapsqueeze.compress_file(work / "map.laz", work / "map.msq", attribute_options=AttributeOptions(
        "intensity"))
    mapsqueeze.decompress_file(work / "map.msq", work / "out.laz")
    decoded = read_point_cloud(work / "out.laz")
    error = attribute_error(points, intensity, decoded.points, decoded.attributes["intensity"])
    return {"attribute_bpp": 8 * info.attribute_bytes / len(points), "error": error,
            "ratio": error / constant_guess_error(points, intensity, decoded.points),
            "fields": sorted(decoded.attributes)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("results/attributes"))
    parser.add_argument("--tmc3", default=tmc3_executable())
    parser.add_argument("--labels", action="store_true", help="only the proxy-label table")
    parser.add_argument("--simulated", type=int, metavar="N", help="only N simulated submaps (in OUT/sim)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    real = real_data_dir()
    if args.simulated:
        lines, results = simulated_table(args.simulated, args.out, args.tmc3, real)
        (args.out / "simulated.json").write_text(json.dumps(results, indent=1))
        (args.out / "simulated.md").write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
        return
    if args.labels:
        lines = label_table(real)
        (args.out / "labels.md").write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
        return
    results = {"mapsqueeze": {}, "gpcc": {}}
    lines = ["# Attribute coding (benchmarks/bench_attributes.py)", ""]
    with tempfile.TemporaryDirectory() as temp:
        work = Path(temp)
        for cloud_name, (points, values) in clouds(real).items():
            rows = [measure(points, values, name, voxel, step)
                    for name in values for voxel in VOXELS_M for step in (STEPS if name != "ring" else STEPS[:1])]
            results["mapsqueeze"][cloud_name] = {"n_points": len(points), "rows": rows,
                                                 "geometry_bpp": 8 * len(mapsqueeze.compress(points)) / len(points)}
            name = next(iter(values))
            scale = 100.0 if name == "reflectance" else 1.0
            results["gpcc"][cloud_name] = {kind: [gpcc(args.tmc3, points, values[name], scale, code, qp, work)
                                                  for qp in GPCC_QPS] for kind, code in GPCC_TRANSFORMS.items()}
            lines += [f"## {cloud_name} ({len(points):,} points, geometry "
                      f"{results['mapsqueeze'][cloud_name]['geometry_bpp']:.3f} bpp with e1)", "",
                      "| codec | attribute | setting | attribute bpp | error | constant guess | ratio / accuracy | "
                      "error at input points | ratio / accuracy there |", "|---|---|---|---|---|---|---|---|---|"]
            for row in rows:
                setting = f"voxel {row['voxel_m']:g} m, step 1/{round(1 / row['step'])}"
                lines.append(f"| mapsqueeze | {row['attribute']} | {setting} | {row['attribute_bpp']:.4f} | "
                             + (f"{row['error']:.4f} | {row['constant_error']:.4f} | {row['ratio']:.3f} | "
                                f"{row['input_error']:.4f} | {row['input_ratio']:.3f} |" if "ratio" in row else
                                f" | | accuracy {row['accuracy']:.4f} | | accuracy {row['input_accuracy']:.4f} |"))
            for kind, gpcc_rows in results["gpcc"][cloud_name].items():
                for row in gpcc_rows:
                    lines.append(f"| G-PCC {kind} | {name} | qp {row['qp']} | {row['attribute_bpp']:.4f} | "
                                 f"{row['error']:.4f} | {row['constant_error']:.4f} | {row['ratio']:.3f} | "
                                 f"{row['input_error']:.4f} | {row['input_ratio']:.3f} |")
            lines.append("")
            if cloud_name == "KITTI 6-scan map":
                results["laz"] = laz_route(points, values["reflectance"], work)
                lines += [f"LAZ route (intensity = round(100 x reflectance), compress_file/decompress_file, default "
                          f"voxel and step): {results['laz']['attribute_bpp']:.3f} attribute bpp, error "
                          f"{results['laz']['error']:.3f}, ratio {results['laz']['ratio']:.3f}, fields back: "
                          f"{', '.join(results['laz']['fields'])}", ""]
            print(f"done {cloud_name}", file=sys.stderr, flush=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    (args.out / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
