"""mapsqueeze rows of one or two `mapsqueeze bench` results.csv files next to the classical fronts of the last one:
per cloud and setting, bytes, bpp, D_e, D_perp, IoU and decoded count, with the classical front's D_e and IoU at the
same bpp (`baselines.rd.distortion_at`, linear in log bpp; IoU as the front of -IoU) and the ratios.

    mapsqueeze bench CLOUDS --codecs mapsqueeze -o results/bench_a          # e.g. one commit
    mapsqueeze bench CLOUDS --codecs mapsqueeze,octree,gpcc -o results/bench_b   # another, with the classical codecs
    .venv/bin/python benchmarks/compare_fronts.py results/bench_a/results.csv results/bench_b/results.csv
"""

import argparse
import csv
from pathlib import Path

import numpy as np

from mapsqueeze.baselines.rd import distortion_at
from mapsqueeze.benchmark.fronts import classical_codecs


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", type=Path, nargs="+", help="results.csv files; the last one holds the classical rows")
    args = parser.parse_args()
    tables = [read_rows(path) for path in args.results]
    classical = [row for row in tables[-1] if row["codec"] in classical_codecs()]
    print("| cloud | setting | run | bytes | bpp | D_e (m) | D_perp (m) | IoU | decoded | front D_e | D_e / front |"
          " front IoU | IoU / front |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for cloud in sorted({row["cloud"] for row in tables[-1]}):
        points = [r for r in classical if r["cloud"] == cloud]
        rates = np.array([float(r["bpp"]) for r in points])
        d_e = np.array([float(r["d_e"]) for r in points])
        iou = np.array([float(r["iou"]) for r in points])
        settings = sorted({r["setting"] for table in tables for r in table
                           if r["cloud"] == cloud and r["codec"] == "mapsqueeze"})
        for setting in settings:
            for run, table in zip(args.results, tables):
                for row in table:
                    if row["cloud"] != cloud or row["codec"] != "mapsqueeze" or row["setting"] != setting:
                        continue
                    bpp = float(row["bpp"])
                    front_d_e = float(distortion_at(rates, d_e, bpp)) if len(points) else float("nan")
                    front_iou = -float(distortion_at(rates, -iou, bpp)) if len(points) else float("nan")
                    print(f"| {cloud} | {setting} | {run.parent.name} | {int(row['n_bytes']):,} | {bpp:.3f} | "
                          f"{float(row['d_e']):.4f} | {float(row['d_perp']):.4f} | {float(row['iou']):.3f} | "
                          f"{int(row['n_decoded']):,} | {front_d_e:.4f} | {float(row['d_e']) / front_d_e:.2f} | "
                          f"{front_iou:.3f} | {float(row['iou']) / front_iou:.2f} |")


if __name__ == "__main__":
    main()
