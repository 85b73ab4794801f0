"""`mapsqueeze compress`, `decompress`, `info`: whole maps to and from .msq containers."""

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import typer

from mapsqueeze import api
from mapsqueeze.cli.app import (
    FORMAT_HELP, app, counted, device_option, make_console, max_tile_points_option, nan_points_line, parse_numbers,
    print_line, print_rows,
)
from mapsqueeze.cli.io_cmds import warn_dropped
from mapsqueeze.codec.attributes import DEFAULT_RELATIVE_STEP, DEFAULT_VOXEL_M
from mapsqueeze.codec.compress import MAX_REFINE_STEPS, AttributeOptions
from mapsqueeze.codec.modes import POST_FILTER_MODES
from mapsqueeze.errors import OutputError

MSQ_SUFFIX = ".msq"


@contextmanager
def _tile_progress(description: str) -> Iterator:
    """A progress(done, total) callback drawing a rich bar on stderr, when it is a terminal, for maps of more than one
    tile (rich is not loaded otherwise)."""
    if not sys.stderr.isatty():
        yield lambda done, total: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    bar = Progress(TextColumn(description), BarColumn(), MofNCompleteColumn(), TextColumn("tiles"),
                   TimeRemainingColumn(), console=make_console(stderr=True), transient=True)
    task = None

    def update(done: int, total: int) -> None:
        nonlocal task
        if total < 2:
            return
        if task is None:
            bar.start()
            task = bar.add_task(description, total=total)
        bar.update(task, completed=done)

    try:
        yield update
    finally:
        if task is not None:
            bar.stop()


def _workers_option() -> typer.models.OptionInfo:
    return typer.Option(None, "--workers", min=1, metavar="N",
                        help="threads coding tiles in parallel (default: one per core); the bytes are the same")


def _dask_option() -> typer.models.OptionInfo:
    return typer.Option(None, "--dask-scheduler", metavar="ADDRESS",
                        help="code the tiles on the Dask cluster at ADDRESS ('local': start one of --workers "
                             "processes); needs the dask extra: pip install 'mapsqueeze[dask]'")


