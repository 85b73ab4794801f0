"""Simulated intensity, semantic labels and instance ids: the intensity model, labels of what was hit, instances per
object, determinism, an unchanged geometry, and simulated submaps through compress / decompress."""

import dataclasses

import numpy as np
import pytest

from mapsqueeze.data import read_dataset
from mapsqueeze.data.simulator import SENSORS, Raycaster, Semantic, SimulationConfig, simulate_dataset, simulate_scene
from mapsqueeze.data.simulator import objects
from mapsqueeze.data.simulator.scene import build_scene
from mapsqueeze.data.simulator.shapes import MeshBuilder, boxes, quads, rotation_z
from mapsqueeze.io import read_point_cloud
from mapsqueeze.metrics import attribute_error, constant_guess_error, label_accuracy

MOUNT_M = 1.73


def ideal_sensor():
    """HDL-64E geometry without noise, dropout, divergence, calibration errors or own-car shadow."""
    model = dataclasses.replace(SENSORS["hdl64"], range_noise_m=0.0, dropout=0.0, divergence_mrad=0.0,
                                elevation_error_deg=0.0, range_offset_m=0.0, ego_shadow=(0.0, 0.0, 1e-3, 1e-3, -1.0),
                                mount_height_m=(MOUNT_M, MOUNT_M))
    return model.instance(np.random.default_rng(0))


def wall(distance_m: float, yaw: float = 0.0) -> MeshBuilder:
    """A 12 x 12 m building wall facing the sensor at the origin, its centre `distance_m` along +x, turned by `yaw`."""
    builder = MeshBuilder(Semantic.BUILDING)
    corners = np.array([[0.0, -6.0, -6.0], [0.0, 6.0, -6.0], [0.0, 6.0, 6.0], [0.0, -6.0, 6.0]])
    builder.add(quads((corners @ rotation_z(yaw).T + [distance_m, 0.0, 0.0])[None]))
    return builder


def head_on_intensity(builder: MeshBuilder, seed: int = 0) -> np.ndarray:
    """Intensity of the returns within 0.3 m of the +x axis (range = the wall's distance there)."""
    sweep = Raycaster(*builder.build()).sweep(ideal_sensor(), np.eye(4), np.random.default_rng(seed),
                                              np.random.default_rng(seed + 1))
    near_axis = (np.abs(sweep.points[:, 1]) < 0.3) & (np.abs(sweep.points[:, 2]) < 0.3)
    assert near_axis.sum() >= 20
    return sweep.intensity[near_axis]


def test_intensity_falls_with_range_for_the_same_material():
    means = [head_on_intensity(wall(distance)).mean() for distance in (4.0, 8.0, 16.0)]
    assert means[0] > means[1] > means[2] > 0.0, means
    assert means[0] < 1.0


def test_intensity_falls_with_the_incidence_angle_for_the_same_material():
    means = [head_on_intensity(wall(8.0, np.deg2rad(angle))).mean() for angle in (0.0, 45.0, 70.0)]
    assert means[0] > means[1] > means[2] > 0.0, means


def test_brighter_classes_give_brighter_returns_at_the_same_range_and_angle():
    def mean_of(label: Semantic) -> float:
        builder = MeshBuilder(label)
        builder.add(quads(np.array([[[8.0, -6, -6], [8.0, 6, -6], [8.0, 6, 6], [8.0, -6, 6]]])))
        return float(head_on_intensity(builder).mean())

    assert mean_of(Semantic.ROAD) < mean_of(Semantic.BUILDING) < mean_of(Semantic.TRAFFIC_SIGN)


def labelled_yard() -> tuple[MeshBuilder, dict[int, np.ndarray]]:
    """Terrain, a building block from x = 12 m, two cars and a tree with object ids 1-3: (mesh, id -> centre xy)."""
    rng = np.random.default_rng(7)
    builder = MeshBuilder(Semantic.TERRAIN)
    builder.add(quads(np.array([[[-40, -40, 0], [40, -40, 0], [40, 40, 0], [-40, 40, 0]]], dtype=float)))
    block = MeshBuilder(Semantic.BUILDING)
    block.add(boxes([[18.0, 0.0, 5.0]], [[12.0, 30.0, 10.0]]))
    builder.extend(block, np.eye(3), np.zeros(3), object_id=-4)
    centres = {1: np.array([6.0, 5.0]), 2: np.array([6.0, -5.0]), 3: np.array([-6.0, 3.0])}
    for object_id, centre in centres.items():
        part = objects.tree(rng) if object_id == 3 else objects.vehicle(rng, "sedan")[0]
        builder.extend(part, np.eye(3), [*centre, 0.0], object_id=object_id)
    return builder, centres


