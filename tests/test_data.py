"""Map building: voxel filter, sequence layouts (KITTI, scan folders), submaps, datasets, grid tiling, CLI."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mapsqueeze.data import (
    aggregate_map,
    build_submaps,
    crop_submap,
    estimate_poses,
    open_sequences,
    read_dataset,
    submap_centers,
    transform,
    write_dataset,
)
from mapsqueeze.data.mapping import Submap, preprocess_scan, submap_bounds
from mapsqueeze.data.sequences import read_poses
from mapsqueeze.errors import DataError, InvalidPointCloudError
from mapsqueeze.geometry.tiling import TILE_SIZE_M, fit_grid, tile_map
from mapsqueeze.geometry.voxel import VoxelAccumulator, pack_indices, voxel_filter, voxel_indices
from mapsqueeze.io import read_point_cloud, read_points, write_points

KITTI_SUBMAP_POINTS = 101_924
UTM_OFFSET_M = np.array([500000.123, 4000000.456, 50.0])


def rotation_z(angle: float) -> np.ndarray:
    cos, sin = np.cos(angle), np.sin(angle)
    return np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])


def rigid(rotation: np.ndarray, translation) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, translation
    return pose


# --- voxel filter ---------------------------------------------------------------------------------------------


def test_voxel_filter_keeps_centroid_per_voxel_sorted_by_index():
    points = np.array([[0.01, 0.02, 0.03], [0.09, 0.08, 0.07], [0.15, 0.0, 0.0], [-0.05, 0.0, 0.0]])
    filtered = voxel_filter(points, 0.1)
    # voxel -1 (x in [-0.1, 0)) first, then the two points of voxel 0 merged to their centroid, then voxel 1
    np.testing.assert_allclose(filtered, [[-0.05, 0.0, 0.0], [0.05, 0.05, 0.05], [0.15, 0.0, 0.0]], atol=1e-12)
    assert filtered.dtype == np.float64


def test_voxel_filter_origin_and_anisotropic_size_change_the_grouping():
    points = np.array([[0.04, 0.0, 0.0], [0.06, 0.0, 0.0]])
    assert len(voxel_filter(points, 0.1)) == 1
    assert len(voxel_filter(points, 0.1, origin=[0.05, 0.0, 0.0])) == 2
    stacked = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.15]])
    assert len(voxel_filter(stacked, [0.2, 0.2, 0.1])) == 2
    assert len(voxel_filter(stacked, 0.2)) == 1


def test_voxel_filter_is_idempotent_and_order_independent():
    points = np.random.default_rng(0).uniform(-5, 5, (20_000, 3))
    filtered = voxel_filter(points, 0.5)
    np.testing.assert_allclose(voxel_filter(points[::-1], 0.5), filtered, atol=1e-12)
    assert len(voxel_filter(filtered, 0.5)) == len(filtered)
    assert len(np.unique(voxel_indices(filtered, 0.5), axis=0)) == len(filtered)


def test_voxel_accumulator_in_batches_equals_one_shot_filter_at_utm_coordinates():
    points = UTM_OFFSET_M + np.random.default_rng(1).uniform(0, 30, (50_000, 3))
    accumulator = VoxelAccumulator(0.3)
    for batch in np.array_split(points, 37):
        accumulator.add(batch)
    accumulator.add(np.empty((0, 3)))
    one_shot = voxel_filter(points, 0.3)
    assert accumulator.n_voxels == len(one_shot)
    np.testing.assert_allclose(accumulator.centroids(), one_shot, rtol=0, atol=1e-9)
    # every centroid lies inside its voxel: the precision survives large coordinates
    occupied = np.unique(voxel_indices(points, 0.3), axis=0)
    assert np.array_equal(np.unique(voxel_indices(one_shot, 0.3), axis=0), occupied)


def test_voxel_filter_edge_cases():
    assert voxel_filter(np.empty((0, 3))).shape == (0, 3)
    with pytest.raises(InvalidPointCloudError):
        voxel_filter(np.array([[0.0, np.nan, 0.0]]))
    with pytest.raises(InvalidPointCloudError):
        voxel_filter(np.zeros((3, 3)), voxel_size=0.0)


def test_pack_indices_sorts_like_rows_and_rejects_out_of_range():
    rows = np.random.default_rng(2).integers(-50, 50, (1000, 3))
    keys = pack_indices(rows)
    assert np.array_equal(np.argsort(keys, kind="stable"), np.lexsort(rows.T[::-1]))
    based = pack_indices(rows, base=np.full(3, -50), bits=7)
    assert np.array_equal(np.argsort(based, kind="stable"), np.lexsort(rows.T[::-1]))
    for base in (-50, [[-50, -50, -50]]):  # any base that broadcasts against the rows
        assert np.array_equal(pack_indices(rows, base=base, bits=7), based)
    with pytest.raises(InvalidPointCloudError):
        pack_indices(np.array([[0, 0, 8]]), base=np.zeros(3, dtype=np.int64), bits=3)


# --- sequences ------------------------------------------------------------------------------------------------


def write_kitti_scan(path: Path, points: np.ndarray) -> None:
    scan = np.zeros((len(points), 4), dtype=np.float32)
    scan[:, :3] = points
    path.write_bytes(scan.tobytes())


def pose_line(pose: np.ndarray) -> str:
    return " ".join(f"{value:.12e}" for value in pose[:3].reshape(-1))


@pytest.fixture
def kitti_root(tmp_path) -> tuple[Path, np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """A tiny SemanticKITTI root: sequences/00 with two scans, camera poses, calibration and labels."""
    sequence = tmp_path / "dataset" / "sequences" / "00"
    (sequence / "velodyne").mkdir(parents=True)
    (sequence / "labels").mkdir()
    tr = rigid(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]), [0.1, -0.2, 0.3])  # LiDAR->camera
    lidar_poses = [np.eye(4), rigid(rotation_z(0.3), [5.0, 1.0, 0.2])]
    scans = [
        np.array([[5.0, 0.0, 0.0], [0.0, 8.0, -1.0], [3.0, 3.0, 0.0], [0.0, -6.0, 0.0], [30.0, 0.0, 0.0]]),
        np.array([[4.0, 0.0, 0.0], [0.0, -9.0, 0.5], [-7.0, 0.0, 0.0], [1.0, 0.0, 0.0]]),
    ]
    labels = [
        np.array([40, 10, 252, 50, 50], dtype=np.uint32) | np.uint32(7 << 16),  # instance ids in the upper bits
        np.array([1, 50, 0, 50], dtype=np.uint32),
    ]
    for index, (points, label) in enumerate(zip(scans, labels)):
        write_kitti_scan(sequence / "velodyne" / f"{index:06d}.bin", points)
        (sequence / "labels" / f"{index:06d}.label").write_bytes(label.tobytes())
    (sequence / "calib.txt").write_text(f"P0: {' '.join(['0'] * 12)}\nTr: {pose_line(tr)}\n")
    camera_poses = [tr @ pose @ np.linalg.inv(tr) for pose in lidar_poses]
    (sequence / "poses.txt").write_text("".join(pose_line(pose) + "\n" for pose in camera_poses))
    return tmp_path / "dataset", tr, np.array(lidar_poses), scans, labels


def test_kitti_layout_converts_camera_poses_and_drops_dynamic_points(kitti_root):
    root, _, lidar_poses, scans, _ = kitti_root
    (sequence,) = open_sequences(root)
    assert (sequence.name, sequence.layout, len(sequence)) == ("kitti-00", "kitti-sequence", 2)
    np.testing.assert_allclose(sequence.poses, lidar_poses, atol=1e-9)
    # scan 0: label 252 (moving car) dropped, 10 (parked car) kept; scan 1: 1 (outlier) and 0 (unlabeled) dropped
    np.testing.assert_allclose(sequence.read_scan(0), scans[0][[0, 1, 3, 4]], atol=1e-6)
    np.testing.assert_allclose(sequence.read_scan(1), scans[1][[1, 3]], atol=1e-6)
    world = aggregate_map(sequence.scans(), min_range=2.0, max_range=20.0, voxel_size=0.01)
    expected = np.concatenate([scans[0][[0, 1, 3]], transform(scans[1][[1]], lidar_poses[1])])  # 30 m and 1 m cut
    assert len(world) == len(expected)
    assert cKDTree(world).query(expected)[0].max() < 0.01


def test_kitti_odometry_layout_reads_poses_folder_and_ignores_labels_on_request(kitti_root):
    root, _, lidar_poses, scans, _ = kitti_root
    (root / "sequences" / "00" / "poses.txt").rename(root / "poses.txt")
    (root / "poses").mkdir()
    (root / "poses.txt").rename(root / "poses" / "00.txt")
    (sequence,) = open_sequences(root / "sequences" / "00", use_labels=False)
    np.testing.assert_allclose(sequence.poses, lidar_poses, atol=1e-9)
    assert len(sequence.read_scan(0)) == len(scans[0])


def test_kitti_label_count_mismatch_and_missing_calibration_are_errors(kitti_root):
    root, *_ = kitti_root
    sequence_dir = root / "sequences" / "00"
    (sequence_dir / "labels" / "000001.label").write_bytes(np.zeros(2, dtype=np.uint32).tobytes())
    (sequence,) = open_sequences(root)
    with pytest.raises(DataError, match="2 labels for 4 points"):
        sequence.read_scan(1)
    (sequence_dir / "calib.txt").unlink()
    with pytest.raises(DataError, match="calib"):
        open_sequences(root)


def test_scan_folder_finds_poses_and_checks_them(tmp_path):
    for index in (0, 1, 10):  # natural order: 2.ply sorts before 10.ply
        write_points(tmp_path / f"scan{index}.ply", np.random.default_rng(index).uniform(-5, 5, (10, 3)))
    (sequence,) = open_sequences(tmp_path)
    assert sequence.poses is None
    assert [path.name for path in sequence.scan_paths] == ["scan0.ply", "scan1.ply", "scan10.ply"]
    poses = np.array([rigid(rotation_z(angle), [angle, 0.0, 0.0]) for angle in (0.0, 0.1, 0.2)])
    lines = [" ".join(str(float(value)) for value in pose.reshape(-1)) for pose in poses]
    (tmp_path / "poses_lidar_test.txt").write_text("\n".join(lines) + "\n")
    (sequence,) = open_sequences(tmp_path)  # 16 numbers per line, found by its name
    np.testing.assert_array_equal(sequence.poses, poses)
    (tmp_path / "other_poses.txt").write_text(pose_line(np.eye(4)) + "\n")
    with pytest.raises(DataError, match="several pose files"):
        open_sequences(tmp_path)
    with pytest.raises(DataError, match="1 poses for 3 scans"):
        open_sequences(tmp_path, poses_file=tmp_path / "other_poses.txt")
    with pytest.raises(DataError, match="no such folder"):
        open_sequences(tmp_path / "absent")


# --- map building and submaps ---------------------------------------------------------------------------------


def test_preprocess_scan_and_transform():
    points = np.array([[1.0, 0.0, 0.0], [0.0, 2.5, 0.0], [19.0, 0.0, 3.0], [25.0, 0.0, 0.0]])
    np.testing.assert_array_equal(preprocess_scan(points), points[[1, 2]])
    pose = rigid(rotation_z(np.pi / 2), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(transform(np.array([[1.0, 0.0, 0.0]]), pose), [[1.0, 3.0, 3.0]], atol=1e-12)


def straight_poses(length_m: float, step_m: float = 1.0) -> np.ndarray:
    return np.array([rigid(np.eye(3), [x, 0.0, 0.0]) for x in np.arange(0.0, length_m + 1e-9, step_m)])


def test_submap_centers_by_travelled_distance_and_by_coverage():
    assert submap_centers(straight_poses(100.0)).tolist() == [0, 15, 30, 45, 60, 75, 90]
    there_and_back = np.concatenate([straight_poses(60.0), straight_poses(60.0)[::-1]])
    assert submap_centers(there_and_back).tolist() == [0, 15, 30, 45, 60, 76, 91, 106, 121]  # pose 61 repeats x = 60
    covered = submap_centers(there_and_back, rule="coverage")
    assert there_and_back[covered, 0, 3].tolist() == [0.0, 16.0, 32.0, 48.0]  # no second pass


def test_build_submaps_matches_brute_force_crop():
    rng = np.random.default_rng(3)
    world = rng.uniform([-30, -30, -5], [130, 30, 15], (200_000, 3))
    poses = straight_poses(100.0)
    submaps = build_submaps(world, poses, "line")
    assert [submap.index for submap in submaps] == list(range(7))
    for submap, pose_index in zip(submaps, submap_centers(poses)):
        lower, upper = submap_bounds(poses[pose_index, :3, 3])
        np.testing.assert_array_equal(lower, poses[pose_index, :3, 3] + [-20.0, -20.0, -3.5])
        np.testing.assert_array_equal(upper, poses[pose_index, :3, 3] + [20.0, 20.0, 11.5])
        inside = np.all((world >= lower) & (world < upper), axis=1)
        np.testing.assert_array_equal(submap.points, world[inside])  # same points, map order
        np.testing.assert_array_equal(submap.bounds, [lower, upper])
    assert [submap.split for submap in submaps] == ["train"] * 7
    assert build_submaps(world, poses, "kitti-08")[0].split == "test"


def test_real_kitti_scans_give_the_reference_submap(real_data, kitti_submap):
    (sequence,) = open_sequences(real_data / "kitti_seq00_scans")
    world = aggregate_map(sequence.scans())
    middle = sequence.poses[len(sequence) // 2, :3, 3]
    submap = crop_submap(world, middle, dz=0.0) - middle  # the reference box is centred on the middle pose
    reference = read_points(kitti_submap)
    assert abs(len(submap) - KITTI_SUBMAP_POINTS) < 0.02 * KITTI_SUBMAP_POINTS  # measured: 101,585
    assert np.all(submap.min(axis=0) >= [-20.0, -20.0, -7.5]) and np.all(submap.max(axis=0) < [20.0, 20.0, 7.5])
    assert np.abs(submap.min(axis=0) - reference.min(axis=0)).max() < 0.1
    assert np.abs(submap.max(axis=0) - reference.max(axis=0)).max() < 0.1
    assert np.median(cKDTree(reference).query(submap)[0]) < 0.05  # same surfaces, 10 cm voxels


def test_real_kitti_poses_estimated_with_kiss_icp(real_data):
    pytest.importorskip("kiss_icp")
    kitti_scans = real_data / "kitti_seq00_scans"
    (sequence,) = open_sequences(kitti_scans)
    estimated = estimate_poses(sequence)
    # the shared poses were made by KISS-ICP too; the trajectory moves ~3.6 m forward
    np.testing.assert_allclose(estimated, read_poses(kitti_scans / "poses_lidar_kissicp.txt"), atol=1e-4)


# --- datasets -------------------------------------------------------------------------------------------------


def test_dataset_round_trip_keeps_precision_and_merges_sources(tmp_path):
    rng = np.random.default_rng(4)
    poses = straight_poses(20.0)
    poses[:, :3, 3] += UTM_OFFSET_M
    world = UTM_OFFSET_M + rng.uniform([-25, -25, -5], [45, 25, 12], (30_000, 3))
    submaps = build_submaps(world, poses, "utm")
    write_dataset(tmp_path, submaps, {"note": "first"})
    write_dataset(tmp_path, build_submaps(world, poses, "kitti-08"), {"note": "second"})
    write_dataset(tmp_path, submaps[:1], {"note": "again"})  # replaces the entries of source "utm"
    dataset = read_dataset(tmp_path)
    assert dataset.sources == {"kitti-08": {"note": "second"}, "utm": {"note": "again"}}
    assert [(record.source, record.index) for record in dataset.records] == [
        ("kitti-08", 0), ("kitti-08", 1), ("utm", 0)
    ]
    assert len(dataset.split("test")) == 2
    assert dataset.split("all") == dataset.records
    with pytest.raises(DataError, match="unknown split"):
        dataset.split("tset")
    assert sorted(path.name for path in tmp_path.glob("utm-*.ply")) == ["utm-00000.ply"]  # stale files removed
    record = dataset.split("train")[0]
    local = record.local_points()
    assert local.dtype == np.float32 and local.min() >= 0 and np.all(local.max(axis=0) < [40, 40, 15])
    loaded = record.load()
    np.testing.assert_array_equal(loaded.bounds, submaps[0].bounds)
    np.testing.assert_array_equal(loaded.pose, submaps[0].pose)
    assert loaded.n_points == submaps[0].n_points
    assert np.abs(loaded.points - submaps[0].points).max() < 1e-5
    json.loads((tmp_path / "manifest.json").read_text())  # valid JSON
    (tmp_path / "manifest.json").write_text("{broken")
    with pytest.raises(DataError, match="corrupt manifest"):
        read_dataset(tmp_path)


# --- tiling ---------------------------------------------------------------------------------------------------


def test_an_interrupted_dataset_write_leaves_the_dataset_as_it_was(tmp_path):
    """Ctrl-C or SIGTERM (any exception) while submaps are written leaves the dataset as it was: no new file, none of
    its files overwritten (a source written again included), no folder made."""
    def submaps(stop_after):
        for number in range(5):
            if number == stop_after:
                raise KeyboardInterrupt
            yield Submap(np.full((3, 3), float(number)) + UTM_OFFSET_M, UTM_OFFSET_M + 5.0,
                         np.stack([UTM_OFFSET_M, UTM_OFFSET_M + 10.0]), "map", number, None, "train")

    with pytest.raises(KeyboardInterrupt):
        write_dataset(tmp_path / "new", submaps(3), {})
    assert not (tmp_path / "new").exists()
    write_dataset(tmp_path / "old", submaps(99), {})
    before = {path.name: path.read_bytes() for path in (tmp_path / "old").iterdir()}
    with pytest.raises(KeyboardInterrupt):
        write_dataset(tmp_path / "old", (Submap(s.points, s.center, s.bounds, "other", s.index, None, "train")
                                         for s in submaps(2)), {})
    with pytest.raises(KeyboardInterrupt):  # the same source again: its files are not overwritten half way
        write_dataset(tmp_path / "old", (Submap(s.points + 1.0, s.center, s.bounds, "map", s.index, None, "train")
                                         for s in submaps(2)), {})
    assert {path.name: path.read_bytes() for path in (tmp_path / "old").iterdir()} == before
    assert len(read_dataset(tmp_path / "old").records) == 5


def test_a_dataset_write_that_fails_at_the_manifest_puts_the_old_files_back(tmp_path, monkeypatch):
    """A manifest write that fails (a full disk) after the submaps are in place puts the files they replaced back:
    the old manifest keeps describing its own files; and two submaps of one file name are a DataError."""
    import mapsqueeze.data.mapping as mapping

    def submaps(n):
        return [Submap(np.zeros((n, 3)) + UTM_OFFSET_M + 1.0, UTM_OFFSET_M + 5.0,
                       np.stack([UTM_OFFSET_M, UTM_OFFSET_M + 10.0]), "s", index, None, "train") for index in (0, 1)]

    write_dataset(tmp_path, submaps(3), {})
    before = {path.name: path.read_bytes() for path in tmp_path.iterdir()}

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(mapping, "atomic_write_bytes", full)
    with pytest.raises(DataError, match="cannot write"):
        write_dataset(tmp_path, submaps(5), {})
    assert {path.name: path.read_bytes() for path in tmp_path.iterdir()} == before
    assert [record.local_points().shape for record in read_dataset(tmp_path).records] == [(3, 3), (3, 3)]
    monkeypatch.undo()
    with pytest.raises(DataError, match="its file name .* is taken"):
        write_dataset(tmp_path / "dup", submaps(3) + submaps(3)[:1], {})
    assert not (tmp_path / "dup").exists()


def test_tiles_partition_the_map_with_exact_local_coordinates():
    rng = np.random.default_rng(5)
    points = UTM_OFFSET_M + rng.uniform([0, 0, 0], [130, 95, 40], (300_000, 3))
    points[:10, 0] = 500040.0  # exactly on a tile face: belongs to the upper tile
    world_grid = np.floor(points.min(axis=0) / TILE_SIZE_M) * TILE_SIZE_M
    tiles = tile_map(points, origin=world_grid)
    (face_tile,) = [tile for tile in tiles if 0 in tile.point_indices]
    assert face_tile.origin[0] == 500040.0 and face_tile.local_points(points)[0, 0] == 0.0
    indices = np.concatenate([tile.point_indices for tile in tiles])
    assert np.array_equal(np.sort(indices), np.arange(len(points)))  # every point in exactly one tile
    assert [tile.index for tile in tiles] == sorted(tile.index for tile in tiles)
    for tile in tiles:
        local = tile.local_points(points)
        assert local.dtype == np.float32
        assert local.min() >= 0 and np.all(local.max(axis=0) < tile.size)
        np.testing.assert_array_equal(tile.origin, np.floor(tile.origin / tile.size) * tile.size)
        reconstructed = tile.origin + local.astype(np.float64)
        assert np.abs(reconstructed - points[tile.point_indices]).max() < 1e-3
        members = points[tile.point_indices]
        assert np.all(members >= tile.bounds[0]) and np.all(members < tile.bounds[1])


def test_the_default_grid_is_fitted_to_the_map():
    rng = np.random.default_rng(6)
    # a 40 m submap around (0, 0, 0) whose points reach every face of its box: one tile (upper faces included)
    submap = rng.uniform([-20, -20, -7.5], [20, 20, 7.5], (5000, 3))
    submap[:3] = [[-20, -20, -7.5], [20, 20, 7.5], [20, -20, 7.5]]
    (tile,) = tile_map(submap)
    np.testing.assert_array_equal(tile.bounds, [[-20, -20, -7.5], [20, 20, 7.5]])
    local = tile.local_points(submap)
    assert local.min() >= 0 and np.all(local.max(axis=0) < tile.size) and len(tile.point_indices) == 5000
    # 130 x 95 x 40 m at UTM: 4 x 3 x 3 tiles centred on the map (5, 12.5 and 2.5 m of slack per side)
    points = UTM_OFFSET_M + rng.uniform([0, 0, 0], [130, 95, 40], (20_000, 3))
    origin, shape = fit_grid(points.min(axis=0), points.max(axis=0), TILE_SIZE_M)
    assert shape.tolist() == [4, 3, 3]
    np.testing.assert_allclose(origin, points.min(axis=0) - (shape * TILE_SIZE_M - np.ptp(points, axis=0)) / 2)
    tiles = tile_map(points)
    assert {tile.index for tile in tiles} <= {(i, j, k) for i in range(4) for j in range(3) for k in range(3)}
    assert sum(len(tile.point_indices) for tile in tiles) == len(points)
    np.testing.assert_allclose(tiles[0].origin, origin)


def test_tiles_with_points_on_faces_of_an_inexact_grid():
    rng = np.random.default_rng(7)
    origin, size = np.array([1234.567, -89.1, 3.3]), 0.3  # grid lines origin + k * 0.3 are not exact in float64
    on_faces = origin + rng.integers(-1000, 1000, (20_000, 3)) * size
    points = np.concatenate([on_faces, np.nextafter(on_faces, np.inf), np.nextafter(on_faces, -np.inf)])
    tiles = tile_map(points, tile_size=size, origin=origin)
    assert sum(len(tile.point_indices) for tile in tiles) == len(points)
    for tile in tiles[:: max(1, len(tiles) // 500)]:
        local = tile.local_points(points)
        assert local.min() >= 0 and local.max() < np.float32(size)
        assert np.abs(tile.origin + local - points[tile.point_indices]).max() < 1e-6


@pytest.mark.parametrize("grid", ["fitted", "origin", "origin and shape"])
def test_tiles_are_the_points_grouped_by_their_floor_index(grid):
    rng = np.random.default_rng(8)
    points = UTM_OFFSET_M + rng.uniform([-60, -50, -20], [70, 45, 20], (30_000, 3))
    points[:100] = points[100:200]  # repeated points land in one tile
    size = np.array([40.0, 30.0, 15.0])
    origin, shape = fit_grid(points.min(axis=0), points.max(axis=0), size)
    if grid == "origin":
        origin = UTM_OFFSET_M + 1.25  # points below it: negative indices
    rows = np.floor((points - origin) / size).astype(np.int64)
    if grid == "origin and shape":
        shape = shape - 1  # the last tiles of each axis take the points beyond them
        rows = np.clip(rows, 0, shape - 1)
    given = {"fitted": {}, "origin": {"origin": origin}, "origin and shape": {"origin": origin, "shape": shape}}
    tiles = tile_map(points, size, **given[grid])
    distinct, which = np.unique(rows, axis=0, return_inverse=True)
    assert (distinct < 0).any() == (grid == "origin") and len(tiles) == len(distinct) > 4
    for tile, index, number in zip(tiles, distinct, range(len(distinct))):
        assert tile.index == tuple(index.tolist())
        assert tile.point_indices.dtype == np.int64
        np.testing.assert_array_equal(tile.point_indices, np.flatnonzero(which.reshape(-1) == number))
        np.testing.assert_array_equal(tile.origin, origin + index * size)


def test_tiles_skip_empty_cells_and_follow_a_given_origin():
    points = np.array([[0.5, 0.5, 0.5], [95.0, 0.5, 0.5], [-0.5, 0.5, 0.5]])
    tiles = tile_map(points, tile_size=10.0, origin=[0.0, 0.0, 0.0])
    assert [tile.index for tile in tiles] == [(-1, 0, 0), (0, 0, 0), (9, 0, 0)]
    assert [tile.point_indices.tolist() for tile in tiles] == [[2], [0], [1]]
    np.testing.assert_array_equal(tiles[0].bounds, [[-10.0, 0.0, 0.0], [0.0, 10.0, 10.0]])


# --- CLI ------------------------------------------------------------------------------------------------------


def test_build_map_cli_missing_folder_is_one_error_line(run_cli, tmp_path):
    code, _, err = run_cli("build-map", str(tmp_path / "absent"), "-o", str(tmp_path / "out"))
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith("error:") and "no such folder" in err


def test_build_map_cli_without_poses_is_an_error(run_cli, tmp_path):
    write_points(tmp_path / "scan.ply", np.ones((5, 3)))
    code, _, err = run_cli("build-map", str(tmp_path), "-o", str(tmp_path / "out"))
    assert code == 2 and err.startswith("error:") and "--estimate-poses" in err


@pytest.mark.parametrize("option", [("--voxel", "0"), ("--spacing", "-1"), ("--dz", "nan"), ("--dz", "inf")])
def test_build_map_cli_bad_values_are_one_error_line_and_no_dataset(run_cli, kitti_root, tmp_path, option):
    """A bad voxel, spacing or box height is one `error:` line (no blank line before it) and writes no dataset."""
    root, *_ = kitti_root
    code, out, err = run_cli("build-map", str(root), "-o", str(tmp_path / "ds"), *option)
    assert (code, out) == (2, "") and err.startswith("error: ") and err.count("\n") == 1, err
    assert not (tmp_path / "ds").exists()


def test_build_map_cli_prints_plain_lines_when_piped(run_cli, kitti_root, tmp_path):
    root, *_ = kitti_root
    code, _, err = run_cli("build-map", str(root), "-o", str(tmp_path / "ds"), "--voxel", "0.05")
    n_points = read_dataset(tmp_path / "ds").records[0].n_points  # the one submap holds the whole map
    assert code == 0 and err.splitlines() == [f"kitti-00: 2 scans -> {n_points} map points -> 1 submaps",
                                              f"dataset: {tmp_path / 'ds'}"], err


def test_build_map_and_tile_cli(run_cli, kitti_root, tmp_path):
    root, *_ = kitti_root
    code, _, err = run_cli("build-map", str(root), "-o", str(tmp_path / "ds"), "--voxel", "0.05")
    assert code == 0, err
    (record,) = read_dataset(tmp_path / "ds").records
    assert (record.source, record.n_points, record.split) == ("kitti-00", 4, "train")
    points = UTM_OFFSET_M + np.random.default_rng(6).uniform(0, 50, (2000, 3))
    intensity, label = np.arange(2000, dtype=np.float32), (np.arange(2000) % 7).astype(np.uint16)
    write_points(tmp_path / "map.ply", points, attributes={"intensity": intensity, "label": label})
    code, _, err = run_cli("tile", str(tmp_path / "map.ply"), "-o", str(tmp_path / "tiles"),
                           "--tile", "25,25,50")
    assert code == 0, err
    records = read_dataset(tmp_path / "tiles").records
    assert sum(record.n_points for record in records) == 2000 and all(record.pose is None for record in records)
    for record in records:  # each tile keeps its points' attributes, dtypes included
        cloud = read_point_cloud(record.path)
        world = cloud.points + record.origin
        index = cKDTree(points).query(world)[1]
        assert cloud.attributes["label"].dtype == np.uint16
        np.testing.assert_array_equal(cloud.attributes["intensity"], intensity[index])
        np.testing.assert_array_equal(cloud.attributes["label"], label[index])
    code, _, err = run_cli("tile", str(tmp_path / "map.ply"), "-o", str(tmp_path / "t"),
                           "--tile", "25,25")
    assert code == 2 and err.startswith("error: --tile")
    code, out, err = run_cli("tile", str(tmp_path / "map.ply"), "-o", str(tmp_path / "t"), "--tile", "25,0,50")
    assert (code, out) == (2, "") and err == "error: --tile: expected three comma-separated positive lengths in " \
        "metres (x,y,z), got '25,0,50'\n"