@app.command("compress")
def compress_command(
    map_path: Path = typer.Argument(..., metavar="MAP", help="point-cloud map (.ply .pcd .las .laz .bin .npy)"),
    output: Path = typer.Option(..., "-o", "--output", help=".msq file to write (atomically; the name must end in "
                                                           ".msq)"),
    model: str | None = typer.Option(None, "--model", help=f"e0|e1|e2|e3 or a model directory (default "
                                     f"{api.DEFAULT_MODEL}; with --max-error or --bpp: the best of e0..e3)"),
    precision: str = typer.Option(api.DEFAULT_PRECISION, "--precision",
                                  help="embedding storage: f32, f16 (the paper's) or q (entropy-coded)"),
    refine: int = typer.Option(0, "--refine", min=0, max=MAX_REFINE_STEPS, metavar="STEPS",
                               help="encode-time refinement steps per tile: 20 lowers D_e ~10 % at the same size, "
                                    "each step ~0.35 CPU-s per dense 40 m tile (whose unrefined encoding takes "
                                    "~0.25); 0 is the paper's encoder"),
    in_format: str | None = typer.Option(None, "--format", metavar="FORMAT", help=f"format of MAP: {FORMAT_HELP}"),
    keep_zero_points: bool = typer.Option(False, "--keep-zero-points",
                                          help="keep points at exactly (0, 0, 0), which sensors write for 'no "
                                               "return' (default: left out, with a count)"),
    attributes: str = typer.Option("all", "--attributes", metavar="all|none|NAMES",
                                   help="per-point attributes to code (comma-separated names, e.g. intensity,label)"),
    attribute_voxel: float = typer.Option(DEFAULT_VOXEL_M, "--attribute-voxel", metavar="METRES",
                                          help="attribute resolution: edge of the voxels attributes are coded on"),
    attribute_step: float = typer.Option(DEFAULT_RELATIVE_STEP, "--attribute-step", metavar="FRACTION",
                                         help="quantisation step of continuous attributes (intensity, colour, time) "
                                              "as a fraction of each one's range"),
    workers: int | None = _workers_option(),
    dask_scheduler: str | None = _dask_option(),
    max_error: float | None = typer.Option(None, "--max-error", metavar="METRES",
                                           help="D_e budget: each tile gets the smallest coding within it, as "
                                                "decoded by default (fewer points decoded: a larger D_e)"),
    bpp: float | None = typer.Option(None, "--bpp", metavar="BITS",
                                     help="rate budget in bits per point: the lowest D_e that fits"),
    fallback: bool = typer.Option(True, "--fallback/--no-fallback",
                                  help="let a tile fall back to the classical octree where it is better"),
    post_filter: str = typer.Option("patch", "--post-filter", metavar="patch|auto|off",
                                    help="decode post-filter chosen per network tile: patch planes (patch, options "
                                         "chosen per decoder patch without --max-error/--bpp), "
                                         "neighbour planes (auto: higher IoU, seconds per tile to encode and "
                                         "decode) or none (off, the paper's decode)"),
    device: str = device_option("the encoder, the --refine steps through torch's autograd and the decoder the mode "
                                "decision measures"),
) -> None:
    """Compress a map: 40 x 40 x 15 m tiles, each stored with the coding its mode decision picks (the network's
    embedding, raw points or an octree); attributes (intensity, colour, labels, ...) on a voxel grid per tile; the
    LAS header's metadata (CRS) is kept."""
    if output.suffix.lower() != MSQ_SUFFIX and not output.is_dir():  # decompress reads the extension as the format
        raise OutputError(f"{output}: compress writes a .msq container; give an output name ending in {MSQ_SUFFIX}")
    if max_error is not None and bpp is not None:
        raise typer.BadParameter("give --max-error or --bpp, not both")
    if post_filter not in POST_FILTER_MODES:
        raise typer.BadParameter(f"--post-filter must be one of {'|'.join(POST_FILTER_MODES)}, got {post_filter!r}")
    options = AttributeOptions(attributes, attribute_voxel, attribute_step)
    with _tile_progress("compressing") as progress:
        summary = api.compress_file(map_path, output, model, precision, refine_steps=refine, max_error=max_error,
                                    bpp=bpp, fallback=fallback, post_filter=post_filter,
                                    progress=progress,
                                    keep_zero_points=keep_zero_points, format=in_format,
                                    attribute_options=options, workers=workers, dask_scheduler=dask_scheduler,
                                    device=device)
    if summary.nan_points_dropped:
        print_line(nan_points_line(summary.nan_points_dropped))
    if summary.zero_points_dropped:
        print_line(f"left out {counted(summary.zero_points_dropped, 'point')} at exactly (0, 0, 0) (sensor 'no "
                      "return' values; --keep-zero-points keeps them)")
    modes = ", ".join(f"{count} {mode}" for mode, count in summary.tile_modes.items())
    print_line(f"wrote {output}: {counted(summary.n_points, 'point')} in {counted(summary.n_tiles, 'tile')} "
                  f"({modes}), "
                  f"{summary.file_bytes:,} bytes, {summary.bits_per_point:.4f} bits per point"
                  + (f"; attributes {', '.join(summary.attributes)}: {summary.attribute_bytes:,} bytes"
                     if summary.attributes else ""))
    if bpp is not None and summary.bits_per_point > bpp:  # the smallest choices were taken (`codec.modes`)
        print(f"warning: {output} takes {summary.bits_per_point:.4f} bits per point, more than --bpp {bpp:g}: no "
              "choice of codings fits, so the smallest found was written", file=sys.stderr)


