"""`mapsqueeze view`: a self-contained web page of a .msq file's decoded map, optionally over its original."""

import webbrowser
from pathlib import Path

import typer

from mapsqueeze.cli.app import app, device_option, max_tile_points_option, nan_points_line, print_line
from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.view import DEFAULT_MAX_POINTS


@app.command("view")
def view_command(
    msq: Path = typer.Argument(..., metavar="MAP.msq", help=".msq file to show"),
    original: Path | None = typer.Option(None, "--original", metavar="FILE",
                                         help="the map it was compressed from (.ply .pcd .las .laz .bin .npy): shown "
                                              "beside or over the decoded one, with errors and D_e, D_perp, IoU"),
    output: Path | None = typer.Option(None, "-o", "--output", metavar="view.html",
                                       help="HTML page to write (atomically; default: MAP.html beside MAP.msq)"),
    max_points: int = typer.Option(DEFAULT_MAX_POINTS, "--max-points", min=1, metavar="N",
                                   help="points drawn per cloud: an evenly spread subset (8-13 bytes of page each: "
                                        "13 with errors and intensity)"),
    model: str | None = typer.Option(None, "--model", help="model to decode with (default: the one in the file)"),
    max_tile_points: int = max_tile_points_option(),
    open_page: bool = typer.Option(False, "--open", help="open the page in the default web browser"),
    device: str = device_option("the decoder"),
) -> None:
    """Write one HTML page (works offline, nothing to serve) showing the decoded map, the original, errors, tiles."""
    from mapsqueeze.io import check_output_path
    from mapsqueeze.view import ViewInput, load_cloud, write_view

    output = output or msq.with_suffix(".html")
    check_output_path(output, inputs=(msq,) if original is None else (msq, original))
    if not msq.is_file():
        raise MapsqueezeError(f"{msq}: no such file")
    view = ViewInput(msq.name, msq, original=None if original is None else load_cloud(original), model=model,
                     device=device, max_tile_points=max_tile_points)
    scene = write_view(view, output, max_points)
    drawn = ", ".join(f"{c['name']} {c['drawn']:,} of {c['total']:,}" for c in scene["clouds"])
    if view.original is not None and view.original.nan_points_dropped:
        print_line(nan_points_line(view.original.nan_points_dropped, original))
    print_line(f"wrote {output} ({output.stat().st_size:,} bytes; points drawn: {drawn})")
    if open_page:
        webbrowser.open(output.resolve().as_uri())
