"""The markdown report of a benchmark (results.md): means per setting, every learned row against the full classical
front of its cloud per metric, wins and losses per setting and per band of cloud size, and the learned codecs
against the reference checkpoints."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from mapsqueeze.benchmark.fronts import METRICS, Comparison, classical_codecs, compare
from mapsqueeze.benchmark.rows import Row

SIZE_BANDS = (20_000, 50_000)
"""Cloud sizes (points) separating the bands of `size_band_comparison`: a 40 m submap of one 32-beam sweep has
~12k points, one 64/128-beam scan 30-60k, an aggregated map 50-250k."""
TARGET_D_E_RATIO = 0.8
"""The project's goal against the full classical front at equal bpp: D_e at most this fraction of the front's, and
IoU at least the front's, on clouds of TARGET_MIN_POINTS or more at rates in TARGET_BPP_RANGE."""
TARGET_MIN_POINTS = 20_000
TARGET_BPP_RANGE = (0.05, 0.6)


def summarise(rows: list[Row]) -> list[dict]:
    """Mean of every metric per (codec, setting) over the clouds, by codec then bpp."""
    groups: dict[tuple[str, str], list[Row]] = {}
    for r in rows:
        groups.setdefault((r.codec, r.setting), []).append(r)
    out = []
    for (codec, setting), rs in groups.items():
        out.append({"codec": codec, "setting": setting, "clouds": len(rs),
                    **{k: float(np.mean([getattr(r, k) for r in rs]))
                       for k in ("bpp", "d_e", "d_perp", "iou", "n_decoded", "encode_s", "decode_s")}})
    return sorted(out, key=lambda s: (s["codec"], s["bpp"]))


def meets_target(c: Comparison) -> bool:
    """D_e <= TARGET_D_E_RATIO x the front's and IoU >= the front's at the row's bpp."""
    return c.within_range() and c.ratio("d_e") <= TARGET_D_E_RATIO and c.difference("iou") >= 0


def in_target_scope(r: Row) -> bool:
    """A row the target speaks about: a cloud of TARGET_MIN_POINTS or more at a rate inside TARGET_BPP_RANGE."""
    return r.n_points >= TARGET_MIN_POINTS and TARGET_BPP_RANGE[0] <= r.bpp <= TARGET_BPP_RANGE[1]


def summary_table(rows: list[Row]) -> list[str]:
    lines = ["Means over the clouds per codec and setting.", "",
             "| codec | setting | clouds | bpp | D_e (m) | D_perp (m) | IoU | decoded points | encode (s) | decode (s) |",
             "|---" * 10 + "|"]
    for s in summarise(rows):
        lines.append(f"| {s['codec']} | {s['setting']} | {s['clouds']} | {s['bpp']:.4f} | {s['d_e']:.4f} | "
                     f"{s['d_perp']:.4f} | {s['iou']:.3f} | {s['n_decoded']:,.0f} | {s['encode_s']:.2f} | "
                     f"{s['decode_s']:.2f} |")
    return lines


def _verdict(c: Comparison) -> str:
    if not c.within_range():
        return "outside the front's bpp range"
    d_e = "wins" if c.wins("d_e") else "loses"
    iou = "wins" if c.wins("iou") else "loses"
    if not in_target_scope(c.row):
        return f"D_e {d_e}, IoU {iou}"
    return f"D_e {d_e}, IoU {iou}; target {'met' if meets_target(c) else 'missed'}"


def front_name(rows: list[Row]) -> str:
    """The classical front these rows make: "the full classical front (codecs)" when every registered baseline ran
    on every cloud with a learned row, else the codecs that ran and those that did not, and the clouds a codec that
    ran elsewhere did not run on (a front of fewer codecs is easier to beat)."""
    registered = classical_codecs()
    ran = [codec for codec in registered if any(r.codec == codec for r in rows)]
    if not ran:
        return f"a classical front (none ran of {', '.join(registered)})"
    learned_clouds = dict.fromkeys(r.cloud for r in rows if r.codec not in registered)
    gaps = []
    for cloud in learned_clouds:
        missing = [codec for codec in ran if not any(r.cloud == cloud and r.codec == codec for r in rows)]
        if missing:
            gaps.append(f"{', '.join(missing)} not run on {cloud}")
    gaps_text = f"; {'; '.join(gaps)}" if gaps else ""
    if len(ran) == len(registered):
        return (f"the classical front of {', '.join(ran)}{gaps_text}" if gaps
                else f"the full classical front ({', '.join(ran)})")
    missing = [codec for codec in registered if codec not in ran]
    return f"the classical front of {', '.join(ran)} only ({', '.join(missing)} not run{gaps_text})"