def test_labels_and_instances_are_those_of_the_surfaces_hit():
    builder, centres = labelled_yard()
    pose = np.eye(4)
    pose[2, 3] = MOUNT_M
    sweep = Raycaster(*builder.build()).sweep(ideal_sensor(), pose, np.random.default_rng(1),
                                              np.random.default_rng(2))
    world = sweep.points + [0.0, 0.0, MOUNT_M]
    on_ground = np.abs(world[:, 2]) < 1e-3
    assert on_ground.sum() > 1000 and np.all(sweep.label[on_ground & (world[:, 0] < 11.9)] == Semantic.TERRAIN)
    on_block = (world[:, 0] > 11.99) & (world[:, 2] > 1e-3)
    assert on_block.sum() > 1000 and np.all(sweep.label[on_block] == Semantic.BUILDING)
    assert np.all(sweep.instance[on_ground | on_block] == 0)  # stuff has no instance
    for object_id, centre in centres.items():
        near = (np.linalg.norm(world[:, :2] - centre, axis=1) < 2.0) & (world[:, 2] > 0.2)
        assert near.sum() > 50
        assert set(np.unique(sweep.instance[near])) == {object_id}
        expected = {Semantic.TRUNK, Semantic.VEGETATION} if object_id == 3 else {Semantic.CAR}
        assert set(np.unique(sweep.label[near])) <= expected


def test_sweep_points_are_scan_points_whatever_the_attribute_generator():
    builder, _ = labelled_yard()
    raycaster = Raycaster(*builder.build())
    sensor = ideal_sensor()
    points = raycaster.scan(sensor, np.eye(4), np.random.default_rng(3))
    first = raycaster.sweep(sensor, np.eye(4), np.random.default_rng(3), np.random.default_rng(10))
    other = raycaster.sweep(sensor, np.eye(4), np.random.default_rng(3), np.random.default_rng(11))
    np.testing.assert_array_equal(first.points, points)
    np.testing.assert_array_equal(other.points, points)
    np.testing.assert_array_equal(first.label, other.label)
    assert not np.array_equal(first.intensity, other.intensity)  # the speckle noise is drawn from its own stream


def test_every_countable_object_of_a_scene_has_its_own_instance_id():
    scene = build_scene("suburban", 60.0, np.random.default_rng(2))
    centroids = scene.vertices[scene.faces].mean(axis=1)
    cars = (scene.labels == Semantic.CAR) | (scene.labels == Semantic.TRUCK)
    assert np.all(scene.objects[cars] > 0)
    car_ids = np.unique(scene.objects[cars])
    assert len(car_ids) >= 3
    for object_id in car_ids:  # one vehicle per id: its faces span at most a truck's length
        mine = centroids[scene.objects == object_id, :2]
        assert np.linalg.norm(mine.max(axis=0) - mine.min(axis=0)) < 9.0
    assert np.all(scene.objects[scene.labels == Semantic.BUILDING] < 0)
    assert np.all(scene.objects[(scene.labels == Semantic.ROAD) | (scene.labels == Semantic.TERRAIN)] <= 0)


# --- whole pipeline ---------------------------------------------------------------------------------------------

TINY = dict(n_submaps=1, sensors=("hdl64",), presets=("urban",), scans_per_submap=(2, 2), strides=(1,))


@pytest.mark.slow
def test_simulated_submaps_carry_deterministic_intensity_labels_and_instances():
    first, again = (simulate_scene(SimulationConfig(seed=5, **TINY), 0).submaps[0] for _ in range(2))
    assert set(first.attributes) == {"intensity", "label", "instance"}
    for name, values in first.attributes.items():
        assert len(values) == first.n_points
        np.testing.assert_array_equal(values, again.attributes[name])
    intensity, label = first.attributes["intensity"], first.attributes["label"]
    assert intensity.dtype == np.float32 and 0.0 <= intensity.min() and intensity.max() < 1.0
    assert {Semantic.ROAD, Semantic.SIDEWALK, Semantic.BUILDING, Semantic.CAR} <= set(np.unique(label).tolist())
    # road points lie on the ground, about a sensor height below the key pose; building walls rise above it
    height = first.points[:, 2] - first.center[2]
    road = np.median(height[label == Semantic.ROAD])
    assert -2.0 < road < -1.4
    assert np.percentile(height[label == Semantic.BUILDING], 90) > road + 1.5


