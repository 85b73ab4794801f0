"""Metrics of the paper (D_e, D_perp, IoU, Chamfer, bpp) and PCA normals, on hand-computed cases."""

import json
from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from mapsqueeze.errors import InvalidPointCloudError, MapsqueezeError
from mapsqueeze.geometry.normals import normals_pca
from mapsqueeze.metrics import (
    bits_per_point,
    chamfer_distance,
    d_euclidean,
    d_point_to_plane,
    evaluate,
    iou,
    nearest_tree,
)

UTM_OFFSET = np.array([456_789.0, 5_432_101.0, 42.0])  # world coordinates as large as real maps have
SPACING = 0.1
SIDE = 30


def tilted_frame() -> np.ndarray:
    """A fixed rotation whose columns are the plane's in-plane axes u, v and its normal n."""
    rotation, _ = np.linalg.qr(np.random.default_rng(7).normal(size=(3, 3)))
    return rotation


def tilted_grid_plane() -> tuple[np.ndarray, np.ndarray]:
    """A SIDE x SIDE grid of SPACING metres on a tilted plane far from the origin, and the rotation used."""
    rotation = tilted_frame()
    u, v = np.meshgrid(np.arange(SIDE) * SPACING, np.arange(SIDE) * SPACING, indexing="ij")
    local = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
    return local @ rotation.T + UTM_OFFSET, rotation


def test_normals_of_tilted_plane_match_analytic_normal():
    plane, rotation = tilted_grid_plane()
    normals = normals_pca(plane)
    assert normals.shape == plane.shape
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    assert np.abs(normals @ rotation[:, 2]).min() > 1 - 1e-9


def test_normals_of_noisy_plane_are_close_to_analytic_normal():
    rng = np.random.default_rng(3)
    rotation = tilted_frame()
    local = np.column_stack([rng.uniform(0, 4, 5000), rng.uniform(0, 4, 5000), rng.normal(0, 0.005, 5000)])
    normals = normals_pca(local @ rotation.T)
    assert np.median(np.abs(normals @ rotation[:, 2])) > 0.999


