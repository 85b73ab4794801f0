"""Statistics of simulated submaps next to the real ones in the shared folder's data/real/submaps.

For each real submap, simulated submaps are made under the same conditions (sensor, number of aggregated
scans, consecutive 10 Hz scans) in several scenes of the given presets, and both are described by: points per
submap, distribution over height and horizontal distance from the sensor, shape of the 0.5 m neighbourhoods
(PCA: linear / planar / scattered, by the largest of the dimensionality features of Demantke et al. 2011) and
nearest-neighbour spacing. Prints markdown tables; --figures renders real and simulated submaps side by side
(sim_<real name>.png) and a camera view of one scene per preset (sim_scene_<preset>.png).

    .venv/bin/python benchmarks/sim_vs_real.py --per-real 8 --figures docs/figures
"""

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mapsqueeze.data.simulator import Raycaster, SimulationConfig, build_scene, iter_scenes
from mapsqueeze.io import read_points
from mapsqueeze.shared import real_submaps_dir

REAL = {  # file stem -> (sensor, scans aggregated)
    "kitti_hdl64_6scans": ("hdl64", 6),
    "nuscenes_hdl32_1scan": ("hdl32", 1),
    "ouster_os2_128_1scan": ("os2_128", 1),
}
HEIGHT_BINS = np.array([-3.5, -2.5, -1.5, -1.0, 0.0, 1.0, 2.5, 4.5, 7.5])  # metres relative to the sensor
RANGE_BINS = np.array([0.0, 5.0, 10.0, 15.0, 20.0, 30.0])  # horizontal metres from the sensor
NEIGHBOURS = 100  # at most this many points of each 0.5 m neighbourhood
SAMPLE = 20000  # points per submap whose neighbourhood shape is measured


def local_frame(points: np.ndarray) -> np.ndarray:
    """Points relative to the sensor inside the common box |x|, |y| < 20 m, -3.5 <= z < 7.5 m.

    (The real files are centred on the middle pose with z in [-7.5, 7.5); mapsqueeze submaps span z in
    [-3.5, 11.5) around the key pose: compare on their overlap.)"""
    keep = (np.abs(points[:, :2]) < 20).all(axis=1) & (points[:, 2] >= -3.5) & (points[:, 2] < 7.5)
    return points[keep]


def dimensionality(points: np.ndarray, rng: np.random.Generator, radius: float = 0.5) -> np.ndarray:
    """Fractions of sampled points whose 0.5 m neighbourhood is [linear, planar, scattered, sparse (< 6 points)].

    sigma_i = sqrt of the covariance eigenvalues (descending); linearity (s1 - s2) / s1, planarity
    (s2 - s3) / s1, scattering s3 / s1; each point takes the largest.
    """
    tree = cKDTree(points)
    sample = points[rng.choice(len(points), min(SAMPLE, len(points)), replace=False)]
    distance, index = tree.query(sample, k=NEIGHBOURS, distance_upper_bound=radius)
    valid = np.isfinite(distance)
    count = valid.sum(axis=1)
    neighbours = points[np.where(valid, index, 0)] - sample[:, None, :]
    weights = valid[..., None]
    mean = (neighbours * weights).sum(axis=1) / count[:, None]
    centred = (neighbours - mean[:, None, :]) * weights
    covariance = np.einsum("nki,nkj->nij", centred, centred) / count[:, None, None]
    sigma = np.sqrt(np.clip(np.linalg.eigvalsh(covariance)[:, ::-1], 0.0, None))
    features = np.stack([(sigma[:, 0] - sigma[:, 1]), (sigma[:, 1] - sigma[:, 2]), sigma[:, 2]], 1)
    label = np.where(count < 6, 3, features.argmax(axis=1))
    return np.bincount(label, minlength=4) / len(label)