def front_table(comparisons: list[Comparison], front: str) -> list[str]:
    """Every learned row against `front` (`front_name`) of its cloud at the same bpp, per metric."""
    if not comparisons:
        return []
    lines = ["", f"Against {front}: every setting, Pareto front per "
             "metric, log-bpp interpolation, of the same cloud at the same bpp. D_e and D_perp ratio: below 1 is "
             f"better; IoU difference: above 0 is better. Target: D_e ratio <= {TARGET_D_E_RATIO} and IoU difference "
             ">= 0.", "",
             "| cloud | points | codec | setting | bpp | D_e (m) | front D_e (m) | D_e ratio | D_perp ratio | IoU | "
             "front IoU | IoU difference | decoded points | verdict |", "|---" * 14 + "|"]
    for c in comparisons:
        r = c.row
        if c.within_range():
            cells = (f"{c.front['d_e']:.4f} | {c.ratio('d_e'):.3f} | {c.ratio('d_perp'):.3f} | {r.iou:.3f} | "
                     f"{c.front['iou']:.3f} | {c.difference('iou'):+.3f}")
        else:
            cells = f" | | | {r.iou:.3f} | |"
        lines.append(f"| {r.cloud} | {r.n_points:,} | {r.codec} | {r.setting} | {r.bpp:.4f} | {r.d_e:.4f} | {cells} | "
                     f"{r.n_decoded:,} | {_verdict(c)} |")
    return lines


def wins_table(comparisons: list[Comparison], front: str) -> list[str]:
    """Per learned setting: clouds where it beats `front` per metric, and where it meets the target."""
    groups: dict[tuple[str, str], list[Comparison]] = {}
    for c in comparisons:
        groups.setdefault((c.row.codec, c.row.setting), []).append(c)
    if not groups:
        return []
    lines = ["", f"Wins and losses against {front} per setting (clouds where it is better at equal "
             "bpp / clouds inside the front's bpp range); target rows: clouds of "
             f"{TARGET_MIN_POINTS:,} points or more at {TARGET_BPP_RANGE[0]}-{TARGET_BPP_RANGE[1]} bpp.", "",
             "| codec | setting | D_e better | D_perp better | IoU better | mean D_e ratio | mean IoU difference | "
             "target met (target rows) |", "|---" * 8 + "|"]
    for (codec, setting), cs in sorted(groups.items()):
        inside = [c for c in cs if c.within_range()]
        scoped = [c for c in inside if in_target_scope(c.row)]
        counts = [f"{sum(c.wins(m.key) for c in inside)} / {len(inside)}" for m in METRICS]
        ratio = f"{np.mean([c.ratio('d_e') for c in inside]):.3f}" if inside else ""
        iou = f"{np.mean([c.difference('iou') for c in inside]):+.3f}" if inside else ""
        lines.append(f"| {codec} | {setting} | {' | '.join(counts)} | {ratio} | {iou} | "
                     f"{sum(map(meets_target, scoped))} / {len(scoped)} |")
    return lines


def margins_table(comparisons: list[Comparison], front: str) -> list[str]:
    """Compact: one line per cloud and codec, one column per setting: bpp, D_e ratio and IoU difference against
    `front` (bold where the target is met)."""
    settings = list(dict.fromkeys(c.row.setting for c in comparisons))
    cells: dict[tuple[str, int, str], dict[str, str]] = {}
    for c in comparisons:
        r = c.row
        text = (f"{r.bpp:.3f}: {c.ratio('d_e'):.2f} / {c.difference('iou'):+.2f}" if c.within_range()
                else f"{r.bpp:.3f}: outside")
        cells.setdefault((r.cloud, r.n_points, r.codec), {})[r.setting] = f"**{text}**" if meets_target(c) else text
    if not cells:
        return []
    lines = ["", f"Margins per cloud: bpp: D_e ratio / IoU difference against {front} at that bpp "
             "(bold: target met).", "",
             "| cloud | points | codec | " + " | ".join(settings) + " |", "|---" * (3 + len(settings)) + "|"]
    for (cloud, n_points, codec), by_setting in cells.items():
        lines.append(f"| {cloud} | {n_points:,} | {codec} | " + " | ".join(by_setting.get(s, "") for s in settings)
                     + " |")
    return lines


