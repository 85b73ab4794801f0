"""`mapsqueeze demo`: the README's main job on the embedded default model and data."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from mapsqueeze.cli.app import app

console = Console()


@app.command("demo")
def demo_cmd(
    model: str = typer.Option("e1", help="Shipped model name or model folder"),
    out: Path = typer.Option(Path("demo_out"), "-o", "--out", help="Where the .msq files and decoded clouds go"),
):
    """Compress and decompress a simulated map (and the real KITTI submap when ../shared is present)."""
    from mapsqueeze.demo import run_demo

    results = run_demo(model, out, progress=lambda m: console.print(f"[dim]{m}"))
    table = Table(title=f"mapsqueeze demo, model {model}")
    for col in ("map", "points", "compressed", "bpp", "decoded pts", "D_e (m)", "D_perp (m)", "IoU",
                "compress (s)", "decompress (s)"):
        table.add_column(col, justify="right")
    for r in results:
        m = r.metrics
        table.add_row(r.name, f"{r.n_points:,}", f"{r.n_bytes:,} B", f"{m.bpp:.4f}", f"{r.n_decoded:,}",
                      f"{m.d_e:.4f}", f"{m.d_perp:.4f}", f"{m.iou:.3f}", f"{r.compress_s:.2f}",
                      f"{r.decompress_s:.2f}")
    console.print(table)
    console.print(f"files in {out}/ (.msq containers, decoded PLYs)")
