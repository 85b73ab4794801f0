"""The README's main job: compress and decompress a simulated map (and the real KITTI submap when the shared folder
is present, see mapsqueeze.shared) with a shipped model, and report size, bpp, D_e, D_perp and IoU."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapsqueeze.shared import real_submaps_dir

UTM_OFFSET_M = np.array([500000.123, 5600000.456, 110.0])
"""The demo map is placed at UTM-sized coordinates to exercise the float64 tile origins."""


@dataclass
class DemoResult:
    name: str
    n_points: int
    n_bytes: int
    n_decoded: int
    metrics: object  # mapsqueeze.metrics.Metrics
    compress_s: float
    decompress_s: float


def simulated_map(seed: int = 7, n_submaps: int = 4) -> np.ndarray:
    """A street map ~80 m long from the simulator (HDL-64E, urban), merged from consecutive submaps, in UTM."""
    from mapsqueeze.data.simulator.simulate import SimulationConfig, simulate_scene
    from mapsqueeze.geometry.voxel import voxel_filter

    config = SimulationConfig(n_submaps=n_submaps, submaps_per_scene=n_submaps, seed=seed, presets=("urban",),
                              sensors=("hdl64",), scans_per_submap=(20, 40))
    scene = simulate_scene(config, 0)
    merged = np.concatenate([s.points for s in scene.submaps])
    return voxel_filter(merged, 0.1) + UTM_OFFSET_M


def run_case(name: str, points: np.ndarray, model, out_dir: Path, refine_steps: int = 0) -> DemoResult:
    """Compress (with refine_steps of encode-time refinement) + decompress through the public API, write NAME.msq
    and the decoded PLY, evaluate."""
    from mapsqueeze.api import compress, decompress
    from mapsqueeze.io import atomic_write_bytes, write_points
    from mapsqueeze.metrics import evaluate

    t0 = time.perf_counter()
    data = compress(points, model=model, refine_steps=refine_steps)
    t1 = time.perf_counter()
    decoded = decompress(data, model=model)
    t2 = time.perf_counter()
    atomic_write_bytes(out_dir / f"{name}.msq", data)
    write_points(out_dir / f"{name}_decoded.ply", decoded)
    metrics = evaluate(points, decoded, n_bytes=len(data))
    return DemoResult(name, len(points), len(data), len(decoded), metrics, t1 - t0, t2 - t1)


def run_demo(model_name: str, out_dir: Path, progress=print, refine_steps: int = 0, device: str = "cpu"
             ) -> list[DemoResult]:
    """The simulated map and the real KITTI submap with the paper's encoder, the network on `device`
    (`load_model`); with refine_steps > 0 the KITTI submap once more with that much encode-time refinement."""
    from mapsqueeze.io import read_points, write_points
    from mapsqueeze.model import load_model

    model = load_model(model_name, device)
    out_dir.mkdir(parents=True, exist_ok=True)
    progress(f"model {model.model_id} (r_s = {model.config.subsampling_dist:g} m)")
    progress("simulating a street map (HDL-64E, 4 submaps) ...")
    sim = simulated_map()
    write_points(out_dir / "simulated_map.ply", sim)
    results = [run_case("simulated_map", sim, model, out_dir)]
    real_submap = real_submaps_dir() / "kitti_hdl64_6scans.ply"
    if real_submap.is_file():
        kitti = read_points(real_submap)
        results.append(run_case("kitti_hdl64_6scans", kitti, model, out_dir))
        if refine_steps:
            progress(f"KITTI submap again with {refine_steps} refinement steps ...")
            results.append(run_case(f"kitti_refine{refine_steps}", kitti, model, out_dir,
                                    refine_steps))
    else:
        progress(f"{real_submap} not found: real-data case skipped")
    return results
