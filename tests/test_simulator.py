"""LiDAR simulator: beam geometry, materials, no sky returns, range limits, determinism, dataset layout, CLI."""

import dataclasses
import sys

import numpy as np
import pytest

from mapsqueeze.data import read_dataset
from mapsqueeze.data.simulator import (
    PRESETS,
    SENSORS,
    Raycaster,
    SimulationConfig,
    build_scene,
    drive,
    simulate_dataset,
    simulate_scene,
)
from mapsqueeze.errors import SimulationError
from mapsqueeze.data.simulator.shapes import Material, MeshBuilder, boxes, quads

MOUNT_M = 1.73


def ideal(name: str, **changes):
    """A sensor model without noise, dropout, divergence, calibration errors or own-car shadow."""
    model = dataclasses.replace(SENSORS[name], range_noise_m=0.0, dropout=0.0, divergence_mrad=0.0,
                                elevation_error_deg=0.0, range_offset_m=0.0, ego_shadow=(0.0, 0.0, 1e-3, 1e-3, -1.0),
                                mount_height_m=(MOUNT_M, MOUNT_M), **changes)
    return model.instance(np.random.default_rng(0))


def flat_ground(half_size: float = 200.0, extra: MeshBuilder | None = None) -> Raycaster:
    builder = MeshBuilder()
    corners = np.array([[[-half_size, -half_size, 0], [half_size, -half_size, 0], [half_size, half_size, 0],
                         [-half_size, half_size, 0]]], dtype=float)
    builder.add(quads(corners))
    if extra is not None:
        builder.extend(extra, np.eye(3), np.zeros(3))
    return Raycaster(*builder.build())


def sensor_pose(height: float = MOUNT_M) -> np.ndarray:
    pose = np.eye(4)
    pose[2, 3] = height
    return pose


# --- sensor geometry and ray casting -----------------------------------------------------------------------------


def test_hdl64_lower_beams_make_rings_at_the_expected_ranges():
    sensor = ideal("hdl64")
    points = flat_ground().scan(sensor, sensor_pose(), np.random.default_rng(1))
    assert np.allclose(points[:, 2], -MOUNT_M, atol=1e-6)  # every return lies on the ground
    horizontal = np.linalg.norm(points[:, :2], axis=1)
    downward = np.array([e for e in SENSORS["hdl64"].elevations_deg if e < 0])
    expected = MOUNT_M / np.tan(np.deg2rad(-downward))
    downward, expected = downward[expected < 15.0], expected[expected < 15.0]  # no grazing-angle dropout
    elevation = np.rad2deg(np.arctan2(points[:, 2], horizontal))
    near = horizontal < 15.0
    horizontal, elevation = horizontal[near], elevation[near]
    laser = np.abs(elevation[:, None] - downward[None, :]).argmin(axis=1)
    assert set(laser) == set(range(len(downward)))  # one ring per downward laser
    assert np.allclose(horizontal, expected[laser], rtol=1e-6, atol=1e-4)
    assert expected.min() == pytest.approx(3.73, abs=0.02)  # lowest beam, -24.9 deg, at a 1.73 m mount
    per_ring = np.bincount(laser)
    assert per_ring.min() == per_ring.max() == pytest.approx(360 / sensor.azimuth_step_deg, abs=1.0)


def test_hdl32_own_car_blocks_its_lowest_beams():
    rng = np.random.default_rng(0)
    directions, lasers = SENSORS["hdl32"].instance(rng).beams(rng)
    per_laser = np.bincount(lasers, minlength=32)  # lasers from +10.67 deg (0) down to -30.67 deg (31)
    assert per_laser[31] < 0.5 * per_laser[0]  # the lowest beam mostly hits the roof
    assert per_laser[20] == per_laser[0]  # beams 16 deg down clear it


def test_no_returns_from_the_sky_or_beyond_the_maximum_range():
    tower = MeshBuilder()
    tower.add(boxes([[8.0, 0.0, 3.0]], [[2.0, 2.0, 6.0]]))
    raycaster = flat_ground(extra=tower)
    sensor = SENSORS["os1_128"].instance(np.random.default_rng(2))  # +22.5 deg beams: many go to the sky
    points = raycaster.scan(sensor, sensor_pose(), np.random.default_rng(3), max_range_m=15.0)
    world_z = points[:, 2] + MOUNT_M
    assert world_z.max() <= 6.0 + 0.2  # nothing above the tower top (noise allowed)
    assert np.linalg.norm(points, axis=1).max() <= 15.0 + 0.2
    upward = points[:, 2] > 0.5
    assert upward.any() and np.all(points[upward, 0] > 6.5)  # upward returns only from the tower


