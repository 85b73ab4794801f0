"""Drive a simulated car through procedural scenes and build submap datasets exactly like real ones.

Per scene: build the scene, drive its main street at a realistic speed (with stops), record 10 Hz sweeps from
one sensor unit, and for each key pose (every 15 m, `mapping.submap_centers`) aggregate a random number of
scans (1 to ~100, at a random stride) with slightly wrong poses (`mapping.aggregate_map`: 2-20 m range filter,
10 cm voxel filter), then crop the 40 x 40 x 15 m submap (`mapping.crop_submap`). Few-scan submaps keep ring
patterns and occlusion shadows; many-scan submaps are dense, as in the paper's whole-sequence maps. Each point
carries the mean intensity of its voxel's returns and their most frequent semantic label and instance id
(`aggregate`), stored as the submap's `intensity`, `label` and `instance` fields.

Every random draw comes from generators seeded by (seed, scene, ...), so a dataset depends only on its
configuration, not on the number of worker processes or the order they finish in. The attributes draw from
generators of their own: the geometry is the same whether or not they are simulated.
"""

import multiprocessing
import os
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from mapsqueeze.data.mapping import (
    MAX_RANGE_M,
    SPLITS,
    VALIDATION_EVERY,
    Submap,
    crop_mask,
    range_mask,
    submap_bounds,
    submap_centers,
    write_dataset,
)
from mapsqueeze.data.simulator.aggregate import aggregate_labelled_map
from mapsqueeze.data.simulator.presets import get_preset
from mapsqueeze.data.simulator.raycast import Raycaster
from mapsqueeze.data.simulator.reflectance import face_reflectivity
from mapsqueeze.data.simulator.scene import Scene, build_scene
from mapsqueeze.data.simulator.sensors import SensorInstance, get_sensor
from mapsqueeze.data.simulator.shapes import Semantic
from mapsqueeze.errors import SimulationError

SCAN_RATE_HZ = 10.0
SUBMAP_SPACING_M = 15.0
WINDOW_MARGIN_M = 30.0
"""Drive before the first and after the last key pose, so that scan windows have scans on both sides."""

ATTRIBUTE_STREAM = 2
"""Seed component of the attribute generators: (seed, scene, 2) draws reflectivities, (seed, scene, 2, scan)
intensity noise; the geometry draws from (seed, scene) and (seed, scene, 1, scan)."""

MAX_WINDOW_M = 60.0
"""Scans more than ~30 m from the key pose add nothing to its 40 m box; strides keep windows within this span."""