def submap_stats(points: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray | float]:
    """The compared statistics of one submap given relative to its sensor (see `local_frame`)."""
    points = local_frame(points)
    spacing = cKDTree(points).query(points, k=2)[0][:, 1]
    return {
        "points": float(len(points)),
        "height": np.histogram(points[:, 2], HEIGHT_BINS)[0] / len(points),
        "range": np.histogram(np.linalg.norm(points[:, :2], axis=1), RANGE_BINS)[0] / len(points),
        "shape": dimensionality(points, rng),
        "spacing": np.percentile(spacing, [5, 25, 50, 75, 95]),
    }


def simulate_matched(sensor: str, scans: int, count: int, presets: tuple[str, ...], seed: int) -> list[np.ndarray]:
    """`count` simulated submaps of `scans` consecutive scans of `sensor`, relative to their key pose."""
    config = SimulationConfig(n_submaps=count, sensors=(sensor,), presets=presets, seed=seed,
                              submaps_per_scene=2, scans_per_submap=(scans, scans), strides=(1,), stops=False)
    return [submap.points - submap.center for result in iter_scenes(config) for submap in result.submaps]


def _fmt(values: np.ndarray, scale: float = 100.0, digits: int = 0) -> str:
    return " / ".join(f"{v * scale:.{digits}f}" for v in np.atleast_1d(values))


def table(name: str, real: dict, simulated: list[dict]) -> str:
    """Markdown rows: the real value, then the simulated mean (and sd for the point count)."""
    mean = {key: np.mean([s[key] for s in simulated], axis=0) for key in real}
    sd_points = np.std([s["points"] for s in simulated])
    rows = [
        ("points per submap", f"{real['points']:,.0f}", f"{mean['points']:,.0f} +- {sd_points:,.0f}"),
        ("height % (" + ", ".join(f"{a:g}..{b:g}" for a, b in zip(HEIGHT_BINS[:-1], HEIGHT_BINS[1:])) + " m)",
         _fmt(real["height"]), _fmt(mean["height"])),
        ("range % (" + ", ".join(f"{a:g}..{b:g}" for a, b in zip(RANGE_BINS[:-1], RANGE_BINS[1:])) + " m)",
         _fmt(real["range"]), _fmt(mean["range"])),
        ("neighbourhood % linear / planar / scattered / sparse", _fmt(real["shape"]), _fmt(mean["shape"])),
        ("NN spacing p5 / p25 / p50 / p75 / p95 (cm)", _fmt(real["spacing"], 100, 1), _fmt(mean["spacing"], 100, 1)),
    ]
    lines = [f"\n### {name} (real) vs {len(simulated)} simulated\n", "| statistic | real | simulated (mean) |",
             "|---|---|---|"]
    lines += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(lines)


def render(path: Path, real: np.ndarray, simulated: np.ndarray, title: str) -> None:
    """Top-down and perspective views, coloured by height, real left and simulated right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 12))
    for column, (label, points) in enumerate((("real", local_frame(real)), ("simulated", local_frame(simulated)))):
        order = np.argsort(points[:, 2])
        style = dict(cmap="turbo", vmin=-2.3, vmax=2.5, linewidths=0, rasterized=True)
        top = fig.add_axes([0.06 + 0.49 * column, 0.5, 0.42, 0.42])
        top.scatter(points[order, 0], points[order, 1], c=points[order, 2], s=0.25, **style)
        top.set_aspect("equal")
        top.set_xlim(-20, 20)
        top.set_ylim(-20, 20)
        top.set_title(f"{label}: {len(points):,} points (top view, metres)", fontsize=10)
        view = fig.add_axes([0.0 + 0.5 * column, 0.0, 0.5, 0.46], projection="3d")
        view.scatter(points[:, 0], points[:, 1], points[:, 2], c=points[:, 2], s=0.12, **style)
        view.set_box_aspect((40, 40, 11), zoom=1.45)
        view.view_init(elev=28, azim=-115)
        view.set_xlim(-20, 20)
        view.set_ylim(-20, 20)
        view.set_zlim(-3.5, 7.5)
        view.set_axis_off()
        view.set_title(f"{label}: perspective", fontsize=10, y=0.92)
    fig.suptitle(title, fontsize=11)
    save_small_png(fig, path, dpi=80)
    plt.close(fig)


def save_small_png(fig, path: Path, dpi: int) -> None:
    """Save a matplotlib figure as a palette PNG (128 colours): a third of the size of the RGBA file."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    Image.open(buffer).convert("RGB").quantize(colors=128).save(path, optimize=True)