@app.command("decompress")
def decompress_command(
    msq: Path = typer.Argument(..., metavar="MAP.msq", help=".msq file to decode"),
    output: Path = typer.Option(..., "-o", "--output", help="point cloud to write (.ply .pcd .las .laz .bin .npy)"),
    bbox: str | None = typer.Option(None, "--bbox", metavar="x0,y0,z0,x1,y1,z1",
                                    help="decode only the tiles meeting this box (metres) and crop to it"),
    density: float | None = typer.Option(None, "--density", metavar="PTS_PER_M3",
                                         help="points per m^3 of the bounding box of each tile's points, each "
                                              "side at least 1 m (default: the count the file states, the native "
                                              "count of each tile's coding; version 1 files: the input count)"),
    points: int | None = typer.Option(None, "--points", metavar="N",
                                      help="total number of points to decode, split over the tiles by their input "
                                           "counts (with --bbox: over the tiles the box touches, before the crop)"),
    model: str | None = typer.Option(None, "--model", help="model to decode with (default: the shipped model "
                                                           "named in the file)"),
    out_format: str | None = typer.Option(None, "--format", metavar="FORMAT",
                                          help=f"format of the output: {FORMAT_HELP}"),
    max_tile_points: int = max_tile_points_option(),
    no_attributes: bool = typer.Option(False, "--no-attributes",
                                       help="write the geometry only, without decoding the attribute fields"),
    workers: int | None = _workers_option(),
    dask_scheduler: str | None = _dask_option(),
    device: str = device_option("the decoder"),
) -> None:
    """Decompress a .msq file to a point cloud."""
    box = None if bbox is None else parse_numbers(bbox, 6, "--bbox", "six comma-separated numbers x0,y0,z0,x1,y1,z1")
    with _tile_progress("decompressing") as progress:
        count = api.decompress_file(msq, output, model=model, bbox=box, density=density, n_points=points,
                                    progress=progress, max_tile_points=max_tile_points, format=out_format,
                                    workers=workers, dask_scheduler=dask_scheduler, attributes=not no_attributes,
                                    device=device)
    summary = api.info(msq)  # what the output could not hold: said once it is written, not before an error
    warn_dropped(() if no_attributes else summary.attributes, output, out_format)
    print_line(f"wrote {counted(count, 'point')} to {output}")


@app.command("info")
def info_command(msq: Path = typer.Argument(..., metavar="MAP.msq", help=".msq file")) -> None:
    """Show a .msq file's model, tiles, sizes, bits per point and origin."""
    from mapsqueeze.model.config import ModelConfig, decodes_files_of
    from mapsqueeze.model.shipped import CONFIG_FILE, SHIPPED_DIR, shipped_weights_sha256

    summary = api.info(msq)
    shipped = shipped_weights_sha256(summary.model_id)
    if shipped == summary.weights_sha256:
        model = f"{summary.model_id} (shipped; weights sha256 {summary.weights_sha256[:16]}...)"
    elif shipped is not None and decodes_files_of(
            shipped, ModelConfig.load(SHIPPED_DIR / summary.model_id / CONFIG_FILE), summary.weights_sha256):
        model = (f"{summary.model_id} (an earlier version of the shipped model, weights sha256 "
                 f"{summary.weights_sha256[:16]}...: the shipped {summary.model_id} has the same decoder)")
    else:
        model = (f"custom, named {summary.model_id!r} (weights sha256 {summary.weights_sha256[:16]}..., not a "
                 "shipped model: decompress needs --model PATH)")
    rows = [
        ("model", model),
        ("precision", summary.precision),
        ("subsampling r_s", f"{summary.subsampling_dist_m:g} m"),
        ("tile size", " x ".join(f"{v:g}" for v in summary.tile_size) + " m"),
        ("tiles", f"{summary.n_tiles}: " + ", ".join(f"{count} {mode}" for mode, count in summary.tile_modes.items())),
        ("default decode", "each tile's input point count" if summary.default_count == "input"
         else "the native count of each tile's coding (the network's output inside the tile after its "
              "post-filter, thinned at faces shared with other tiles)"),
        ("points", f"{summary.n_points:,}"),
        ("file size", f"{summary.file_bytes:,} bytes (header and tile table {summary.header_bytes:,})"),
        ("bits per point", f"{summary.bits_per_point:.4f}"),
        ("origin", ", ".join(f"{v:.3f}" for v in summary.origin)),
        ("bounds", " .. ".join("(" + ", ".join(f"{v:.2f}" for v in corner) + ")" for corner in summary.bounds)),
        ("attributes", summary.attribute_summary()),
    ]
    if "crs" in summary.metadata:
        rows.append(("crs", summary.metadata["crs"]))
    las = summary.metadata.get("las")
    if las:
        rows.append(("las header", f"version {las['version']}, point format {las['point_format']}, scales "
                     + ", ".join(f"{v:g}" for v in las["scales"]) + ", offsets "
                     + ", ".join(f"{v:g}" for v in las["offsets"]) + f", {len(las['vlrs'])} VLRs, "
                     f"{len(las['evlrs'])} EVLRs, extra bytes: {', '.join(las['extra_bytes']) or 'none'}"))
    print_rows(rows)