@dataclass(frozen=True)
class SimulationConfig:
    """What to simulate. Each scene draws its preset and sensor from the given lists."""

    n_submaps: int = 200
    sensors: tuple[str, ...] = ("hdl64",)
    presets: tuple[str, ...] = ("urban",)
    seed: int = 0
    submaps_per_scene: int = 5
    scans_per_submap: tuple[int, int] = (1, 100)  # drawn log-uniformly
    strides: tuple[int, ...] = (1, 1, 2, 3, 5, 10)  # scan subsampling at 10 Hz, drawn uniformly (then capped)
    pose_noise: bool = True  # aggregate with slightly wrong poses, like estimated (KISS-ICP / SLAM) ones
    stops: bool = True  # the car sometimes stops (traffic lights): many scans from one place
    split: str = ""  # one split for every submap (train / val / test); empty: every 10th scene to val

    def __post_init__(self) -> None:
        if self.n_submaps < 1:
            raise SimulationError(f"number of submaps must be at least 1, got {self.n_submaps}")
        if self.submaps_per_scene < 1:
            raise SimulationError(f"submaps per scene must be at least 1, got {self.submaps_per_scene}")
        low, high = self.scans_per_submap
        if not 1 <= low <= high:
            raise SimulationError(f"scans per submap must be 1 <= min <= max, got {self.scans_per_submap}")
        if not self.sensors or not self.presets:
            raise SimulationError("give at least one sensor and one preset")
        if self.split and self.split not in SPLITS:
            raise SimulationError(f"unknown split {self.split!r} (one of {', '.join(SPLITS)})")
        for name in self.sensors:
            get_sensor(name)
        for name in self.presets:
            get_preset(name)

    @property
    def n_scenes(self) -> int:
        return -(-self.n_submaps // self.submaps_per_scene)

    def scene_submaps(self, scene: int) -> int:
        """Submaps that scene `scene` contributes."""
        return min(self.submaps_per_scene, self.n_submaps - scene * self.submaps_per_scene)


@dataclass
class SceneResult:
    """The submaps of one scene plus what was drawn for it (stored in the manifest as the source's meta)."""

    source: str
    submaps: list[Submap]
    meta: dict = field(default_factory=dict)


def _rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations Rz(yaw) Ry(-pitch) Rx(roll): pitch > 0 lifts the x axis (nose up)."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    return np.stack([
        np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        np.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


def drive(scene: Scene, sensor: SensorInstance, rng: np.random.Generator, stops: bool = True) -> np.ndarray:
    """(N, 4, 4) sensor-to-world poses at SCAN_RATE_HZ along the scene's drive: cruising speed that varies,
    sometimes a stop, a slow wander within the lane, pitch from the road grade and a little roll."""
    preset = get_preset(scene.preset)
    cruise = rng.uniform(*preset.speed)
    period, phase = rng.uniform(10.0, 40.0), rng.uniform(0, 2 * np.pi)
    length = scene.drive_end_m - scene.drive_start_m
    stop_at = rng.uniform(0.2, 0.8) * length if stops and preset.name != "highway" and rng.random() < 0.35 else None
    wait = int(rng.uniform(2.0, 15.0) * SCAN_RATE_HZ)
    braking = 1.5  # m/s^2
    positions, s, time = [], 0.0, 0.0
    while s <= length:
        positions.append(s)
        speed = cruise * (1 + 0.15 * np.sin(2 * np.pi * time / period + phase))
        if stop_at is not None:
            if s < stop_at:
                speed = min(speed, max(0.3, np.sqrt(2 * braking * (stop_at - s))))
                if stop_at - s < speed / SCAN_RATE_HZ:
                    positions.extend([stop_at] * wait)
                    s = stop_at
            else:
                speed = min(speed, 0.5 + np.sqrt(2 * braking * (s - stop_at)))
        s += speed / SCAN_RATE_HZ
        time += 1 / SCAN_RATE_HZ
    s = scene.drive_start_m + np.array(positions)
    amplitude, wavelength, phase = 0.25, rng.uniform(40.0, 120.0), rng.uniform(0, 2 * np.pi)
    wander = amplitude * np.sin(2 * np.pi * s / wavelength + phase)
    wander_slope = amplitude * 2 * np.pi / wavelength * np.cos(2 * np.pi * s / wavelength + phase)
    street = scene.street
    offset = scene.lane_offset_m + wander
    xy = street.point(s, offset)
    z = street.surface_z(s, offset) + sensor.mount_height_m
    _, heading, _ = street.at(s)
    grade = street.at(s + 0.5)[2] - street.at(s - 0.5)[2]  # rise over 1 m
    time = np.arange(len(s)) / SCAN_RATE_HZ
    sway = [np.deg2rad(rng.uniform(0.02, 0.12)) * np.sin(2 * np.pi * rng.uniform(0.3, 1.5) * time + rng.uniform(0, 7))
            for _ in range(2)]  # body pitch and roll on the suspension
    yaw = heading + np.arctan(wander_slope) + rng.normal(0.0, 0.002, len(s))
    pitch = np.arctan(grade) + sway[0] + rng.normal(0.0, 0.001, len(s))
    roll = sway[1] + rng.normal(0.0, 0.001, len(s))
    poses = np.tile(np.eye(4), (len(s), 1, 1))
    poses[:, :3, :3] = _rotation(yaw, pitch, roll)
    poses[:, :3, 3] = np.column_stack([xy, z])
    return poses


def perturb_poses(poses: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poses with a slowly drifting error like estimated ones: ~0.5-2.5 cm and ~0.02-0.1 degrees (1 sigma)."""
    n = len(poses)
    sigma_t, sigma_r = rng.uniform(0.002, 0.01), np.deg2rad(rng.uniform(0.01, 0.04))
    error_t, error_r = np.zeros((n, 3)), np.zeros((n, 3))
    for k in range(1, n):  # AR(1) drift
        error_t[k] = 0.9 * error_t[k - 1] + rng.normal(0.0, sigma_t, 3)
        error_r[k] = 0.9 * error_r[k - 1] + rng.normal(0.0, sigma_r, 3)
    noisy = poses.copy()
    noisy[:, :3, :3] = _rotation(error_r[:, 2], error_r[:, 1], error_r[:, 0]) @ poses[:, :3, :3]
    noisy[:, :3, 3] += error_t
    return noisy


def _scan_window(key: int, n_poses: int, n_scans: int, stride: int) -> np.ndarray:
    """Indices of `n_scans` poses `stride` apart, centred on `key` as far as the drive allows."""
    first = key - (n_scans // 2) * stride
    first = int(np.clip(first, key % stride, max(key % stride, n_poses - 1 - (n_scans - 1) * stride)))
    indices = first + stride * np.arange(n_scans)
    return np.unique(np.clip(indices, 0, n_poses - 1))


def simulate_scene(config: SimulationConfig, scene_index: int) -> SceneResult:
    """The submaps of scene `scene_index` of `config` (deterministic for a given config and index)."""
    if not 0 <= scene_index < config.n_scenes:
        raise SimulationError(f"scene {scene_index} is not one of the {config.n_scenes} scenes of this configuration")
    seed = (config.seed, scene_index)
    rng = np.random.default_rng(seed)
    preset = str(rng.choice(config.presets))
    sensor_name = str(rng.choice(config.sensors))
    n_submaps = config.scene_submaps(scene_index)
    drive_length = 2 * WINDOW_MARGIN_M + (n_submaps - 1) * SUBMAP_SPACING_M + 5.0
    scene = build_scene(preset, drive_length, rng)
    sensor = get_sensor(sensor_name).instance(rng)
    poses = drive(scene, sensor, rng, config.stops)
    map_poses = perturb_poses(poses, rng) if config.pose_noise else poses
    travelled = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))]
    first = int(np.searchsorted(travelled, WINDOW_MARGIN_M))
    keys = first + submap_centers(poses[first:], SUBMAP_SPACING_M)[:n_submaps]
    reflectivity = face_reflectivity(scene.labels, scene.objects, scene.materials,
                                     np.random.default_rng((*seed, ATTRIBUTE_STREAM)))
    raycaster = Raycaster(scene.vertices, scene.faces, scene.materials, scene.labels, scene.objects, reflectivity,
                          scene.lane_markings)
    speed = travelled[-1] / max(len(poses) - 1, 1) * SCAN_RATE_HZ
    low, high = config.scans_per_submap
    cache: dict[int, tuple[np.ndarray, dict[str, np.ndarray]]] = {}  # scan index -> (points, attributes)
    source = f"sim{config.seed}-{scene_index:05d}-{preset}-{sensor_name}"
    split = config.split or ("val" if scene_index % VALIDATION_EVERY == VALIDATION_EVERY - 1 else "train")
    submaps, drawn = [], []
    for number, key in enumerate(keys):
        n_scans = int(np.exp(rng.uniform(np.log(low), np.log(high + 1))))
        n_scans = min(max(n_scans, low), high)
        stride = int(rng.choice(config.strides))
        step = max(speed, 0.5) / SCAN_RATE_HZ
        stride = max(1, min(stride, int(MAX_WINDOW_M / (step * n_scans))))
        window = _scan_window(int(key), len(poses), n_scans, stride)
        for index in window:
            if index not in cache:
                scan_rng = np.random.default_rng((*seed, 1, int(index)))
                attribute_rng = np.random.default_rng((*seed, ATTRIBUTE_STREAM, int(index)))
                sweep = raycaster.sweep(sensor, poses[index], scan_rng, attribute_rng, MAX_RANGE_M + 1.0)
                keep = range_mask(sweep.points)
                cache[int(index)] = (sweep.points[keep].astype(np.float32),
                                     {name: values[keep] for name, values in sweep.attributes().items()})
        world, values = aggregate_labelled_map((*cache[int(index)], map_poses[index]) for index in window)
        centre = map_poses[key, :3, 3]
        inside = crop_mask(world, centre)
        if not inside.any():
            continue
        submaps.append(Submap(world[inside], centre.copy(), submap_bounds(centre), source, number, map_poses[key],
                              split, {name: column[inside] for name, column in values.items()}))
        drawn.append({"index": number, "n_scans": int(len(window)), "stride": stride})
        for index in [index for index in cache if index < window[0]]:  # windows move forward
            del cache[index]
    meta = {
        "simulator": "mapsqueeze.data.simulator",
        "config": {key: value for key, value in asdict(config).items() if key != "n_submaps"},
        "scene": scene_index,
        "preset": preset,
        "sensor": sensor_name,
        "mount_height_m": round(sensor.mount_height_m, 3),
        "azimuth_step_deg": round(sensor.azimuth_step_deg, 4),
        "mean_speed_mps": round(float(speed), 2),
        "triangles": int(len(scene.faces)),
        "submaps": drawn,
        "labels": {str(int(semantic)): semantic.label_name for semantic in Semantic},  # `label` field: class names
    }
    return SceneResult(source, submaps, meta)


def _simulate_scene_job(job: tuple[SimulationConfig, int]) -> SceneResult:
    return simulate_scene(*job)


def iter_scenes(config: SimulationConfig, workers: int = 1) -> Iterator[SceneResult]:
    """Scene results in scene order, computed by `workers` processes (1: in this process).

    Embree casts rays on every core through OpenMP; worker processes get one OpenMP thread each instead (they
    share the cores already), which is ~20 % faster than letting them compete. In this process the thread count
    is the environment's: OMP_NUM_THREADS=1 keeps a run on one core.
    """
    jobs = [(config, index) for index in range(config.n_scenes)]
    if workers <= 1:
        yield from map(_simulate_scene_job, jobs)
        return
    previous = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"  # read by the spawned workers' OpenMP runtimes when they start
    try:
        pool = multiprocessing.get_context("spawn").Pool(min(workers, len(jobs)))
    finally:
        if previous is None:
            del os.environ["OMP_NUM_THREADS"]
        else:
            os.environ["OMP_NUM_THREADS"] = previous
    with pool:
        yield from pool.imap(_simulate_scene_job, jobs)


def simulate_dataset(out_dir: str | os.PathLike, config: SimulationConfig, workers: int = 1,
                     progress: Callable[[int], None] | None = None) -> Path:
    """Simulate `config` into a dataset directory (PLY per submap + manifest.json, as `mapping.write_dataset`).

    Scenes are written one source at a time as they finish (in scene order); `progress(n)` is called with the
    number of submaps just written. Sources already in the directory under other names are kept. Returns
    the manifest path.
    """
    if workers < 1:
        raise SimulationError(f"workers must be at least 1, got {workers}")
    manifest = None
    for result in iter_scenes(config, workers):
        manifest = write_dataset(out_dir, result.submaps, result.meta)
        if progress is not None:
            progress(len(result.submaps))
    return manifest
