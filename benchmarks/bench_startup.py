"""Start-up of a `mapsqueeze` command as issue 16 measures it: CPU seconds of the cold command minus those of the
same command repeated warm in the same process (imports, model, compiled kernels; the tile's own work cancels out).

    .venv/bin/python benchmarks/bench_startup.py ../shared/data/real/submaps/kitti_hdl64_6scans.ply --runs 10

Each run is a fresh process (`--child`) that calls `cli.main` with `compress MAP -o OUT --workers 1`, once cold and
`--warm` times more, and prints its process CPU seconds; the parent prints every run and the median. The
environment is passed on as it is (`OMP_NUM_THREADS=1` before the command keeps the k-d tree searches on one thread).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time


def child(source: str, out: str, warm: int) -> None:
    from mapsqueeze.cli import main

    def run() -> None:
        sys.argv = ["mapsqueeze", "compress", source, "-o", out, "--workers", "1"]
        try:
            main()
        except SystemExit as exc:
            if exc.code not in (0, None):
                raise
    run()
    cold = time.process_time()
    warm_runs = []
    for _ in range(warm):
        start = time.process_time()
        run()
        warm_runs.append(time.process_time() - start)
    print(json.dumps({"cold_cpu_s": cold, "warm_cpu_s": warm_runs, "startup_cpu_s": cold - min(warm_runs)}),
          file=sys.__stderr__)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("map", help="point cloud to compress (one tile shows the start-up best)")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--warm", type=int, default=3, help="warm repeats per run (the fastest counts)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.map, args.out, args.warm)
        return
    startups = []
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as folder:
        for run in range(args.runs):
            done = subprocess.run([sys.executable, __file__, args.map, "--child", "--warm", str(args.warm),
                                   "--out", os.path.join(folder, "out.msq")],
                                  capture_output=True, text=True, check=True)
            row = json.loads(done.stderr.strip().splitlines()[-1])
            startups.append(row["startup_cpu_s"])
            print(f"run {run + 1}: cold {row['cold_cpu_s']:.3f} CPU-s, warm {min(row['warm_cpu_s']):.3f}, "
                  f"start-up {row['startup_cpu_s']:.3f} (load {os.getloadavg()[0]:.1f})", flush=True)
    print(f"start-up CPU-s: {min(startups):.2f}-{max(startups):.2f}, median {statistics.median(startups):.2f}, "
          f"{sum(value <= 1.0 for value in startups)} of {len(startups)} runs within 1 CPU-s")


if __name__ == "__main__":
    main()
