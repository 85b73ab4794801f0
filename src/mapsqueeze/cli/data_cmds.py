"""`mapsqueeze build-map` (scan sequences -> submap dataset) and `mapsqueeze tile` (one map -> grid tiles)."""

import math
from pathlib import Path

import typer
from rich.progress import Progress

from mapsqueeze.cli.app import app, counted, make_console, parse_numbers
from mapsqueeze.data.mapping import (
    MAX_RANGE_M,
    MIN_RANGE_M,
    SPLITS,
    SUBMAP_DZ_M,
    SUBMAP_SPACING_M,
    VOXEL_SIZE_M,
    Submap,
    aggregate_map,
    build_submaps,
    write_dataset,
)
from mapsqueeze.data.sequences import estimate_poses, open_sequences
from mapsqueeze.errors import DataError, InvalidPointCloudError, MapsqueezeError
from mapsqueeze.geometry.tiling import TILE_SIZE_M, tile_map
from mapsqueeze.geometry.voxel import as_lengths
from mapsqueeze.io import read_point_cloud, write_points

_DEFAULT_SIZE = ",".join(f"{length:g}" for length in TILE_SIZE_M)
_SPLIT_HELP = f"Put every submap in this split ({', '.join(SPLITS)}); default: KITTI 08 test, every 10th val"


def _lengths(text: str, option: str) -> tuple[float, float, float]:
    """'40,40,15' -> (40.0, 40.0, 15.0) metres."""
    meaning = "three comma-separated positive lengths in metres (x,y,z)"
    lengths = parse_numbers(text, 3, option, meaning)
    try:
        return tuple(as_lengths(lengths, option))
    except InvalidPointCloudError:
        raise MapsqueezeError(f"{option}: expected {meaning}, got {text!r}") from None


def _check_split(split: str) -> None:
    if split and split not in SPLITS:
        raise MapsqueezeError(f"--split: expected one of {', '.join(SPLITS)}, got {split!r}")


@app.command("build-map")
def build_map(
    scans_dir: Path = typer.Argument(
        ..., help="KITTI dataset root (sequences/XX), one KITTI sequence folder, or a folder of scans + poses."
    ),
    out_dir: Path = typer.Option(..., "-o", "--out", help="Dataset directory: one PLY per submap + manifest.json."),
    poses: Path | None = typer.Option(None, "--poses", help="LiDAR-frame poses, 12 or 16 numbers per line."),
    labels: bool = typer.Option(True, "--labels/--no-labels", help="Drop moving/outlier points (SemanticKITTI)."),
    min_range: float = typer.Option(MIN_RANGE_M, "--min-range", min=0.0, help="Keep points beyond (m)."),
    max_range: float = typer.Option(MAX_RANGE_M, "--max-range", min=0.0, help="Keep points within (m)."),
    voxel: float = typer.Option(VOXEL_SIZE_M, "--voxel", help="Voxel filter size (m)."),
    spacing: float = typer.Option(SUBMAP_SPACING_M, "--spacing", help="Distance between submap centres (m)."),
    size: str = typer.Option(_DEFAULT_SIZE, "--size", help="Submap box x,y,z (m)."),
    dz: float = typer.Option(SUBMAP_DZ_M, "--dz", help="Box centre height above the key pose (m)."),
    centers: str = typer.Option("travelled", "--centers", help="Key poses every SPACING of path (travelled) or "
                                "of new ground (coverage, the reference's rule)."),
    split: str = typer.Option("", "--split", help=_SPLIT_HELP),
    estimate: bool = typer.Option(False, "--estimate-poses", help="Estimate missing poses with KISS-ICP."),
    save_map: bool = typer.Option(False, "--save-map", help="Also write each whole map as <name>-map.ply."),
) -> None:
    """Build maps from scan sequences the paper's way and cut them into submaps (a training/eval dataset)."""
    box = _lengths(size, "--size")
    _check_split(split)
    if not min_range < max_range:
        raise MapsqueezeError(f"--min-range ({min_range} m) must be below --max-range ({max_range} m)")
    if centers not in ("travelled", "coverage"):
        raise MapsqueezeError(f"--centers: expected travelled or coverage, got {centers!r}")
    if not math.isfinite(dz):
        raise MapsqueezeError(f"--dz must be a finite height in metres, got {dz}")
    sequences = open_sequences(scans_dir, poses, use_labels=labels)
    missing = [sequence.name for sequence in sequences if sequence.poses is None]
    if missing and not estimate:
        raise DataError(f"no poses for {', '.join(missing)}: give --poses FILE or --estimate-poses")
    console = make_console(stderr=True)
    meta = {"min_range_m": min_range, "max_range_m": max_range, "voxel_size_m": voxel, "spacing_m": spacing,
            "size_m": list(box), "dz_m": dz, "centers": centers, "labels": labels}
    with Progress(console=console, transient=True, disable=not console.is_terminal) as progress:
        for sequence in sequences:
            if sequence.poses is None:
                sequence = sequence.with_poses(estimate_poses(
                    sequence, lambda items: progress.track(items, description=f"{sequence.name}: KISS-ICP")))
            scans = progress.track(sequence.scans(), total=len(sequence), description=f"{sequence.name}: scans")
            world = aggregate_map(scans, min_range, max_range, voxel)
            submaps = build_submaps(world, sequence.poses, sequence.name, spacing, box, dz, centers, split)
            write_dataset(out_dir, submaps, {**meta, "layout": sequence.layout, "n_scans": len(sequence)})
            if save_map and len(world):
                write_points(out_dir / f"{sequence.name}-map.ply", world)
            console.print(f"{sequence.name}: {len(sequence):,} scans -> {len(world):,} map points -> "
                          f"{len(submaps):,} submaps")
    console.print(f"dataset: {out_dir}")


@app.command("tile")
def tile(
    map_path: Path = typer.Argument(..., metavar="MAP", help="Map point cloud (any format mapsqueeze reads)."),
    out_dir: Path = typer.Option(..., "-o", "--out", help="Output directory: one PLY per tile (points and attributes) + manifest.json."),
    tile_size: str = typer.Option(_DEFAULT_SIZE, "--tile", help="Tile size x,y,z (m)."),
    split: str = typer.Option("", "--split", help=_SPLIT_HELP),
) -> None:
    """Cut a map into grid tiles (float32 coordinates relative to each tile's float64 origin, every attribute of the
    map with its points)."""
    size = _lengths(tile_size, "--tile")
    _check_split(split)
    cloud = read_point_cloud(map_path)
    points = cloud.points
    tiles = tile_map(points, size)
    source = map_path.name.split(".")[0]
    submaps = (
        Submap(points[tile.point_indices], tile.origin + tile.size / 2, tile.bounds, source, number, None, split,
               {name: values[tile.point_indices] for name, values in cloud.attributes.items()})
        for number, tile in enumerate(tiles)
    )
    write_dataset(out_dir, submaps, {"map": str(map_path), "tile_size_m": list(size)})
    make_console().print(f"{counted(len(points), 'point')} -> {counted(len(tiles), 'tile')} in {out_dir}")
