"""Pictures of decoded maps: original vs mapsqueeze (default model and decode, as a user gets it) vs MPEG G-PCC
trisoup at about the same bpp; top view and a 1 m side slice (across the band of the original's densest y), one
PNG per cloud.

The G-PCC setting is the trisoup setting of the benchmark sweep whose bpp is closest (in log bpp) to mapsqueeze's.
`--mirrored-2x2 NAME` adds a multi-tile map: the first cloud and three mirrored copies of it in a 2 x 2 grid (a
map twice as wide and long whose tile faces run through continuous surfaces).

    .venv/bin/python benchmarks/figures_decoded.py ../shared/data/real/submaps/kitti_hdl64_6scans.ply \
        ../shared/data/real/submaps/ouster_os2_128_1scan.ply --mirrored-2x2 kitti_2x2 -o docs/figures
"""

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import mapsqueeze
from mapsqueeze.baselines import GpccCodec
from mapsqueeze.io import atomic_output, read_points
from mapsqueeze.metrics import evaluate

SLICE_M = 1.0
"""Thickness (metres) of the side slice."""


def mirrored_2x2(points: np.ndarray) -> np.ndarray:
    """The cloud and its mirror images across its box's x-max face, y-max face and both: a 2 x 2 map."""
    local = points - points.min(axis=0)
    width, length = local[:, 0].max(), local[:, 1].max()
    flip_x = local * [-1, 1, 1] + [2 * width, 0, 0]
    flip_y = local * [1, -1, 1] + [0, 2 * length, 0]
    flip_xy = local * [-1, -1, 1] + [2 * width, 2 * length, 0]
    return np.vstack([local, flip_x, flip_y, flip_xy]) + points.min(axis=0)


def closest_trisoup(points: np.ndarray, target_bpp: float, codec: GpccCodec) -> tuple[str, np.ndarray, dict]:
    """(setting label, decoded points, metrics) of the trisoup setting whose bpp is closest to target_bpp."""
    best = None
    for setting in (s for s in codec.settings() if s["mode"] == "trisoup"):
        data = codec.encode(points, setting)
        bpp = 8 * len(data) / len(points)
        distance = abs(np.log(bpp / target_bpp))
        if best is None or distance < best[0]:
            best = (distance, setting, data)
    _, setting, data = best
    decoded = codec.decode(data)
    label = f"trisoup, {setting['cell_m'] * 100:.0f} cm cells, node 2^{setting['node_log2']}"
    return label, decoded, _stats(points, decoded, len(data))


def _stats(points: np.ndarray, decoded: np.ndarray, n_bytes: int) -> dict:
    m = evaluate(points, decoded, n_bytes=n_bytes)
    return {"bpp": m.bpp, "d_e": m.d_e, "iou": m.iou, "points": len(decoded)}


def densest_band(points: np.ndarray) -> float:
    """y (metres) of the SLICE_M band across x holding the most original points, within the middle 80 % of y."""
    low, high = np.percentile(points[:, 1], [10, 90])
    centres = np.arange(low, high, SLICE_M / 4)
    counts = [np.count_nonzero(np.abs(points[:, 1] - y) < SLICE_M / 2) for y in centres]
    return float(centres[int(np.argmax(counts))])


def _draw(axes, clouds: list[tuple[str, np.ndarray]], slice_y: float) -> None:
    """Top row: top view coloured by height; bottom row: points within SLICE_M / 2 of y = slice_y, x against z
    (not to scale)."""
    low = np.percentile(clouds[0][1][:, 2], 1)
    high = np.percentile(clouds[0][1][:, 2], 99)
    for column, (title, points) in enumerate(clouds):
        top, side = axes[0, column], axes[1, column]
        top.scatter(points[:, 0], points[:, 1], c=points[:, 2], s=0.4, cmap="turbo", vmin=low, vmax=high,
                    linewidths=0, rasterized=True)
        top.axhline(slice_y, color="red", linewidth=0.5)
        top.set_title(title, fontsize=9)
        top.set_aspect("equal")
        band = np.abs(points[:, 1] - slice_y) < SLICE_M / 2
        side.scatter(points[band, 0], points[band, 2], s=0.8, color="black", linewidths=0, rasterized=True)
        side.set_xlabel("x (m)")
        side.set_title(f"{SLICE_M:g} m slice at the red line: {band.sum():,} points", fontsize=8)
    axes[0, 0].set_ylabel("y (m)")
    axes[1, 0].set_ylabel("z (m)")


def figure(name: str, points: np.ndarray, out_dir: Path, model: str | None) -> None:
    data = mapsqueeze.compress(points) if model is None else mapsqueeze.compress(points, model=model)
    decoded = mapsqueeze.decompress(data)
    ours = _stats(points, decoded, len(data))
    label, trisoup, theirs = closest_trisoup(points, ours["bpp"], GpccCodec())

    def caption(what: str, s: dict) -> str:
        return f"{what}\n{s['bpp']:.3f} bpp, D_e {s['d_e']:.3f} m, IoU {s['iou']:.2f}, {s['points']:,} points"

    clouds = [(f"original\n{len(points):,} points", points),
              (caption(f"mapsqueeze ({model or 'default model'}, default decode)", ours), decoded),
              (caption(f"G-PCC {label}", theirs), trisoup)]
    fig, axes = plt.subplots(2, 3, figsize=(18, 10.5), gridspec_kw={"height_ratios": [3, 1.2]})
    _draw(axes, clouds, densest_band(points))
    fig.suptitle(name)
    fig.tight_layout()
    with atomic_output(out_dir / f"decoded_{name}.png") as tmp:
        fig.savefig(tmp, format="png", dpi=80)
    plt.close(fig)
    def line(s: dict) -> str:
        return f"{s['bpp']:.3f} bpp, D_e {s['d_e']:.4f} m, IoU {s['iou']:.3f}, {s['points']:,} points"

    print(f"{name}: mapsqueeze {line(ours)}; G-PCC {label}: {line(theirs)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("clouds", nargs="+", type=Path)
    parser.add_argument("--mirrored-2x2", metavar="NAME", help="also draw the first cloud mirrored into a 2 x 2 map")
    parser.add_argument("--model", default=None, help="mapsqueeze model (default: the API's default model)")
    parser.add_argument("-o", "--out", type=Path, default=Path("docs/figures"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    first = None
    for path in args.clouds:
        points = read_points(path)
        first = points if first is None else first
        figure(path.stem, points, args.out, args.model)
    if args.mirrored_2x2:
        figure(args.mirrored_2x2, mirrored_2x2(first), args.out, args.model)


if __name__ == "__main__":
    main()
