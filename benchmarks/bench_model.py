"""Speed and memory of the network on CPU (issue targets: encode < 0.3 s, decode to ~300k points < 0.7 s, one
training step < 1.5 s, peak training memory < 6 GB for a 40 m submap with 30k input points at r_s = 3.0 m).

    .venv/bin/python benchmarks/bench_model.py [--rate e0] [--repeats 5] [--threads 2]
Uses the real KITTI submap from the shared folder (mapsqueeze.shared) when present, else a synthetic street patch.
"""

import argparse
import resource
import time

import numpy as np
import torch

from mapsqueeze.geometry.threads import set_threads
from mapsqueeze.model import CompressionModel, ModelConfig, build_model
from mapsqueeze.model.loss import depoco_loss
from mapsqueeze.shared import real_submaps_dir

REAL = real_submaps_dir() / "kitti_hdl64_6scans.ply"


def load_cloud(n: int) -> tuple[np.ndarray, str]:
    if REAL.is_file():
        from mapsqueeze.io import read_points

        pts, name = read_points(REAL), REAL.name
    else:
        rng = np.random.default_rng(0)
        pts = np.c_[rng.random((120000, 2)) * 40, rng.normal(0, 0.05, 120000)]
        name = "synthetic plane"
    pts = pts - pts.min(axis=0)
    keep = np.random.default_rng(0).choice(len(pts), min(n, len(pts)), replace=False)
    return pts[keep].astype(np.float32), name


def timed(fn, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rate", default="e0")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    set_threads(args.threads)
    cloud, name = load_cloud(30000)
    network = build_model(ModelConfig.for_rate(args.rate))
    model = CompressionModel.from_network(network, args.rate, "")
    emb = model.encode(cloud)
    model.decode(emb.points, emb.features)
    t_enc = timed(lambda: model.encode(cloud), args.repeats)
    t_dec = timed(lambda: model.decode(emb.points, emb.features), args.repeats)
    n_out = len(model.decode(emb.points, emb.features))
    network.train()
    x = torch.from_numpy(cloud / 40.0)

    def step():
        out, inter, _ = network(x)
        loss, _ = depoco_loss(x, out, inter)
        loss.backward()

    t_step = timed(step, args.repeats)
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    print(f"cloud: {name}, 30,000 input points, rate {args.rate}, torch threads {args.threads}")
    print(f"encode:        {t_enc:.3f} s  ({len(emb.points)} embedding points)")
    print(f"decode:        {t_dec:.3f} s  ({n_out:,} output points)")
    print(f"training step: {t_step:.3f} s  (forward + loss with intermediate terms + backward)")
    print(f"peak RSS:      {peak_gb:.2f} GB")


if __name__ == "__main__":
    main()
