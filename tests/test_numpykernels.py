"""The encoder's numpy path for small maps (`codec.compress.NUMPY_KERNEL_POINTS`): each numpy version of a compiled
kernel gives its twin's bytes, and a small map's compress through either path gives the same file, loading no
numba on the numpy path."""

import subprocess
import sys

import numpy as np
import pytest

import mapsqueeze
from mapsqueeze.codec import compress as compress_module
from mapsqueeze.codec.tilepoints import keep_inside
from mapsqueeze.codec.postfilter import PATCH_OPTIONS, PATCH_STRENGTH
from mapsqueeze.geometry import (
    cells,
    cellsnumpy,
    grid,
    gridnumpy,
    introsort,
    introsortnumpy,
    nearest,
    nearestnumpy,
    occupancy,
    occupancynumpy,
)
from mapsqueeze.geometry.inside import points_inside
from mapsqueeze.metrics import IOU_VOXEL_M
from mapsqueeze.model import influences, influencesnumpy
from mapsqueeze.model.kernels import grid_kernel_points

FRAME = np.array([500_000.0, 4_000_000.0, 50.0])
EXTENT = np.array([12.0, 12.0, 4.0])


def tie_keys() -> list[np.ndarray]:
    """Sort keys with long runs of ties, sorted and reversed runs, float32 ties and tiny arrays."""
    cases = [np.zeros(100, np.float32), np.arange(1000, dtype=np.float32), np.arange(1000, dtype=np.float32)[::-1],
             np.r_[np.arange(5000), np.arange(5000)[::-1]].astype(np.float32),
             (np.arange(30000) % 7).astype(np.float32),
             np.float32(1000) + np.random.default_rng(4).random(30000).astype(np.float32) * np.float32(0.7),
             np.round(np.random.default_rng(2).random(20000) * 50) / np.float32(50)]
    for seed in range(60):
        rng = np.random.default_rng(seed)
        cases.append(rng.integers(0, int(rng.integers(1, 40)), int(rng.integers(0, 3000))).astype(np.float32))
    return cases


def median_of_three_killer(n: int) -> np.ndarray:
    """Keys that drive the compiled introsort to its depth limit (its heap sort): McIlroy's adversary, answering
    the kernel's own comparisons (run as Python) so as to make every pivot a bad one."""
    values: list = [None] * n
    state = {"solid": 0, "candidate": 0}

    def freeze(i):
        values[i] = state["solid"]
        state["solid"] += 1

    class Key:
        def __init__(self, i):
            self.i = i

        def __lt__(self, other):
            a, b = self.i, other.i
            if values[a] is None and values[b] is None:
                freeze(a if a == state["candidate"] else b)
            if values[a] is None:
                state["candidate"] = a
                return False
            if values[b] is None:
                state["candidate"] = b
                return True
            return values[a] < values[b]

    names = ("_swap", "_partition", "_insert_unguarded", "_insertion_sort", "_sift", "_heap_sort")
    kernels = {name: getattr(introsort, name) for name in names}
    try:
        for name, kernel in kernels.items():
            setattr(introsort, name, kernel.py_func)
        keys = np.empty(n, dtype=object)
        keys[:] = [Key(i) for i in range(n)]
        introsort._introsort.py_func(keys, np.arange(n))
    finally:
        for name, kernel in kernels.items():
            setattr(introsort, name, kernel)
    for i in range(n):
        if values[i] is None:
            freeze(i)
    return np.array(values, dtype=np.float32)


def test_the_numpy_introsort_orders_like_the_compiled_one():
    for keys in tie_keys() + [np.random.default_rng(n).integers(0, 4, n).astype(np.float64) for n in range(20)]:
        assert np.array_equal(introsortnumpy.introsort_argsort(keys), introsort.introsort_argsort(keys))
    with pytest.raises(ValueError, match="NaN"):
        introsortnumpy.introsort_argsort(np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="1-D"):
        introsortnumpy.introsort_argsort(np.zeros((2, 2)))


def test_the_numpy_introsort_heap_sorts_at_the_depth_limit_like_the_compiled_one(monkeypatch):
    heap_sorts = []
    heap_sort = introsortnumpy._heap_sort
    monkeypatch.setattr(introsortnumpy, "_heap_sort", lambda *args: heap_sorts.append(args[2:]) or heap_sort(*args))
    for n in (200, 700):
        killer = median_of_three_killer(n)
        for keys in (killer, np.floor(killer / 3)):  # distinct keys, then ties
            assert np.array_equal(introsortnumpy.introsort_argsort(keys), introsort.introsort_argsort(keys))
    assert heap_sorts