def size_band_comparison(comparisons: list[Comparison]) -> list[str]:
    """Markdown lines: each learned setting's mean D_e change against the front, and its wins, per band of cloud
    size (SIZE_BANDS; sparse clouds are where the learned codecs lose)."""
    edges = (0, *SIZE_BANDS, np.inf)
    bands = [f"{lo:,} - {hi:,}" if np.isfinite(hi) else f">= {lo:,}" for lo, hi in zip(edges, edges[1:])]
    changes: dict[tuple[str, str], list[list[float]]] = {}
    for c in comparisons:
        if c.within_range():
            band = int(np.searchsorted(SIZE_BANDS, c.row.n_points, side="right"))
            changes.setdefault((c.row.codec, c.row.setting), [[] for _ in bands])[band].append(c.ratio("d_e") - 1)
    if not changes:
        return []
    lines = ["", "By cloud size: mean D_e change against the front at the same bpp (clouds better / clouds) per band "
             "of points in the cloud.", "",
             "| codec | setting | " + " | ".join(f"{band} points" for band in bands) + " |",
             "|---" * (2 + len(bands)) + "|"]
    for (codec, setting), per_band in sorted(changes.items()):
        cells = [f"{np.mean(v):+.1%} ({sum(x < 0 for x in v)} / {len(v)})" if v else "" for v in per_band]
        lines.append(f"| {codec} | {setting} | " + " | ".join(cells) + " |")
    return lines


def reference_comparison(rows: list[Row]) -> list[str]:
    """Markdown lines: each mapsqueeze row against the depoco-ref D_e front on the same cloud at the same bpp, once
    as published (f16 embeddings) and once through every precision (our q coding of the reference networks)."""
    published = [replace(r, codec="depoco-ref f16") for r in rows
                 if r.codec == "depoco-ref" and r.setting.endswith(",f16")]
    against_published = compare(rows + published, ("depoco-ref f16",), ("mapsqueeze",))
    against_all = compare(rows, ("depoco-ref",), ("mapsqueeze",))
    if not any(c.within_range() for c in against_all):
        return []

    def cells(c: Comparison) -> str:
        if not c.within_range():
            return "outside its bpp range | |"
        return f"{c.front['d_e']:.4f} | {c.ratio('d_e') - 1:+.1%} |"

    lines = ["", "Per cloud: mapsqueeze against the front of depoco-ref (the reference checkpoints) on the same cloud, "
             "interpolated in log bpp: as published (f16 embeddings), and through every precision (with our q).", "",
             "| cloud | setting | bpp | D_e (m) | depoco-ref f16 D_e at this bpp (m) | change | "
             "depoco-ref (f16, q) D_e at this bpp (m) | change |", "|---" * 8 + "|"]
    for published_c, all_c in zip(against_published, against_all):
        r = all_c.row
        lines.append(f"| {r.cloud} | {r.setting} | {r.bpp:.4f} | {r.d_e:.4f} | {cells(published_c)} {cells(all_c)}")
    return lines


def markdown_report(rows: list[Row]) -> str:
    """The whole results.md text."""
    comparisons, front = compare(rows), front_name(rows)
    lines = [*summary_table(rows), *wins_table(comparisons, front), *margins_table(comparisons, front),
             *front_table(comparisons, front),
             *size_band_comparison(comparisons), *reference_comparison(rows)]
    return "\n".join(lines) + "\n"


def write_markdown(rows: list[Row], out_dir: Path) -> None:
    """results.md in out_dir (atomically)."""
    from mapsqueeze.io import atomic_output

    with atomic_output(out_dir / "results.md") as tmp:
        Path(tmp).write_text(markdown_report(rows))
