"""The benchmark's HTML report (report.html beside results.csv): the summary and per-cloud tables, the plots, and a
link per cloud to a viewer page of its mapsqueeze result (views/<cloud>.html)."""

from __future__ import annotations

import html
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mapsqueeze.metrics import Metrics

VIEWS_FOLDER = "views"
BENCH_VIEW_MAX_POINTS = 200_000
"""Points drawn per cloud in the benchmark's viewer pages (about 4.3 MB a page with the original)."""
_SUMMARY_COLUMNS = (("codec", "codec", "{}"), ("setting", "setting", "{}"), ("clouds", "clouds", "{}"),
                    ("bpp", "bpp", "{:.4f}"), ("d_e", "D_e (m)", "{:.4f}"), ("d_perp", "D_perp (m)", "{:.4f}"),
                    ("iou", "IoU", "{:.3f}"), ("encode_s", "encode (s)", "{:.2f}"), ("decode_s", "decode (s)", "{:.2f}"))
_ROW_COLUMNS = (("cloud", "cloud", "{}"), ("codec", "codec", "{}"), ("setting", "setting", "{}"),
                ("n_points", "points", "{:,}"), ("n_bytes", "bytes", "{:,}"), ("bpp", "bpp", "{:.4f}"),
                ("d_e", "D_e (m)", "{:.4f}"), ("d_perp", "D_perp (m)", "{:.4f}"), ("iou", "IoU", "{:.3f}"),
                ("n_decoded", "decoded points", "{:,}"))
_STYLE = """body { font: 13px/1.4 system-ui, sans-serif; margin: 16px; color: #1d2430; }
table { border-collapse: collapse; margin: 8px 0 16px; } td, th { border: 1px solid #ccd2dc; padding: 2px 6px; }
th { background: #eef1f5; } td.n { text-align: right; } img { max-width: 48%; margin: 4px; border: 1px solid #ccd2dc; }"""


def view_file_name(cloud: str) -> str:
    """views/<cloud>.html, the cloud's name made safe for a file name (dataset/cloud -> dataset__cloud)."""
    return f"{VIEWS_FOLDER}/{re.sub(r'[^A-Za-z0-9._-]+', '__', cloud)}.html"


def cloud_view_writer(out_dir: Path) -> Callable[..., None]:
    """A `run_benchmark` on_decoded callback writing `write_cloud_view` pages: for each cloud, of the first mapsqueeze
    result of the run."""
    viewed: set[str] = set()

    def on_decoded(cloud: str, codec: str, setting: str, msq: bytes, original: np.ndarray, decoded: np.ndarray,
                   metrics: Metrics) -> None:
        if codec == "mapsqueeze" and cloud not in viewed:
            viewed.add(cloud)
            write_cloud_view(out_dir, cloud, setting, msq, original, decoded, metrics)

    return on_decoded


def write_cloud_view(out_dir: Path, cloud: str, setting: str, msq: bytes, original: np.ndarray, decoded: np.ndarray,
                     metrics: Metrics) -> Path:
    """Write out_dir/views/<cloud>.html, the viewer page of one cloud's mapsqueeze result at `setting`."""
    from mapsqueeze.view import CloudInput, ViewInput, write_view

    path = Path(out_dir) / view_file_name(cloud)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_view(ViewInput(f"{cloud} (mapsqueeze {setting})", msq, original=CloudInput(original),
                         decoded=CloudInput(decoded), metrics=metrics), path, BENCH_VIEW_MAX_POINTS)
    return path


def _table(records: list[dict], columns: tuple) -> str:
    head = "".join(f"<th>{html.escape(title)}</th>" for _, title, _ in columns)
    lines = [f"<table><tr>{head}</tr>"]
    for record in records:
        cells = []
        for key, _, form in columns:
            value = record[key]
            numeric = isinstance(value, (int, float))
            cells.append(f"<td{' class=n' if numeric else ''}>{form.format(value)}</td>")
        lines.append(f"<tr>{''.join(cells)}</tr>")
    return "\n".join(lines + ["</table>"])


def write_report(out_dir: Path, rows: list[dict], summary: list[dict]) -> Path:
    """out_dir/report.html (atomically) from the benchmark's rows and summary, the rd*.png plots and the viewer pages
    found in out_dir; links are relative, so the folder can be moved as a whole."""
    from mapsqueeze.io import atomic_write_bytes

    out_dir = Path(out_dir)
    clouds = sorted({r["cloud"] for r in rows})
    views = {c: view_file_name(c) for c in clouds if (out_dir / view_file_name(c)).is_file()}
    plots = sorted(p.name for p in out_dir.glob("rd*.png"))
    view_rows = [{"cloud": html.escape(c), "view": f'<a href="{html.escape(views[c])}">{html.escape(views[c])}</a>'}
                 for c in clouds if c in views]
    escaped_rows = [{k: html.escape(v) if isinstance(v, str) else v for k, v in r.items()} for r in rows]
    escaped_summary = [{k: html.escape(v) if isinstance(v, str) else v for k, v in s.items()} for s in summary]
    parts = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8"><title>mapsqueeze benchmark</title>',
             f"<style>{_STYLE}</style></head><body>", "<h1>mapsqueeze benchmark</h1>",
             f"<p>{len(clouds)} clouds, {len(rows)} results (results.csv, results.md beside this page).</p>",
             "<h2>Mean over the clouds</h2>", _table(escaped_summary, _SUMMARY_COLUMNS), "<h2>Plots</h2>",
             "".join(f'<img src="{html.escape(p)}" alt="{html.escape(p)}">' for p in plots),
             "<h2>Views</h2>", "<p>Each cloud's first mapsqueeze result over its original in the viewer "
             "(docs/viewer.md).</p>", _table(view_rows, (("cloud", "cloud", "{}"), ("view", "page", "{}"))),
             "<h2>Per cloud</h2>",
             _table(sorted(escaped_rows, key=lambda r: (r["cloud"], r["codec"], r["bpp"])), _ROW_COLUMNS),
             "</body></html>"]
    path = out_dir / "report.html"
    atomic_write_bytes(path, "\n".join(parts).encode("utf-8"))
    return path
