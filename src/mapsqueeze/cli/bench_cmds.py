"""`mapsqueeze bench`: the rate-distortion benchmark against the classical codecs."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

import typer

from mapsqueeze.cli.app import app, device_option, make_console
from mapsqueeze.errors import MapsqueezeError

console = make_console()


def parse_refine_steps(text: str) -> list[int]:
    """'0,20' -> [0, 20] (checked by run_benchmark), or a MapsqueezeError."""
    try:
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise MapsqueezeError(f"--refine: expected comma-separated step counts such as 0,20, got {text!r}") from None


def parse_codecs(text: str) -> list[str]:
    """'gpcc, draco' -> ['gpcc', 'draco'], or a MapsqueezeError naming an unknown codec and the known ones."""
    from mapsqueeze.benchmark.variants import known_codecs

    codecs = [c.strip() for c in text.split(",") if c.strip()]
    unknown = [c for c in codecs if c not in known_codecs()]
    if unknown or not codecs:
        raise MapsqueezeError(f"--codecs: unknown codec {unknown[0] if unknown else text!r} "
                              f"(known: {', '.join(known_codecs())})")
    return codecs


@app.command("bench")
def bench_cmd(
    inputs: list[Path] = typer.Argument(..., help="Dataset folders (manifest.json), folders of clouds, or files"),
    codecs: str = typer.Option("mapsqueeze,depoco-ref,draco,octree,octree-ac,gpcc",
                               help="Comma-separated codecs: mapsqueeze, depoco-ref and the classical baselines"),
    out: Path = typer.Option(Path("results"), "-o", "--out", help="Output folder (CSV, markdown, plots)"),
    models: Optional[str] = typer.Option(None, help="mapsqueeze models (names or folders, comma-separated); "
                                                    "default: every shipped model"),
    precision: str = typer.Option("q", help="Embedding precision of mapsqueeze: q, f16 or f32"),
    split: str = typer.Option("test", help="Split of dataset folders to run on: train, val, test or all (a held-out dataset)"),
    refine: str = typer.Option("0", help="Encode-time refinement steps of the learned codecs, comma-separated "
                                         "(each a setting of its own, e.g. 0,20; 0 is the paper's encoder)"),
    every: int = typer.Option(1, min=1, help="Run on every N-th cloud only (first, N+1-th, ...), e.g. for slow settings"),
    fresh: bool = typer.Option(False, "--fresh", help="Ignore results already in the output folder (default: keep "
                                                      "them and run only the missing cloud/codec/setting rows)"),
    device: str = device_option("of the mapsqueeze and depoco-ref rows: encoder, refinement steps, decoder; "
                                "results already in the folder are kept whatever ran them"),
):
    """Run every codec and setting on every cloud: bytes, bpp, D_e, D_perp, IoU, encode/decode seconds."""
    from mapsqueeze.benchmark import run_benchmark
    from mapsqueeze.benchmark.report import summarise
    from mapsqueeze.view.report import cloud_view_writer, write_report

    for path in inputs:
        if not path.exists():
            raise MapsqueezeError(f"{path}: no such file or folder")
    codec_names = parse_codecs(codecs)
    refine_steps = tuple(parse_refine_steps(refine))
    with console.status("benchmark") as status:
        rows = run_benchmark(inputs, codec_names, out,
                             models=[m.strip() for m in models.split(",")] if models else None,
                             precision=precision, split=split, log=lambda m: console.print(f"[yellow]{m}"),
                             progress=lambda m: status.update(m), fresh=fresh, refine=refine_steps, every=every,
                             on_decoded=cloud_view_writer(out), device=device)
    write_report(out, [dataclasses.asdict(r) for r in rows], summarise(rows))
    console.print((out / "results.md").read_text(), markup=False, highlight=False)
    console.print(f"{len(rows)} results -> {out}/results.csv, results.md, run.json, rd*.png, report.html")
