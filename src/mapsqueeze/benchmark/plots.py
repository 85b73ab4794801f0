"""Rate-distortion plots of a benchmark: D_e, D_perp and IoU against bpp, one line per codec (mode)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapsqueeze.benchmark.fronts import METRICS, classical_codecs, front_indices
from mapsqueeze.benchmark.report import summarise
from mapsqueeze.benchmark.rows import Row

PER_CLOUD_PLOTS_UP_TO = 6
"""Benchmarks of at most this many clouds also get one rd_<cloud>.png per cloud."""


def series_name(result: dict) -> str:
    """Plot line of a result: a classical codec (with its mode, e.g. "gpcc trisoup"), or a learned codec at one
    embedding precision ("mapsqueeze q")."""
    if result["codec"] in classical_codecs():
        mode = result["setting"].split(",")[0]
        return f"{result['codec']} {mode.split('=', 1)[1]}" if mode.startswith("mode=") else result["codec"]
    return f"{result['codec']} {result['setting'].rsplit(',', 1)[-1]}"


def plot_rd(summary: list[dict], path: Path, title: str) -> None:
    """D_e, D_perp and IoU against bpp (log x), one line per series (the Pareto front of a classical codec's
    settings, every setting of a learned one) -> PNG at path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mapsqueeze.io import atomic_output

    classical = classical_codecs()
    fig, axes = plt.subplots(1, len(METRICS), figsize=(5 * len(METRICS), 4.2))
    for ax, metric in zip(axes, METRICS):
        for name in sorted({series_name(s) for s in summary}):
            pts = [s for s in summary if series_name(s) == name]
            bpp = np.array([s["bpp"] for s in pts])
            val = np.array([s[metric.key] for s in pts])
            if pts[0]["codec"] in classical and len(pts) > 2:
                keep = front_indices(bpp, val, metric)
                bpp, val = bpp[keep], val[keep]
            order = np.argsort(bpp)
            ax.plot(bpp[order], val[order], marker="o", markersize=4,
                    linestyle="--" if pts[0]["codec"] in classical else "-", label=name)
        ax.set_xscale("log")
        ax.set_xlabel("bits per point")
        ax.set_ylabel(metric.label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def write_plots(rows: list[Row], out_dir: Path, per_cloud: bool = True) -> None:
    """rd.png (means over the clouds) and, for benchmarks of up to PER_CLOUD_PLOTS_UP_TO clouds with per_cloud,
    rd_<cloud>.png."""
    plot_rd(summarise(rows), out_dir / "rd.png", f"mean over {len({r.cloud for r in rows})} clouds")
    clouds = sorted({r.cloud for r in rows})
    if per_cloud and len(clouds) <= PER_CLOUD_PLOTS_UP_TO:
        for cloud in clouds:
            plot_rd(summarise([r for r in rows if r.cloud == cloud]), out_dir / f"rd_{Path(cloud).name}.png", cloud)
