"""Grid subsampling and capped radius neighbours against brute force; Morton codes and the spread subset."""

import numpy as np
import pytest

from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.grid import grid_subsample, radius_neighbors
from mapsqueeze.geometry.threads import set_threads, threads
from mapsqueeze.geometry.morton import (
    MAX_BITS,
    SPREAD_BITS,
    bit_reversal_order,
    coarse_to_fine_subset,
    morton_cells,
    morton_codes,
    morton_rank,
    spread_subset,
)


def brute_force_neighbors(source, queries, radius, cap):
    """The documented rule by brute force: in-radius neighbours in scan order of cells a hair over radius / 2,
    evenly capped."""
    source64, queries64 = source.astype(np.float64), queries.astype(np.float64)
    low = np.minimum(source64.min(axis=0), queries64.min(axis=0))
    cells = np.floor((source64 - low) / (radius * (1 + 1e-9) / 2)).astype(np.int64)
    scan_order = np.lexsort((np.arange(len(source)), cells[:, 2], cells[:, 1], cells[:, 0]))
    rank = np.empty(len(source), dtype=np.int64)
    rank[scan_order] = np.arange(len(source))
    rows = []
    for q in queries64:
        found = np.flatnonzero(((source64 - q) ** 2).sum(axis=1) <= radius**2)
        found = found[np.argsort(rank[found])]
        m = len(found)
        rows.append(found if m <= cap else found[(m * np.arange(cap)) // cap])
    width = max(len(r) for r in rows)
    return np.array([np.r_[r, np.full(width - len(r), len(source))] for r in rows])


def test_radius_neighbors_keep_an_evenly_spread_subset_whatever_the_thread_count():
    rng = np.random.default_rng(3)
    source = rng.random((3000, 3)).astype(np.float32)
    # queries on source points, between them, and outside the source's bounding box (empty neighbourhoods)
    queries = np.r_[source[::5], rng.random((300, 3)).astype(np.float32) * 1.6 - 0.3]
    expected = brute_force_neighbors(source, queries, 0.12, 25)
    assert (expected == len(source)).all(axis=1).any() and (expected != len(source)).all(axis=1).any()
    assert ((expected == len(source)).any(axis=1) & (expected != len(source)).any(axis=1)).any()
    previous = threads()
    try:
        for n in (1, 2, 3):
            set_threads(n)
            np.testing.assert_array_equal(radius_neighbors(source, queries, 0.12, 25), expected)
    finally:
        set_threads(previous)


def test_radius_neighbors_on_flat_and_degenerate_clouds():
    rng = np.random.default_rng(5)
    plane = np.c_[rng.random((2000, 2)), np.zeros(2000)].astype(np.float32)  # zero extent in z
    np.testing.assert_array_equal(radius_neighbors(plane, plane[:400], 0.05, 40),
                                  brute_force_neighbors(plane, plane[:400], 0.05, 40))
    one = np.zeros((1, 3), dtype=np.float32)
    np.testing.assert_array_equal(radius_neighbors(one, one, 0.1, 8), [[0]])
    assert radius_neighbors(one, one + 1, 0.1, 8).shape == (1, 0)


def test_radius_neighbors_on_clusters_with_ties_and_points_on_cell_faces():
    """Dense clusters (in-radius counts from a few to hundreds over caps that divide them unevenly, so every
    spread position and remainder of the cap's steps occurs), repeated points (ties in position and cell) and
    coordinates on multiples of the search cell's edge (points on cell faces), against the brute force."""
    rng = np.random.default_rng(11)
    centres = 0.1 + 0.8 * rng.random((12, 3))  # inside [0, 1): the faces grid starts at the lowest corner, 0
    counts = rng.integers(2, 400, len(centres))
    clusters = np.vstack([c + rng.normal(0, 0.01 * (1 + i % 4), (n, 3))
                          for i, (c, n) in enumerate(zip(centres, counts))])
    faces = np.round(rng.random((600, 3)) / 0.02) * 0.02  # the search cells' edges for radius 0.04 are 0.02
    source = np.vstack([clusters, faces, clusters[::7]]).astype(np.float32)
    queries = np.vstack([source[::3], faces[:50] + np.float32(0.01)]).astype(np.float32)
    for radius, cap in ((0.04, 7), (0.04, 64), (0.025, 1), (0.06, 13)):
        expected = brute_force_neighbors(source, queries, radius, cap)
        np.testing.assert_array_equal(radius_neighbors(source, queries, radius, cap), expected)
        np.testing.assert_array_equal(radius_neighbors(source, queries, radius, cap, np.int32), expected)


def test_to_local_rounds_each_float64_difference_to_float32():
    from mapsqueeze.geometry.tiling import to_local

    rng = np.random.default_rng(12)
    origin = np.array([1234567.891, -7654321.123, 12.5])
    points = origin + rng.random((5000, 3)) * 40.0
    points[:10] = origin + 40.0  # on the upper faces: clamped just inside
    size = np.full(3, 40.0)
    expected = (points - origin).astype(np.float32)
    np.testing.assert_array_equal(to_local(points, origin), expected)
    clamped = to_local(points, origin, size)
    assert clamped.dtype == np.float32 and (clamped < np.float32(40.0)).all()
    np.testing.assert_array_equal(clamped, np.clip(expected, np.float32(0), np.nextafter(np.float32(40), 0)))
    origins = origin + rng.random((5000, 3))  # an origin per point, or a (1, 3) one: numpy's broadcasting
    np.testing.assert_array_equal(to_local(points, origins), (points - origins).astype(np.float32))
    np.testing.assert_array_equal(to_local(points, origin[None, :], size), clamped)
    np.testing.assert_array_equal(to_local(points[0], origin), expected[0])


def test_grid_subsample_keeps_the_point_nearest_each_voxel_centre():
    rng = np.random.default_rng(4)
    points = rng.random((5000, 3)).astype(np.float32)
    kept = grid_subsample(points, 0.1)
    voxels = np.floor(points / 0.1).astype(np.int64)
    assert len(np.unique(voxels[kept], axis=0)) == len(kept) == len(np.unique(voxels, axis=0))
    distance = np.linalg.norm(points - (voxels + 0.5) * 0.1, axis=1)
    for index in kept[:200]:
        same = (voxels == voxels[index]).all(axis=1)
        assert distance[index] <= distance[same].min() + 1e-6


def test_run_over_ranges_covers_every_row_once_for_any_thread_count():
    from mapsqueeze.geometry.threads import run_over_ranges

    previous = threads()
    try:
        for n_threads, n_rows, min_rows in ((1, 1000, 10), (3, 1000, 10), (4, 5, 1), (2, 0, 256), (3, 700, 256)):
            set_threads(n_threads)
            hits = np.zeros(n_rows, dtype=np.int64)
            ranges = []

            def kernel(first, stop):
                ranges.append((first, stop))
                hits[first:stop] += 1

            run_over_ranges(kernel, n_rows, min_rows)
            assert (hits == 1).all()
            assert len(ranges) == max(1, min(n_threads, n_rows // min_rows))
    finally:
        set_threads(previous)


def _morton_by_bits(cells: np.ndarray, bits: int) -> np.ndarray:
    """The definition, one bit at a time: bit b of axis a goes to bit 3 b + a."""
    codes = np.zeros(len(cells), dtype=np.int64)
    for bit in range(bits):
        for axis in range(3):
            codes |= ((cells[:, axis] >> bit) & 1) << (3 * bit + axis)
    return codes


@pytest.mark.parametrize("bits", [1, 7, 16, MAX_BITS])
def test_morton_codes_interleave_bits_and_invert(bits):
    cells = np.random.default_rng(bits).integers(0, 1 << bits, (5000, 3))
    cells[0] = (1 << bits) - 1  # every bit set: the top code bit is 3 bits - 1, still a non-negative int64
    codes = morton_codes(cells, bits)
    assert codes.dtype == np.int64 and codes.min() >= 0
    np.testing.assert_array_equal(codes, _morton_by_bits(cells, bits))
    np.testing.assert_array_equal(morton_cells(codes), cells)


def test_morton_codes_refuse_cells_outside_the_grid():
    with pytest.raises(ValueError):
        morton_codes(np.array([[0, 0, 8]]), 3)
    with pytest.raises(ValueError):
        morton_codes(np.array([[0, -1, 0]]), 3)
    with pytest.raises(ValueError):
        morton_codes(np.zeros((1, 3), dtype=np.int64), MAX_BITS + 1)


def test_spread_subset_leaves_no_holes_and_follows_density():
    rng = np.random.default_rng(0)
    square = np.c_[rng.random((40000, 2)) * 10, np.zeros(40000)]  # 10 m x 10 m, 400 points per m^2
    keep = spread_subset(square, 400)
    assert len(keep) == 400 and len(np.unique(keep)) == 400 and np.all(np.diff(keep) > 0)
    np.testing.assert_array_equal(keep, spread_subset(square, 400))  # deterministic
    # every 1 m cell keeps some of its ~4 expected points, with less than half the spread of a random subset's
    cell_of = (square[:, 0] // 1 * 10 + square[:, 1] // 1).astype(int)
    per_cell = np.bincount(cell_of[keep], minlength=100)
    random_cells = np.bincount(cell_of[rng.choice(len(square), 400, replace=False)], minlength=100)
    assert per_cell.min() >= 1 and per_cell.var() < 0.5 * random_cells.var()
    # a cloud twice as dense on its left half keeps twice as many points there
    dense = np.concatenate([square, square[square[:, 0] < 5]])
    left = (dense[spread_subset(dense, 600), 0] < 5).sum()
    assert 380 <= left <= 420
    assert len(spread_subset(square[:10], 20)) == 10 and len(spread_subset(square[:1], 1)) == 1


def test_bit_reversal_order_halves_the_step_with_each_doubling():
    np.testing.assert_array_equal(bit_reversal_order(8), [0, 4, 2, 6, 1, 5, 3, 7])
    for count in (1, 2, 5, 1000):
        order = bit_reversal_order(count)
        assert sorted(order) == list(range(count))
    order = bit_reversal_order(1024)
    for k in (2, 16, 256):
        np.testing.assert_array_equal(np.sort(order[:k]), np.arange(k) * (1024 // k))


def test_coarse_to_fine_subset_is_the_spread_subset_and_every_prefix_is_spread():
    rng = np.random.default_rng(0)
    square = np.c_[rng.random((40000, 2)) * 10, np.zeros(40000)]
    order = coarse_to_fine_subset(square, 4096)
    np.testing.assert_array_equal(np.sort(order), spread_subset(square, 4096))
    cell_of = (square[:, 0] // 1 * 10 + square[:, 1] // 1).astype(int)
    for prefix in (400, 1000):  # a prefix covers every 1 m cell, spread more evenly than a random subset
        per_cell = np.bincount(cell_of[order[:prefix]], minlength=100)
        random_cells = np.bincount(cell_of[rng.choice(len(square), prefix, replace=False)], minlength=100)
        assert per_cell.min() >= 1 and per_cell.var() < 0.5 * random_cells.var()
    assert sorted(coarse_to_fine_subset(square[:10], 20)) == list(range(10))
    assert len(coarse_to_fine_subset(square, 0)) == 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_bounding_box_matches_the_axis_reduction(dtype):
    points = (np.random.default_rng(3).normal(size=(1001, 3)) * [5, 50, 500]).astype(dtype)
    low, high = bounding_box(points[::2])  # a strided view, as the codec passes
    np.testing.assert_array_equal(low, points[::2].min(axis=0))
    np.testing.assert_array_equal(high, points[::2].max(axis=0))
    assert low.dtype == dtype


def test_select_rows_is_boolean_indexing():
    from mapsqueeze.geometry.rows import select_rows

    rng = np.random.default_rng(5)
    for dtype in (np.float32, np.float64):
        points = rng.normal(size=(1000, 3)).astype(dtype)
        for mask in (rng.random(1000) < 0.7, np.zeros(1000, dtype=bool), np.ones(1000, dtype=bool)):
            for array in (points, points[:, [2, 0, 1]], np.asfortranarray(points)):
                chosen = select_rows(array, mask)
                assert chosen.dtype == dtype and chosen.shape == (mask.sum(), 3)
                assert np.array_equal(chosen, array[mask])


def test_morton_rank_cells_are_the_broadcast_formulas():
    """Cells computed column by column hold the values of (points - low) * scale floored over the whole array."""
    points = np.random.default_rng(5).normal(size=(20_000, 3)) * [20.0, 20.0, 3.0] + [3.7, -12.1, 0.4]
    low, extent = points.min(axis=0), float((points.max(axis=0) - points.min(axis=0)).max())
    cells = np.floor((points - low) * (((1 << SPREAD_BITS) - 1) / extent)).astype(np.int64)
    np.testing.assert_array_equal(morton_rank(points), morton_codes(cells, SPREAD_BITS))


def test_spread_subset_is_every_nth_of_the_stable_sort_of_the_codes():
    """The radix passes over the codes' 16-bit words and the mask of the picks give the indices of numpy's stable
    argsort of `morton_rank`, sorted: codes using all 48 bits, many ties (repeated and coincident points), float32
    and float64 points."""
    rng = np.random.default_rng(11)
    cloud = rng.normal(size=(150_000, 3)) * [15.0, 12.0, 2.0]
    cloud[::7] = cloud[3]  # a tie of ~21,000 points
    cloud[1::5] = cloud[::5]  # pairs of coincident points
    for points in (cloud, cloud.astype(np.float32), cloud[:, [2, 0, 1]]):
        codes = morton_rank(points)
        assert int(codes.max()).bit_length() > 2 * SPREAD_BITS
        order = np.argsort(codes, kind="stable")
        for count in (1, 999, 30_000, 149_999):
            expected = np.sort(order[(np.arange(count) * len(points)) // count])
            np.testing.assert_array_equal(spread_subset(points, count), expected)


def test_grid_nearest_distances_are_the_k_d_tree_search_s():
    """NearestGrid gives nearest_tree's distances bit for bit: uniform, flat and line clouds, a lattice whose queries
    tie between points, queries outside the cloud's box, far beyond MAX_SHELLS cells (left to a tree), one point."""
    from mapsqueeze.geometry.nearest import NearestGrid
    from mapsqueeze.metrics import nearest_tree

    rng = np.random.default_rng(8)
    flat = np.column_stack([rng.uniform(0, 40, 20_000), rng.uniform(0, 40, 20_000), np.zeros(20_000)])
    lattice = np.stack(np.meshgrid(np.arange(30.0), np.arange(30.0), np.arange(10.0)), -1).reshape(-1, 3) * 0.2
    cases = [(rng.uniform(0, 40, (50_000, 3)).astype(np.float32), rng.uniform(0, 40, (3000, 3))),
             (flat, rng.uniform(-2, 42, (3000, 3)) * [1, 1, 0.05]),
             (flat, rng.uniform(-500, 500, (200, 3))),
             (np.column_stack([np.linspace(0, 40, 5000), np.zeros(5000), np.zeros(5000)]), rng.normal(20, 10, (500, 3))),
             (lattice, np.round(rng.uniform(-1, 7, (3000, 3)), 1)),
             (np.full((4, 3), 2.5), rng.normal(0, 1, (100, 3)))]
    for points, queries in cases:
        expected = nearest_tree(points).query(np.ascontiguousarray(queries, dtype=np.float64), k=1)[0]
        assert np.array_equal(NearestGrid(points).distances(queries), expected)
    with pytest.raises(ValueError, match="at least one point"):
        NearestGrid(np.zeros((0, 3)))
