"""`mapsqueeze convert`: point-cloud format conversion."""

from pathlib import Path

import typer
from rich.console import Console

from mapsqueeze.cli.app import app
from mapsqueeze.io import SUPPORTED_FORMATS, read_point_cloud, write_points

_FORMAT_HELP = f"one of {', '.join(SUPPORTED_FORMATS)} (default: from the extension)"


@app.command()
def convert(
    input_path: Path = typer.Argument(..., metavar="IN", help="point-cloud file to read"),
    output_path: Path = typer.Argument(..., metavar="OUT", help="point-cloud file to write (atomically)"),
    in_format: str | None = typer.Option(None, "--in-format", help=f"format of IN: {_FORMAT_HELP}"),
    out_format: str | None = typer.Option(None, "--out-format", help=f"format of OUT: {_FORMAT_HELP}"),
) -> None:
    """Convert a point cloud between formats (KITTI .bin, nuScenes .pcd.bin, PLY, PCD, LAS/LAZ, .npy)."""
    cloud = read_point_cloud(input_path, format=in_format)
    stored = write_points(output_path, cloud.points, format=out_format, attributes=cloud.attributes)
    console = Console()
    console.print(f"wrote {len(cloud):,} points to {output_path}")
    dropped = [name for name in cloud.attributes if name not in stored]
    if dropped:
        console.print(f"attributes the output format cannot store, not written: {', '.join(dropped)}")
