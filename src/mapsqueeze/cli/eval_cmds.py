"""`mapsqueeze eval`: the paper's reconstruction metrics of one reconstruction against its ground truth."""

import dataclasses
import json
from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from mapsqueeze.cli.app import app, make_console, nan_points_line, print_table
from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.io import read_point_cloud


def _compressed_size(n_bytes: int | None, compressed: Path | None) -> int | None:
    """The compressed size in bytes from --bytes or the size of --compressed (at most one of them)."""
    if n_bytes is not None and compressed is not None:
        raise MapsqueezeError("give either --bytes or --compressed, not both")
    if compressed is None:
        return n_bytes
    try:
        return compressed.stat().st_size
    except OSError as exc:
        raise MapsqueezeError(f"{compressed}: cannot read its size ({exc.strerror or exc})") from None


def _table(metrics) -> Table:
    """The rows of `mapsqueeze eval` for a mapsqueeze.metrics.Metrics."""
    from mapsqueeze.metrics import IOU_VOXEL_M

    voxel_cm = " x ".join(f"{size * 100:g}" for size in IOU_VOXEL_M)
    table = Table("metric", "value", "unit")
    table.add_row("D_e", f"{metrics.d_e:.6f}", "m")
    table.add_row("D_perp", f"{metrics.d_perp:.6f}", "m")
    table.add_row("IoU", f"{metrics.iou:.4f}", f"{voxel_cm} cm voxels")
    table.add_row("Chamfer", f"{metrics.chamfer:.6g}", "m^2")
    table.add_row("bpp", "-" if metrics.bpp is None else f"{metrics.bpp:.4f}", "bits per GT point")
    table.add_row("GT points", f"{metrics.n_gt:,}", "")
    table.add_row("reconstructed points", f"{metrics.n_rec:,}", "")
    return table


@app.command("eval")
def eval_command(
    gt: Path = typer.Argument(..., help="Ground-truth point cloud (any format `mapsqueeze` reads)."),
    recon: Path = typer.Argument(..., help="Reconstructed point cloud."),
    n_bytes: int | None = typer.Option(None, "--bytes", min=0, help="Compressed size in bytes, for bpp."),
    compressed: Path | None = typer.Option(None, "--compressed", help="Compressed file whose size gives bpp."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object instead of a table."),
) -> None:
    """D_e, D_perp, IoU, Chamfer and bits per point of RECON against GT (the paper's Sec. IV-A metrics); a PCD's
    points with a NaN coordinate ('no return') are left out of both, with a count on stderr."""
    from mapsqueeze.metrics import EVALUATION_STAGES, evaluate, overlap_warning  # scipy: imported here

    size = _compressed_size(n_bytes, compressed)
    stages = ("reading", *EVALUATION_STAGES)
    console = make_console(stderr=True)
    bar = Progress(TextColumn("evaluating: {task.description}"), BarColumn(), MofNCompleteColumn(),
                   TimeElapsedColumn(), console=console, transient=True, disable=not console.is_terminal)
    with bar:
        task = bar.add_task(stages[0], total=len(stages))
        clouds = {path: read_point_cloud(path, attributes=False) for path in (gt, recon)}
        gt_points, recon_points = clouds[gt].points, clouds[recon].points
        metrics = evaluate(gt_points, recon_points, n_bytes=size, progress=lambda stage: bar.update(
            task, advance=1, description=stage))
    for path, cloud in clouds.items():
        if cloud.nan_points_dropped:
            console.print(nan_points_line(cloud.nan_points_dropped, path))
    warning = overlap_warning(gt_points, recon_points, metrics.d_e)
    if warning:
        console.print(f"warning: {warning}")
    if as_json:
        print(json.dumps(dataclasses.asdict(metrics)))
    else:
        print_table(_table(metrics))
