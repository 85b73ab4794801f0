"""How closely this code reproduces the reference checkpoints' golden outputs on the KITTI submap, per model.

Prints, for e0..e3: the decoder's largest difference from the golden decoded points, the embedding-feature
difference |ours - golden| (mean, 99th percentile, max over all n_emb x 3 values) and the end-to-end D_e against
the reference's (golden/README.md), from the golden embedding and from our encoder. These are the figures that
tests/test_model.py bounds (FEATURE_DIFF_BOUNDS, MEASURED_DE_DEVIATION).

    .venv/bin/python benchmarks/reference_golden.py
"""

import tempfile
from pathlib import Path

import numpy as np
import torch

from mapsqueeze.io import read_points
from mapsqueeze.metrics import d_euclidean
from mapsqueeze.model import import_reference, load_model, save_model
from mapsqueeze.shared import real_submaps_dir, reference_checkpoints_dir

REFERENCE_DE_M = {"e0": 0.0926, "e1": 0.0782, "e2": 0.0577, "e3": 0.0564}


def main() -> None:
    reference = reference_checkpoints_dir()
    full = read_points(real_submaps_dir() / "kitti_hdl64_6scans.ply")
    print("model | decoder max diff | feature diff mean / p99 / max | D_e golden embedding | D_e our encoder")
    for rate, reference_d_e in REFERENCE_DE_M.items():
        golden = np.load(reference / "golden" / f"{rate}_kitti_hdl64_6scans.npz")
        network = import_reference(reference / rate).eval()
        with torch.no_grad():
            decoded, _ = network.decoder(torch.from_numpy(golden["embedding_points"]),
                                         torch.from_numpy(golden["embedding_features"]))
            _, features = network.encoder(torch.from_numpy(golden["input_points_normalized"]))
        decoder_diff = np.abs(decoded.numpy() - golden["decoded_points_normalized"]).max()
        difference = np.abs(features.half().float().numpy() - golden["embedding_features"])
        scale, origin = float(golden["normalizer_scale"]), golden["normalizer_min"].reshape(3)
        with tempfile.TemporaryDirectory() as folder:
            save_model(network, Path(folder) / rate)
            model = load_model(Path(folder) / rate)
        from_golden = model.decode(golden["embedding_points"] * np.float32(scale), golden["embedding_features"])
        embedding = model.encode(golden["input_points_normalized"] * np.float32(scale))
        ours = model.decode(embedding.points.astype(np.float16).astype(np.float32),
                            embedding.features.astype(np.float16).astype(np.float32))
        d_e = [d_euclidean(full, cloud.astype(np.float64) + origin) for cloud in (from_golden, ours)]
        print(f"{rate} | {decoder_diff:.1e} | {difference.mean():.4f} / {np.percentile(difference, 99):.4f} / "
              f"{difference.max():.4f} | " + " | ".join(f"{v:.5f} m ({100 * (v / reference_d_e - 1):+.2f} %)"
                                                      for v in d_e))


if __name__ == "__main__":
    main()