@pytest.mark.slow
def test_a_simulated_submap_keeps_its_fields_through_compress_and_decompress(run_cli, tiny_model_dir, tmp_path):
    config = SimulationConfig(seed=5, **TINY)
    simulate_dataset(tmp_path / "sim", config)
    record = read_dataset(tmp_path / "sim").records[0]
    original = read_point_cloud(record.path)
    assert set(original.attributes) == {"intensity", "label", "instance"}
    names = read_dataset(tmp_path / "sim").sources[record.source]["labels"]
    assert names["40"] == "road" and names["81"] == "traffic-sign"
    assert {str(label) for label in np.unique(original.attributes["label"])} <= set(names)
    code, _, err = run_cli("compress", str(record.path), "-o", str(tmp_path / "map.msq"), "--model",
                           str(tiny_model_dir))
    assert code == 0, err
    code, _, err = run_cli("decompress", str(tmp_path / "map.msq"), "-o", str(tmp_path / "out.ply"), "--model",
                           str(tiny_model_dir))
    assert code == 0, err
    decoded = read_point_cloud(tmp_path / "out.ply")
    assert set(decoded.attributes) == {"intensity", "label", "instance"}
    assert decoded.attributes["label"].dtype == np.uint16 and decoded.attributes["intensity"].dtype == np.float32
    values = original.attributes
    error = attribute_error(original.points, values["intensity"], decoded.points, decoded.attributes["intensity"])
    assert error < 0.8 * constant_guess_error(original.points, values["intensity"], decoded.points)
    assert label_accuracy(original.points, values["label"], decoded.points, decoded.attributes["label"]) > 0.8


@pytest.mark.parametrize("preset", ["highway", "suburban"])
def test_road_labels_lie_on_the_road_and_sidewalk_labels_beside_it(preset):
    rng = np.random.default_rng(4)
    scene = build_scene(preset, 40.0, rng)
    pose = np.eye(4)
    pose[:3, 3] = [*scene.street.point(scene.drive_start_m + 20.0, scene.lane_offset_m),
                   float(scene.street.surface_z(scene.drive_start_m + 20.0, scene.lane_offset_m)) + MOUNT_M]
    raycaster = Raycaster(scene.vertices, scene.faces, scene.materials, scene.labels, scene.objects)
    sweep = raycaster.sweep(ideal_sensor(), pose, np.random.default_rng(5), np.random.default_rng(6))
    world = sweep.points + pose[:3, 3]
    s, t, beside = scene.street.project(world[:, :2])
    half = scene.street.half_width[(t > 0).astype(int)]
    mine = beside & ~scene.street.in_gap(s, t)  # junction mouths belong to cross streets
    road = mine & np.isin(sweep.label, [Semantic.ROAD, Semantic.PARKING])
    assert road.sum() > 1000 and np.all(np.abs(t[road]) < half[road] + 0.05)
    side = mine & np.isin(sweep.label, [Semantic.SIDEWALK, Semantic.TERRAIN])
    assert side.sum() > 100 and np.all(np.abs(t[side]) > half[side] - 0.05)
    assert np.all(np.abs(world[road, 2] - scene.street.surface_z(s[road], t[road])) < 0.05)


def test_lane_markings_are_labelled_and_brighter_than_the_asphalt_around_them():
    scene = build_scene("urban", 40.0, np.random.default_rng(8))
    s0 = scene.drive_start_m + 20.0
    pose = np.eye(4)
    pose[:3, 3] = [*scene.street.point(s0, scene.lane_offset_m),
                   float(scene.street.surface_z(s0, scene.lane_offset_m)) + MOUNT_M]
    raycaster = Raycaster(scene.vertices, scene.faces, scene.materials, scene.labels, scene.objects,
                          markings=scene.lane_markings)
    sweep = raycaster.sweep(ideal_sensor(), pose, np.random.default_rng(5), np.random.default_rng(6))
    paint = sweep.label == Semantic.LANE_MARKING
    asphalt = sweep.label == Semantic.ROAD
    assert paint.sum() > 50 and asphalt.sum() > 20 * paint.sum()
    distance = np.linalg.norm(sweep.points, axis=1)
    for low in (3.0, 6.0, 9.0):  # same range band: similar incidence, same falloff
        band = (distance >= low) & (distance < low + 3.0)
        assert sweep.intensity[paint & band].mean() > 1.5 * sweep.intensity[asphalt & band].mean()
    world = sweep.points + pose[:3, 3]
    _, t, _ = scene.street.project(world[paint, :2])
    assert np.all(np.abs(t) < scene.street.half_width[(t > 0).astype(int)])
