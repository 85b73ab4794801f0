"""`mapsqueeze demo`: the README's main job on the embedded default model and data."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from mapsqueeze.cli.app import app, device_option, make_console, print_table
from mapsqueeze.codec.compress import MAX_REFINE_STEPS

console = make_console()


@app.command("demo")
def demo_cmd(
    model: str = typer.Option("e1", help="Shipped model name or model folder"),
    out: Path = typer.Option(Path("demo_out"), "-o", "--out", help="Where the .msq files and decoded clouds go"),
    refine: int = typer.Option(20, min=0, max=MAX_REFINE_STEPS, metavar="STEPS",
                               help="Also compress the KITTI submap with this many encode-time refinement steps "
                                    "(0: skip)"),
    device: str = device_option("encoder, refinement steps, decoder"),
):
    """Compress and decompress a simulated map (and the real KITTI submap when the shared folder is present)."""
    from mapsqueeze.demo import run_demo

    results = run_demo(model, out, progress=lambda m: console.print(f"[dim]{m}"), refine_steps=refine,
                       device=device)
    table = Table(title=f"mapsqueeze demo, model {model}")
    table.add_column("")
    for r in results:
        table.add_column(r.name, justify="right")
    rows = {
        "input points": lambda r: f"{r.n_points:,}",
        "compressed size": lambda r: f"{r.n_bytes:,} B",
        "bits per point": lambda r: f"{r.metrics.bpp:.4f}",
        "decoded points": lambda r: f"{r.n_decoded:,}",
        "D_e (m)": lambda r: f"{r.metrics.d_e:.4f}",
        "D_perp (m)": lambda r: f"{r.metrics.d_perp:.4f}",
        "IoU": lambda r: f"{r.metrics.iou:.3f}",
        "compress (s)": lambda r: f"{r.compress_s:.2f}",
        "decompress (s)": lambda r: f"{r.decompress_s:.2f}",
    }
    for label, cell in rows.items():
        table.add_row(label, *(cell(r) for r in results))
    print_table(table)
    console.print(f"files in {out}/ (.msq containers, decoded PLYs)")
