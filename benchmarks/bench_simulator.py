"""Simulator throughput: submaps per minute for a given sensor/preset mix and number of worker processes.

    .venv/bin/python benchmarks/bench_simulator.py --submaps 20 --workers 2 --sensor hdl64 --preset urban

Writes the dataset to a temporary directory (deleted afterwards) and prints one markdown table row: wall time,
submaps per minute, mean scans aggregated and points per submap. (Embree's ray casting runs on all cores by itself
through OpenMP; worker processes get one thread each; set OMP_NUM_THREADS=1 to measure one core with --workers 1.)
"""

import argparse
import os
import sys
import tempfile
import time

import numpy as np

from mapsqueeze.data import read_dataset
from mapsqueeze.data.simulator import SimulationConfig, simulate_dataset


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--submaps", type=int, default=20)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--sensor", default="hdl64")
    parser.add_argument("--preset", default="urban")
    parser.add_argument("--scans", default="1-100", help="MIN-MAX scans per submap")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    low, _, high = args.scans.partition("-")
    config = SimulationConfig(n_submaps=args.submaps, sensors=tuple(args.sensor.split(",")),
                              presets=tuple(args.preset.split(",")), seed=args.seed,
                              scans_per_submap=(int(low), int(high or low)))
    with tempfile.TemporaryDirectory() as directory:
        start = time.perf_counter()
        simulate_dataset(directory, config, args.workers)
        wall = time.perf_counter() - start
        dataset = read_dataset(directory)
        scans = [entry["n_scans"] for meta in dataset.sources.values() for entry in meta["submaps"]]
        points = [record.n_points for record in dataset.records]
    threads = "1 per worker" if args.workers > 1 else os.environ.get("OMP_NUM_THREADS", "all")
    print("| sensor | preset | workers | OpenMP threads | submaps | wall (min) | submaps / min | scans / submap "
          "| points / submap |")
    print("|---|---|---|---|---|---|---|---|---|")
    print(f"| {args.sensor} | {args.preset} | {args.workers} | {threads} | {len(points)} | {wall / 60:.1f} "
          f"| {len(points) / (wall / 60):.1f} | {np.mean(scans):.1f} | {np.mean(points):,.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