def test_porous_foliage_lets_some_beams_through_to_the_wall_behind():
    scene = MeshBuilder()
    scene.add(quads(np.array([[[5.0, -5, -2], [5.0, 5, -2], [5.0, 5, 3], [5.0, -5, 3]]])), Material.VEGETATION)
    scene.add(quads(np.array([[[8.0, -5, -2], [8.0, 5, -2], [8.0, 5, 3], [8.0, -5, 3]]])), Material.SOLID)
    raycaster = Raycaster(*scene.build())
    sensor = ideal("hdl64")
    points = raycaster.scan(sensor, np.eye(4), np.random.default_rng(4))
    front = np.isclose(points[:, 0], 5.0, atol=0.3)
    behind = np.isclose(points[:, 0], 8.0, atol=0.05)
    assert front.sum() > 1000 and behind.sum() > 300
    assert front.sum() + behind.sum() == len(points)


def test_glass_gives_fewer_returns_than_a_solid_wall():
    def returns(material: Material) -> int:
        builder = MeshBuilder()
        builder.add(quads(np.array([[[6.0, -3, -1], [6.0, 3, -1], [6.0, 3, 1], [6.0, -3, 1]]])), material)
        return len(Raycaster(*builder.build()).scan(ideal("hdl64"), np.eye(4), np.random.default_rng(5)))

    assert returns(Material.GLASS) < 0.4 * returns(Material.SOLID)


# --- scenes -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_preset_builds_a_closed_street_scene(preset):
    scene = build_scene(preset, 20.0, np.random.default_rng(7))
    assert len(scene.faces) > 10_000 and len(scene.materials) == len(scene.faces)
    assert np.isfinite(scene.vertices).all() and scene.faces.max() < len(scene.vertices)
    assert scene.drive_end_m - scene.drive_start_m == pytest.approx(20.0)
    start, end = scene.street.at(np.array([scene.drive_start_m, scene.drive_end_m]))[0]
    assert np.linalg.norm(end - start) > 10.0
    assert scene.top_z - scene.street.z.max() < 40.0


def test_a_sweep_in_a_built_scene_has_no_point_above_the_scene_top():
    rng = np.random.default_rng(8)
    scene = build_scene("urban", 20.0, rng)
    sensor = SENSORS["os1_128"].instance(rng)
    pose = drive(scene, sensor, rng)[10]
    points = Raycaster(scene.vertices, scene.faces, scene.materials).scan(sensor, pose, rng)
    world = points @ pose[:3, :3].T + pose[:3, 3]
    assert len(points) > 50_000
    assert world[:, 2].max() <= scene.top_z + 0.2


def test_bad_configurations_are_simulation_errors():
    with pytest.raises(SimulationError, match="unknown sensor"):
        SimulationConfig(n_submaps=1, sensors=("lidar9000",))
    with pytest.raises(SimulationError, match="unknown preset"):
        SimulationConfig(n_submaps=1, presets=("moon",))
    with pytest.raises(SimulationError):
        SimulationConfig(n_submaps=0)
    with pytest.raises(SimulationError):
        SimulationConfig(n_submaps=1, scans_per_submap=(5, 2))
    with pytest.raises(SimulationError, match="unknown split 'training'"):
        SimulationConfig(n_submaps=1, split="training")


# --- whole pipeline ---------------------------------------------------------------------------------------------

TINY = dict(n_submaps=1, sensors=("hdl64",), presets=("suburban",), scans_per_submap=(2, 2), strides=(1,))


@pytest.fixture(scope="module")
def tiny_runs():
    """The same tiny scene simulated twice with seed 0 and once with seed 1."""
    return [simulate_scene(SimulationConfig(seed=seed, **TINY), 0) for seed in (0, 0, 1)]