def lattice_cloud(seed: int, n: int) -> np.ndarray:
    """float32 normalised points: half of them on a lattice of the grid sizes (exact ties of the subsampling keys,
    points on cell faces), duplicates included, half scattered."""
    rng = np.random.default_rng(seed)
    lattice = rng.integers(0, 40, (n // 2, 3)) * np.float32(0.0125)
    scattered = rng.random((n - n // 2, 3)) * np.float32(0.5)
    return np.concatenate([lattice, scattered]).astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_numpy_grid_subsampling_and_neighbours_are_the_compiled_ones(seed, monkeypatch):
    points = lattice_cloud(seed, 3000)
    for voxel in (0.0125, 0.025, 0.05, 0.1):
        kept = gridnumpy.grid_subsample(points, voxel)
        assert np.array_equal(kept, grid.grid_subsample(points, voxel))
        queries = points[kept]
        for radius, cap in ((0.025, 16), (float(np.float32(0.025)), 16), (0.05, 40), (0.2, 7)):  # 2nd: ties
            for dtype in (np.int32, np.int64):
                expected = grid.radius_neighbors(points, queries, radius, cap, dtype)
                found = gridnumpy.radius_neighbors(points, queries, radius, cap, dtype)
                assert found.dtype == expected.dtype and np.array_equal(found, expected)
    monkeypatch.setattr(gridnumpy, "CHUNK_CANDIDATES", 500)  # many query ranges
    assert np.array_equal(gridnumpy.radius_neighbors(points, points, 0.05, 30),
                          grid.radius_neighbors(points, points, 0.05, 30))
    empty = np.zeros((0, 3), dtype=np.float32)
    assert gridnumpy.grid_subsample(empty, 0.1).shape == (0,)
    assert np.array_equal(gridnumpy.radius_neighbors(empty, points[:5], 0.1, 4),
                          grid.radius_neighbors(empty, points[:5], 0.1, 4))


def test_the_numpy_influences_are_the_compiled_ones():
    points = lattice_cloud(3, 2000)
    queries = points[grid.grid_subsample(points, 0.05)]
    neighbors = grid.radius_neighbors(points, queries, 0.06, 30, np.int32)
    assert (neighbors == len(points)).any()  # shadow neighbours
    scattered = np.random.default_rng(5).normal(0, 0.03, (27, 3)).astype(np.float32)
    for kernel_points in (grid_kernel_points(0.06, 27), scattered):
        for first, stop in ((0, len(queries)), (7, 40)):
            expected = influences.cpu_influences(queries, points, neighbors, kernel_points, 0.03, first, stop)
            found = influencesnumpy.cpu_influences(queries, points, neighbors, kernel_points, 0.03, first, stop)
            assert found.tobytes() == expected.tobytes()


def test_the_numpy_crop_to_the_box_is_the_compiled_one():
    upper = EXTENT.astype(np.float32)
    rng = np.random.default_rng(9)
    near_faces = (rng.uniform(-1, 1, (20_000, 3)) * 0.05 + rng.choice([0.0, 1.0], (20_000, 3)) * upper)
    spread = rng.uniform(-0.5, 1.5, (20_000, 3)) * upper
    special = np.array([[0, 0, 0], upper, [-0.0, 1, 1], [np.nan, 1, 1], [1, np.inf, 1], [1, 1, -np.inf],
                        [np.nextafter(np.float32(0), np.float32(-1)), 1, 1], [1, 1, np.nextafter(upper[2], 99)]])
    clouds = {"empty": np.empty((0, 3)), "none inside": spread[(spread > upper).any(axis=1)],
              "all inside": np.clip(spread, 0, upper), "near the faces": near_faces, "spread": spread,
              "special values": np.concatenate([special, spread[:50], special])}
    for name, cloud in clouds.items():
        for dtype in (np.float32, np.float64):
            cloud = np.asarray(cloud, dtype=dtype)
            expected, found = keep_inside(cloud, EXTENT), keep_inside(cloud, EXTENT, compiled=True)
            assert found.dtype == expected.dtype and found.shape == expected.shape, name
            assert found.tobytes() == expected.tobytes(), name
            assert found.flags.c_contiguous
    assert len(keep_inside(clouds["special values"], EXTENT, compiled=True)) == 2 * 3 + np.sum(
        (spread[:50] >= 0).all(axis=1) & (spread[:50] <= upper).all(axis=1))
    assert 0 < len(points_inside(clouds["spread"], upper)) < len(clouds["spread"])
    assert len(points_inside(clouds["none inside"], upper)) == 0


def test_the_numpy_cell_distances_are_the_compiled_ones():
    rng = np.random.default_rng(6)
    edge = 0.25
    points = np.concatenate([rng.uniform(-1, 12, (3000, 3)), rng.integers(-4, 48, (500, 3)) * edge,  # on faces
                             rng.integers(0, 48, (500, 3)) * edge + edge / 2 + rng.normal(0, 1e-9, (500, 3))])
    upper = np.array([10.0, 11.0, 9.5], dtype=np.float32)
    for margin in (0.0, 0.01):
        expected = cells.own_cell_distances(points, edge, 40, upper, margin)
        assert np.isnan(expected).any() and not np.isnan(expected).all()
        assert cellsnumpy.own_cell_distances(points, edge, 40, upper, margin).tobytes() == expected.tobytes()


def test_the_k_d_tree_distances_are_the_grid_ones():
    rng = np.random.default_rng(7)
    cloud = np.concatenate([rng.random((4000, 3)) * [30, 30, 3], rng.integers(0, 30, (1000, 3)).astype(float)])
    queries = np.concatenate([rng.random((2000, 3)) * [30, 30, 3], cloud[:500], [[400.0, -300.0, 20.0]]])
    expected = nearest.NearestGrid(cloud).distances(queries)
    assert nearestnumpy.NearestTree(cloud).distances(queries).tobytes() == expected.tobytes()
    with pytest.raises(ValueError):
        nearestnumpy.NearestTree(np.zeros((0, 3)))


def patch_cloud(seed: int, patch: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """(original in world metres, a decoder-ordered float32 tile-local cloud of patches): flat and tilted patches
    and blocks, some points on voxel faces and some outside the box [0, EXTENT]."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-0.3, EXTENT - 0.3, (60, 3))
    offsets = rng.normal(0, [0.3, 0.3, 0.05], (60, patch, 3))
    offsets[::3] = rng.uniform(-0.3, 0.3, (20, patch, 3))
    decoded = (centres[:, None, :] + offsets).reshape(-1, 3)
    decoded[::17] = np.round(decoded[::17] / IOU_VOXEL_M) * IOU_VOXEL_M  # on voxel faces (relative to FRAME's grid)
    original = decoded[rng.permutation(len(decoded))[:4000]] + rng.normal(0, 0.03, (4000, 3))
    return original + FRAME, decoded.astype(np.float32)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_numpy_occupancy_ious_are_the_compiled_ones(seed):
    original, decoded = patch_cloud(seed)
    clouds = [decoded, decoded[::2], decoded[:0]]
    assert occupancynumpy.occupancy_ious(original, clouds, FRAME, IOU_VOXEL_M) == \
        occupancy.occupancy_ious(original, clouds, FRAME, IOU_VOXEL_M)
    for patch in (256, 64):
        for upper in (EXTENT, EXTENT * 0.4):
            arguments = (original, decoded, patch, PATCH_STRENGTH, (1, 2), 0.05, upper, FRAME, IOU_VOXEL_M)
            expected = occupancy.patch_setting_ious(*arguments)
            assert expected is not None and occupancynumpy.patch_setting_ious(*arguments) == expected
    far = original + 1e4
    assert occupancynumpy.patch_setting_ious(far, decoded, 256, PATCH_STRENGTH, (1, 2), 0.05, EXTENT, FRAME,
                                             IOU_VOXEL_M) is None
    outside = decoded + np.float32(100)
    assert occupancynumpy.patch_setting_ious(original, outside, 256, PATCH_STRENGTH, (1, 2), 0.05, EXTENT, FRAME,
                                             IOU_VOXEL_M) is None


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("weights", [(), (2.0,), (2.0, 1e-4, 2), (0.0, 3e-4, 2)])
def test_the_numpy_patch_choice_search_is_the_compiled_one(seed, weights, monkeypatch):
    original, decoded = patch_cloud(seed)
    start = np.random.default_rng(seed).integers(0, len(PATCH_OPTIONS), len(decoded) // 256)

    def search(module, upper=EXTENT):
        return module.patch_option_ious(original, decoded, 256, PATCH_OPTIONS, upper, start, FRAME, IOU_VOXEL_M, 3,
                                        *weights)

    expected = search(occupancy)
    found = search(occupancynumpy)
    assert np.array_equal(found[0], expected[0]) and found[1:] == expected[1:]
    monkeypatch.setattr(occupancynumpy, "CHUNK_ROWS", 1000)  # a patch range per option row block
    found = search(occupancynumpy, EXTENT * 0.5)
    expected = search(occupancy, EXTENT * 0.5)
    assert np.array_equal(found[0], expected[0]) and found[1:] == expected[1:]


def test_the_numpy_search_falls_back_to_the_points_box_and_to_none_as_the_compiled_one(monkeypatch):
    original, decoded = patch_cloud(2)
    start = np.zeros(len(decoded) // 256, dtype=np.int64)
    for limit in (200_000, 50_000, 1_000):
        monkeypatch.setattr(occupancy, "_MAX_OCCUPANCY_VOXELS", limit)
        monkeypatch.setattr(occupancynumpy, "MAX_OCCUPANCY_VOXELS", limit)
        expected = occupancy.patch_option_ious(original, decoded, 256, PATCH_OPTIONS, EXTENT * 4, start, FRAME,
                                               IOU_VOXEL_M, 3)
        found = occupancynumpy.patch_option_ious(original, decoded, 256, PATCH_OPTIONS, EXTENT * 4, start, FRAME,
                                                 IOU_VOXEL_M, 3)
        assert (found is None) == (expected is None)
        if expected is not None:
            assert np.array_equal(found[0], expected[0]) and found[1:] == expected[1:]
    assert found is None


def small_map(seed: int) -> np.ndarray:
    """A small map: a ground and a wall with 2 cm noise, a third of the points on a 5 cm lattice (exact ties of the
    encoder's sort keys, points on its cell faces and on IoU voxel faces), far from the origin."""
    rng = np.random.default_rng(seed)
    n = 2500
    ground = np.c_[rng.random((n, 2)) * 25, rng.normal(0.3, 0.02, n)]
    wall = np.c_[rng.random(n // 2) * 25, np.full(n // 2, 9.0) + rng.normal(0, 0.02, n // 2), rng.random(n // 2) * 5]
    lattice = np.c_[rng.integers(0, 400, (n // 2, 2)) * 0.05, rng.integers(0, 40, n // 2) * 0.05]
    return np.concatenate([ground, wall, lattice]) + [600_000.0, 5_000_000.0, 40.0]


@pytest.mark.parametrize("model", ["e0", "e1", "e2", "e3"])
def test_a_small_map_compresses_to_the_same_bytes_through_either_path(model, monkeypatch):
    assert len(small_map(0)) <= compress_module.NUMPY_KERNEL_POINTS
    for seed in (0, 1, 2):
        points = small_map(seed)
        numpy_file = mapsqueeze.compress(points, model=model, workers=1)
        monkeypatch.setattr(compress_module, "NUMPY_KERNEL_POINTS", 0)
        assert mapsqueeze.compress(points, model=model, workers=1) == numpy_file
        monkeypatch.undo()


def test_a_small_map_with_a_rate_target_compresses_to_the_same_bytes_through_either_path(monkeypatch):
    points = small_map(3)
    for options in ({"max_error": 0.08}, {"bpp": 0.5}):
        numpy_file = mapsqueeze.compress(points, workers=1, **options)
        monkeypatch.setattr(compress_module, "NUMPY_KERNEL_POINTS", 0)
        assert mapsqueeze.compress(points, workers=1, **options) == numpy_file
        monkeypatch.undo()


def test_a_small_compress_loads_no_numba_and_a_larger_one_does(tmp_path):
    probe = ("import sys\nimport numpy as np\nimport mapsqueeze\nfrom mapsqueeze.codec import compress\n"
             "rng = np.random.default_rng(0)\n"
             "points = np.c_[rng.random((3000, 2)) * 30, rng.normal(1, 0.05, 3000)]\n"
             "assert len(mapsqueeze.compress(points, model='e3', workers=2)) > 0\n"
             "print('numba' in sys.modules)\n"
             "n = compress.NUMPY_KERNEL_POINTS + 1\n"
             "more = np.c_[rng.random((n, 2)) * 30, np.ones(n)]\n"
             "assert len(mapsqueeze.compress(more, model='e3', workers=1)) > 0\n"
             "print('numba' in sys.modules)\n")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["False", "True"]
