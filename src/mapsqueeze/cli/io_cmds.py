"""`mapsqueeze convert`: point-cloud format conversion."""

from pathlib import Path

import typer

from mapsqueeze.cli.app import FORMAT_HELP, app, counted, nan_points_line, print_line
from mapsqueeze.io import check_output_path, dropped_fields, format_name, read_point_cloud, unnamed_fields, write_points


@app.command()
def convert(
    input_path: Path = typer.Argument(..., metavar="IN", help="point-cloud file to read"),
    output_path: Path = typer.Argument(..., metavar="OUT", help="point-cloud file to write (atomically)"),
    in_format: str | None = typer.Option(None, "--in-format", help=f"format of IN: {FORMAT_HELP}"),
    out_format: str | None = typer.Option(None, "--out-format", help=f"format of OUT: {FORMAT_HELP}"),
) -> None:
    """Convert a point cloud between formats (KITTI .bin, nuScenes .pcd.bin, PLY, PCD, LAS/LAZ, .npy), keeping
    every attribute and the LAS header's metadata the output format can hold; a PCD's points with a NaN
    coordinate ('no return') are left out, with a count."""
    format_name(output_path, out_format)  # a bad output fails before the input is read
    check_output_path(output_path, inputs=(input_path,))
    cloud = read_point_cloud(input_path, format=in_format)
    write_points(output_path, cloud.points, format=out_format, attributes=cloud.attributes, metadata=cloud.metadata)
    warn_dropped(cloud.attributes, output_path, out_format)
    if cloud.nan_points_dropped:
        print_line(nan_points_line(cloud.nan_points_dropped))
    print_line(f"wrote {counted(len(cloud), 'point')} to {output_path}")


def warn_dropped(names, output_path: Path, out_format: str | None = None) -> None:
    """One warning line on stderr naming the attributes the output format cannot hold, if any, and one naming those
    it holds without their names and dtypes (.npy's columns, unless already named so). (A CRS the output cannot
    hold is a CrsNotWrittenWarning of the writer's, printed as it is written.)"""
    dropped = dropped_fields(names, output_path, out_format)
    if dropped:
        print_line(f"warning: {output_path.name} cannot hold attribute(s) {', '.join(dropped)}; not written",
                   stderr=True)
    unnamed = unnamed_fields(names, output_path, out_format)
    if unnamed and unnamed != [f"column{3 + column}" for column in range(len(unnamed))]:
        print_line(f"warning: {output_path.name} holds attributes as unnamed float64 columns: "
                   f"{', '.join(f'{name} as column{3 + column}' for column, name in enumerate(unnamed))}",
                   stderr=True)