@pytest.mark.slow
def test_same_seed_gives_identical_points_and_other_seeds_differ(tiny_runs):
    first, again, other = (run.submaps[0] for run in tiny_runs)
    assert first.n_points > 20_000
    np.testing.assert_array_equal(first.points, again.points)
    np.testing.assert_array_equal(first.pose, again.pose)
    assert tiny_runs[0].meta == tiny_runs[1].meta
    assert other.n_points != first.n_points or not np.array_equal(other.points, first.points)


@pytest.mark.slow
def test_submaps_respect_the_mapping_ranges_and_box(tiny_runs):
    submap = tiny_runs[0].submaps[0]
    assert tiny_runs[0].meta["submaps"] == [{"index": 0, "n_scans": 2, "stride": 1}]
    lower, upper = submap.bounds
    assert np.all((submap.points >= lower) & (submap.points < upper))
    relative = submap.points - submap.center
    assert np.abs(relative[:, :2]).max() < 20.0 + 1e-9
    # two scans 10 Hz apart: every point lies within the 20 m mapping range of the key pose (+ drive + noise)
    assert np.linalg.norm(relative, axis=1).max() < 20.0 + 3.0
    # 10 cm voxel filter: no two points share a voxel of the world grid
    keys = np.floor(submap.points / 0.1).astype(np.int64)
    assert len(np.unique(keys, axis=0)) == submap.n_points


@pytest.mark.slow
def test_simulated_dataset_reads_back_and_does_not_depend_on_workers(tmp_path):
    config = SimulationConfig(n_submaps=2, submaps_per_scene=1, sensors=("hdl32",), presets=("highway",),
                              scans_per_submap=(1, 1), seed=3)
    progress = []
    manifest = simulate_dataset(tmp_path / "sim", config, progress=progress.append)
    assert manifest == tmp_path / "sim" / "manifest.json" and progress == [1, 1]
    dataset = read_dataset(tmp_path / "sim")
    assert [record.source for record in dataset.records] == ["sim3-00000-highway-hdl32", "sim3-00001-highway-hdl32"]
    assert {record.split for record in dataset.records} == {"train"}
    for record in dataset.records:
        local = record.local_points()
        assert local.dtype == np.float32 and local.shape == (record.n_points, 3) and record.n_points > 1000
        assert np.all(local >= 0) and np.all(local < (record.bounds[1] - record.bounds[0]).astype(np.float32))
    assert dataset.sources["sim3-00000-highway-hdl32"]["sensor"] == "hdl32"
    # two worker processes write byte-identical files
    simulate_dataset(tmp_path / "sim2", config, workers=2)
    for path in sorted((tmp_path / "sim").iterdir()):
        assert path.read_bytes() == (tmp_path / "sim2" / path.name).read_bytes(), path.name
    # another seed simulated into the same dataset adds its submaps, here all forced into one split
    simulate_dataset(tmp_path / "sim", dataclasses.replace(config, n_submaps=1, seed=4, split="test"))
    grown = read_dataset(tmp_path / "sim")
    assert [(r.source, r.split) for r in grown.records] == [("sim3-00000-highway-hdl32", "train"),
                                                             ("sim3-00001-highway-hdl32", "train"),
                                                             ("sim4-00000-highway-hdl32", "test")]
    np.testing.assert_array_equal(grown.records[0].local_points(), dataset.records[0].local_points())


def test_cli_rejects_unknown_sensor_with_one_error_line(monkeypatch, capsys, tmp_path):
    from mapsqueeze.cli import main

    monkeypatch.setattr(sys, "argv", ["mapsqueeze", "simulate", "-o", str(tmp_path / "x"), "--sensor", "foo"])
    with pytest.raises(SystemExit) as exit_info:
        main()
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip() == (
        "error: unknown sensor 'foo'; choose from hdl64, hdl32, vlp32c, os1_128, os2_128")
    assert not (tmp_path / "x").exists()


def test_cli_simulate_prints_plain_lines_when_piped(run_cli, tmp_path):
    """Piped, simulate prints its summary line only, not the last frame of a progress bar."""
    code, out, err = run_cli("simulate", "-o", str(tmp_path / "sim"), "--sensor", "hdl32", "--preset", "highway",
                             "--submaps", "1", "--scans", "1-1", "--seed", "0")
    assert (code, out) == (0, "") and len(err.splitlines()) == 1, err
    assert err.startswith("1 submaps (1 scenes) in ") and err.rstrip().endswith("manifest.json")