def test_dense_cloud_normals_are_taken_in_blocks_with_the_same_result(monkeypatch):
    """A cloud with more neighbour pairs than PAIRS_AT_ONCE (an unfiltered scan: 200k points on 10 x 10 m made 2.5
    GB of pairs and a MemoryError) is taken in blocks of points: the same neighbourhoods, the same normals, and
    query_pairs, which holds every pair at once, is not called."""
    import mapsqueeze.geometry.normals as normals_module

    rng = np.random.default_rng(4)
    rotation = tilted_frame()
    local = np.column_stack([rng.uniform(0, 3, 3000), rng.uniform(0, 3, 3000), rng.normal(0, 0.01, 3000)])
    cloud = np.vstack([local @ rotation.T, np.repeat(local[:1] @ rotation.T, 200, axis=0)])  # and a pile of copies
    at_once = normals_pca(cloud)
    monkeypatch.setattr(normals_module, "PAIRS_AT_ONCE", 5000)
    from scipy.spatial import cKDTree

    held = []

    class NoPairsAtOnce(cKDTree):
        def query_pairs(self, *args, **kwargs):
            raise AssertionError("query_pairs holds every pair at once")

        def query_ball_point(self, *args, **kwargs):
            found = super().query_ball_point(*args, **kwargs)
            if not kwargs.get("return_length"):
                held.append(sum(map(len, found)))
            return found

    in_blocks = normals_pca(cloud, tree=NoPairsAtOnce(cloud))
    largest = int(cKDTree(cloud).query_ball_point(cloud, 0.5, return_length=True).max())  # a point in the pile
    assert len(held) > 3 and max(held) <= max(5000 // 4, largest)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", at_once, in_blocks)), 1.0, atol=1e-9)


def test_isolated_point_falls_back_to_its_nearest_points():
    plane, rotation = tilted_grid_plane()
    far = plane[0] + 0.8 * rotation[:, 0] - 0.7 * rotation[:, 1]  # in the plane, > 0.5 m from every grid point
    normals = normals_pca(np.vstack([plane, far]))
    assert abs(normals[-1] @ rotation[:, 2]) > 1 - 1e-9


def test_shift_along_normal_gives_d_perp_and_d_e_of_the_shift():
    gt, rotation = tilted_grid_plane()
    rec = gt + 0.05 * rotation[:, 2]
    assert d_point_to_plane(gt, rec) == pytest.approx(0.05, abs=1e-6)
    assert d_euclidean(gt, rec) == pytest.approx(0.05, abs=1e-6)
    assert chamfer_distance(gt, rec) == pytest.approx(0.05**2, abs=1e-7)


def test_shift_within_plane_by_grid_spacing():
    gt, rotation = tilted_grid_plane()
    rec = gt + SPACING * rotation[:, 0]
    # Only the first row of GT (and the last row of rec) lacks a partner at distance 0: its nearest is SPACING away.
    assert d_point_to_plane(gt, rec) == pytest.approx(0.0, abs=1e-6)
    assert d_euclidean(gt, rec) == pytest.approx(SPACING / SIDE, abs=1e-6)


def test_d_perp_uses_the_matched_ground_truth_normal_for_reconstructed_points():
    # GT: horizontal grid z = 0. rec: a vertical wall of points at x = 1.0 above GT grid nodes, z = 0.02 .. 0.10.
    axis = np.arange(21) * SPACING
    x, y = np.meshgrid(axis, axis, indexing="ij")
    gt = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    y_rec, z_rec = np.meshgrid(axis, 0.02 * np.arange(1, 6), indexing="ij")
    rec = np.column_stack([np.full(y_rec.size, 1.0), y_rec.ravel(), z_rec.ravel()])
    # GT -> rec: nearest is the lowest wall point (z = 0.02) in the same row: |n_z * dz| = 0.02 for every GT point.
    # rec -> GT: the GT node below, normal z: |dz| = 0.02 * k, mean 0.06 (a rec-side normal, x, would give 0).
    assert d_point_to_plane(gt, rec) == pytest.approx(0.02 / 2 + 0.06 / 2, abs=1e-9)


def test_identical_clouds():
    gt, _ = tilted_grid_plane()
    metrics = evaluate(gt, gt.copy())
    assert metrics.d_e == 0.0 and metrics.d_perp == 0.0 and metrics.chamfer == 0.0
    assert metrics.iou == 1.0
    assert (metrics.n_gt, metrics.n_rec, metrics.bpp) == (SIDE * SIDE, SIDE * SIDE, None)


def test_disjoint_clouds_have_zero_iou():
    gt, _ = tilted_grid_plane()
    assert iou(gt, gt + np.array([0.0, 0.0, 5.0])) == 0.0


def test_iou_counts_voxels_of_both_grids():
    # Voxels 0.2 x 0.2 x 0.1 m: GT occupies voxels A, B; rec occupies B (two points), C. IoU = 1 / 3.
    gt = np.array([[0.05, 0.05, 0.05], [0.25, 0.05, 0.05]])
    rec = np.array([[0.21, 0.01, 0.01], [0.39, 0.19, 0.09], [0.05, 0.05, 0.15]])
    assert iou(gt, rec) == pytest.approx(1 / 3)
    assert iou(gt, rec, voxel=(1.0, 1.0, 1.0)) == 1.0


def test_asymmetric_two_point_one_point_example():
    gt = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    rec = np.array([[1.0, 0.0, 0.0]])
    # GT -> rec distances 1, 2 (mean 1.5); rec -> GT distance 1. D_e = 1.5 / 2 + 1 / 2.
    assert d_euclidean(gt, rec) == pytest.approx(1.25)
    # Squared: 1, 4 (mean 2.5); 1. Chamfer = 2.5 / 2 + 1 / 2.
    assert chamfer_distance(gt, rec) == pytest.approx(1.75)
    assert evaluate(rec, gt).d_e == pytest.approx(1.25)


def test_bits_per_point():
    assert bits_per_point(1000, 4000) == 2.0
    gt, _ = tilted_grid_plane()
    assert evaluate(gt, gt, n_bytes=90).bpp == pytest.approx(8 * 90 / (SIDE * SIDE))


@pytest.mark.parametrize(
    "gt, rec",
    [
        (np.zeros((0, 3)), np.zeros((1, 3))),
        (np.zeros((2, 3)), np.full((1, 3), np.nan)),
        (np.zeros((2, 2)), np.zeros((1, 3))),
    ],
)
def test_bad_clouds_raise_typed_error(gt, rec):
    with pytest.raises(InvalidPointCloudError):
        evaluate(gt, rec)


def test_wrong_normals_shape_raises_typed_error():
    gt, _ = tilted_grid_plane()
    with pytest.raises(InvalidPointCloudError):
        d_point_to_plane(gt, gt, gt_normals=np.ones((3, 3)))


def test_non_positive_normal_radius_raises_typed_error():
    plane, _ = tilted_grid_plane()
    with pytest.raises(MapsqueezeError):
        normals_pca(plane, radius=0.0)


def write_ply(path: Path, points: np.ndarray) -> None:
    vertices = np.array([tuple(p) for p in points], dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    PlyData([PlyElement.describe(vertices, "vertex")]).write(str(path))


@pytest.fixture
def cloud_files(tmp_path):
    gt, rotation = tilted_grid_plane()
    gt_path, rec_path = tmp_path / "gt.ply", tmp_path / "rec.npy"
    write_ply(gt_path, gt)
    np.save(rec_path, gt + 0.05 * rotation[:, 2])
    return gt_path, rec_path


def test_cli_eval_prints_table(run_cli, cloud_files):
    """Piped (as run_cli captures it): plain lines, a header and one row per metric, no box characters."""
    code, out, _ = run_cli("eval", *map(str, cloud_files), "--bytes", "225")
    assert code == 0
    lines = out.splitlines()
    assert lines[0].split() == ["metric", "value", "unit"] and len(lines) == 8
    assert lines[1].split() == ["D_e", "0.050000", "m"] and "2.0000" in lines[5]  # bpp = 8 * 225 / 900
    assert all(line == line.rstrip() and not set(line) & set("┃│┏━┡└─") for line in lines)


def test_cli_eval_json(run_cli, cloud_files, tmp_path):
    compressed = tmp_path / "map.msq"
    compressed.write_bytes(b"x" * 450)
    args = ["eval", *map(str, cloud_files), "--compressed", str(compressed), "--json"]
    code, out, _ = run_cli(*args)
    assert code == 0
    result = json.loads(out)
    assert result["d_e"] == pytest.approx(0.05, abs=1e-6) and result["bpp"] == pytest.approx(4.0)
    assert (result["n_gt"], result["n_rec"]) == (SIDE * SIDE, SIDE * SIDE)


def test_cli_eval_missing_file_is_one_error_line(run_cli, cloud_files, tmp_path):
    code, out, err = run_cli("eval", str(cloud_files[0]), str(tmp_path / "missing.ply"))
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "missing.ply" in lines[0]


def test_real_kitti_ground_normals_are_vertical(kitti_submap):
    vertex = PlyData.read(str(kitti_submap))["vertex"]
    points = np.column_stack([vertex["x"], vertex["y"], vertex["z"]]).astype(np.float64)
    normals = normals_pca(points)
    assert np.isfinite(normals).all()
    lowest_decile = points[:, 2] < np.quantile(points[:, 2], 0.1)
    assert np.mean(np.abs(normals[lowest_decile, 2]) > 0.9) > 0.9


def test_d_euclidean_gives_the_distances_of_scipys_tree_and_uses_known_ones():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(5)
    gt, rec = rng.normal(size=(3000, 3)), rng.normal(size=(2000, 3)).astype(np.float32).astype(np.float64)
    rec[:10] = gt[:10]  # duplicates: distance 0
    forward, backward = cKDTree(rec).query(gt)[0], cKDTree(gt).query(rec)[0]
    assert d_euclidean(gt, rec) == forward.mean() / 2 + backward.mean() / 2
    known = forward.copy()
    known[::3] = np.nan
    assert d_euclidean(gt, rec, nearest_tree(gt), known) == d_euclidean(gt, rec)
    known[1] = 100.0  # a known distance is taken as given
    assert d_euclidean(gt, rec, gt_to_rec=known) > d_euclidean(gt, rec)


@pytest.mark.parametrize("leaf_points", [1, 64, 1000])
def test_nearest_tree_distances_do_not_depend_on_its_leaf_size(leaf_points):
    rng = np.random.default_rng(9)
    points = np.round(rng.uniform(0, 5, size=(5000, 3)), 1)  # on a 10 cm grid: many equal distances
    queries = np.round(rng.uniform(-1, 6, size=(3000, 3)), 2)
    expected = nearest_tree(points).query(queries, k=1)[0]
    assert np.array_equal(nearest_tree(points, leaf_points).query(queries, k=1)[0], expected)