def render_scene(path: Path, preset: str, seed: int) -> None:
    """A shaded camera view (ray cast, 2.2 m above the driven lane) of one simulated scene, coloured by material:
    grey solid, green foliage / grass, blue glass, orange wire mesh."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene = build_scene(preset, 60.0, np.random.default_rng(seed))
    raycaster = Raycaster(scene.vertices, scene.faces, scene.materials)
    s = scene.drive_start_m + 20.0
    _, heading, z = scene.street.at(s)
    eye = np.array([*scene.street.point(s, scene.lane_offset_m), z + 2.2])
    width, height, half_fov = 960, 480, np.deg2rad(50)
    forward = np.array([np.cos(heading), np.sin(heading), 0.0])
    left = np.array([-np.sin(heading), np.cos(heading), 0.0])
    u, v = np.meshgrid(np.linspace(-1, 1, width), np.linspace(0.5, -0.5, height))
    rays = forward - u[..., None] * np.tan(half_fov) * left + (v * 2 * np.tan(half_fov))[..., None] * [0, 0, 0.5]
    rays = rays.reshape(-1, 3) / np.linalg.norm(rays.reshape(-1, 3), axis=1, keepdims=True)
    distance, face = raycaster.first_hits(np.broadcast_to(eye, rays.shape).copy(), rays)
    image = np.tile([0.75, 0.85, 1.0], (len(rays), 1))
    hit = face >= 0
    light = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    shade = 0.35 + 0.65 * np.abs(raycaster.normals[face[hit]] @ light)
    palette = np.array([[0.8, 0.8, 0.8], [0.2, 0.65, 0.2], [0.4, 0.6, 0.9], [0.55, 0.8, 0.4], [0.9, 0.6, 0.2]])
    fade = np.clip(1.2 - distance[hit] / 80.0, 0.35, 1.0)
    image[hit] = palette[raycaster.materials[face[hit]]] * (shade * fade)[:, None]
    figure = plt.figure(figsize=(width / 100, height / 100))
    figure.figimage(image.reshape(height, width, 3).clip(0, 1))
    save_small_png(figure, path, dpi=100)
    plt.close(figure)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", type=Path, default=real_submaps_dir())
    parser.add_argument("--per-real", type=int, default=8, help="simulated submaps per real one")
    parser.add_argument("--presets", default="urban,suburban")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--figures", type=Path, default=None, help="write sim_<name>.png here")
    args = parser.parse_args()
    if not args.real.is_dir():
        print(f"no real submaps at {args.real}", file=sys.stderr)
        return 1
    presets = tuple(args.presets.split(","))
    rng = np.random.default_rng(args.seed)
    print(f"Simulated: presets {', '.join(presets)}, seed {args.seed}; real: {args.real}")
    for stem, (sensor, scans) in REAL.items():
        path = args.real / f"{stem}.ply"
        if not path.is_file():
            continue
        real_points = read_points(path)
        simulated = simulate_matched(sensor, scans, args.per_real, presets, args.seed)
        real_stats = submap_stats(real_points, rng)
        simulated_stats = [submap_stats(points, rng) for points in simulated]
        print(table(f"{stem}: {sensor}, {scans} scan(s)", real_stats, simulated_stats))
        if args.figures is not None:
            args.figures.mkdir(parents=True, exist_ok=True)
            typical = int(np.argmin([abs(s["points"] - real_stats["points"]) for s in simulated_stats]))
            render(args.figures / f"sim_{stem}.png", real_points, simulated[typical],
                   f"{stem} (left) vs simulated {sensor}, {scans} scan(s) (right)")
    if args.figures is not None:
        for preset in ("urban", "suburban", "rural", "highway"):
            render_scene(args.figures / f"sim_scene_{preset}.png", preset, args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
