"""The encoder's voxel kernels of the patch planes (geometry.patches: `patch_setting_voxels`, `patch_option_cells`)
give the voxels of the reworked points that numpy's patch planes (geometry.patchesnumpy) and `patch_options` make,
whatever their blocking: points on voxel faces, points outside the box, a degenerate patch, several copy counts; the
patch-choice search's greedy sweeps (geometry.occupancy) choose as a plain reference of their rule does, ties
included."""

import math

import numpy as np
import pytest

from mapsqueeze.codec.postfilter import PATCH_OPTIONS
from mapsqueeze.codec.tilepoints import keep_inside
from mapsqueeze.geometry import occupancy, patches
from mapsqueeze.geometry.patches import patch_option_cells, patch_options, patch_setting_voxels
from mapsqueeze.geometry.patchesnumpy import patch_planes
from mapsqueeze.geometry.surface import GOLDEN_ANGLE, GOLDEN_FRACTION

FRAME = np.array([500_000.0, 4_000_000.0, 50.0])
EXTENT = np.array([6.0, 6.0, 2.0])
VOXEL = np.array([0.2, 0.2, 0.1])


def decoded_cloud(patch: int, n_patches: int, seed: int) -> np.ndarray:
    """float32 tile-local patches of `patch` points around random centres, partly outside the box [0, EXTENT]; half
    of the points snapped onto voxel faces (ties of the floor), patch 1 a single repeated point (no plane)."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-0.5, 6.5, (n_patches, 3)) * [1, 1, 0.35]
    cloud = np.repeat(centres, patch, axis=0) + rng.normal(0, [0.15, 0.15, 0.05], (n_patches * patch, 3))
    snapped = rng.random(len(cloud)) < 0.5
    cloud[snapped] = np.round(cloud[snapped] / VOXEL) * VOXEL
    cloud[patch:2 * patch] = cloud[patch]
    return cloud.astype(np.float32)


def cells_of(points: np.ndarray, low: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """The flat grid cell of each float32 point: voxel floor((p + FRAME) / VOXEL) from `low`."""
    voxels = np.floor((points.astype(np.float64) + FRAME) / VOXEL).astype(np.int64) - low
    return (voxels[:, 0] * shape[1] + voxels[:, 1]) * shape[2] + voxels[:, 2]


def grid_box() -> tuple[np.ndarray, np.ndarray]:
    low = np.floor(FRAME / VOXEL).astype(np.int64) - 1
    return low, np.floor((EXTENT + FRAME) / VOXEL).astype(np.int64) - low + 2


def test_the_disk_samples_fraction_is_the_remainder():
    """`_disk_sample` takes s x golden_fraction less its floor for its % 1.0: the same numbers for every sample
    index a tile of up to 2^22 points with 11 copies reaches, and beyond."""
    sample = np.concatenate([np.arange(1 << 22, dtype=np.float64) * 11, np.arange(2**40, 2**40 + 4096.0)])
    product = sample * GOLDEN_FRACTION
    assert np.array_equal(product % 1.0, product - np.floor(product))
    for s in (0, 1, 7, 12_345, 2**31 + 3):
        radius = 0.05 * math.sqrt((s * GOLDEN_FRACTION) % 1.0)
        angle = s * GOLDEN_ANGLE
        assert patches._disk_sample(s, 0.05, GOLDEN_ANGLE, GOLDEN_FRACTION) == (radius * math.cos(angle),
                                                                                radius * math.sin(angle))


@pytest.mark.parametrize("copies", [(1, 2), (3,), (2, 3), (0, 2)])
@pytest.mark.parametrize("block", [5, 4096])
def test_setting_voxels_are_those_of_numpys_patch_planes(monkeypatch, copies, block):
    """Every bit of the grid and every count as the points of numpy's `patch_planes` (the cloud cropped for bit 1,
    each setting's for bit 2 + c) mark them, with disk samples made in blocks shorter than a patch or longer
    than the cloud's, points on voxel faces and outside the box."""
    monkeypatch.setattr(patches, "SAMPLE_BLOCK_POINTS", block)
    patch = 25
    cloud = decoded_cloud(patch, 30, seed=len(copies) + block)
    low, shape = grid_box()
    grid = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    inside = patch_setting_voxels(cloud, patch, 0.7, copies, 0.05, EXTENT, FRAME, VOXEL, low, shape, grid)
    expected = np.zeros_like(grid)
    clouds = [keep_inside(cloud, EXTENT)] + [patch_planes(cloud, patch, 0.7, c, 0.05, EXTENT) for c in copies]
    for bit, points in enumerate(clouds, start=1):
        np.bitwise_or.at(expected, cells_of(points, low, shape), np.uint8(1 << bit))
    assert 0 < len(clouds[0]) < len(cloud)
    assert inside.tolist() == [len(points) for points in clouds]
    assert np.array_equal(grid, expected)


def test_option_cells_are_the_distinct_voxels_of_patch_options_points_on_voxel_faces():
    """Each list holds the distinct cells of its patch's points under its option (`patch_options`), points on
    voxel faces and outside the box, a patch without a plane included."""
    patch = 36
    cloud = decoded_cloud(patch, 24, seed=3)
    low, shape = grid_box()
    points, ends = patch_options(cloud, patch, PATCH_OPTIONS, EXTENT)
    cells, offsets = patch_option_cells(cloud, patch, PATCH_OPTIONS, EXTENT, FRAME, VOXEL, low, shape)
    linear = cells_of(points, low, shape)
    assert len(offsets) == len(ends) + 1
    for entry, (begin, end) in enumerate(zip(np.concatenate([[0], ends[:-1]]), ends)):
        listed = cells[offsets[entry]:offsets[entry + 1]].tolist()
        assert len(set(listed)) == len(listed) and set(listed) == set(linear[begin:end].tolist())


def reference_greedy(original, n_original, lists, n_options, choice, sweeps, bonus, bit_weight, rate_sweeps):
    """`occupancy._greedy_choices`'s rule in plain Python: lists[k][i] the distinct cells of patch i under option
    k; each sweep gives each patch in turn the option of the highest value with the other patches as chosen (ties:
    its current option, then the lowest); returns (IoU before, IoU after), `choice` updated in place."""
    n_patches = len(choice)

    def union(skip=None):
        return set().union(*(lists[choice[j]][j] for j in range(n_patches) if j != skip))

    def iou_now():
        occupied = union()
        return sum(original[c] for c in occupied) / max(1, n_original + sum(1 - original[c] for c in occupied))

    before = iou_now()
    for rate, count in ((0.0, sweeps), (bit_weight, rate_sweeps)):
        for _ in range(count):
            changed = False
            for i in range(n_patches):
                others = union(skip=i)
                shared = sum(original[c] for c in others)
                false = len(others) - shared
                counts = np.bincount(np.delete(choice, i), minlength=n_options)
                best, best_value = choice[i], -np.inf
                for option in range(n_options):
                    cells = lists[option][i]
                    new = [c for c in cells if c not in others]
                    gained = sum(original[c] for c in new)
                    credit = bonus[option] * sum(original[c] for c in cells) / max(1, len(cells))
                    value = (shared + gained + credit) / max(1, n_original + false + len(new) - gained)
                    if rate > 0.0:
                        value += rate * math.log2((counts[option] + 0.5) / (n_patches - 1 + 0.5 * n_options))
                    if value > best_value or (value == best_value and option == choice[i]):
                        best, best_value = option, value
                changed |= best != choice[i]
                choice[i] = best
            if not changed:
                break
    return before, iou_now()


@pytest.mark.parametrize("seed", range(6))
def test_the_greedy_sweeps_choose_as_the_reference(seed):
    """Random cell lists over few cells (many equal values: ties), with and without the copy bonus and the bits'
    rate term: the same choices and the same IoUs, to the bit."""
    rng = np.random.default_rng(seed)
    n_cells, n_patches, n_options = 40, 14, 5
    original = (rng.random(n_cells) < 0.4).astype(np.uint8)
    n_original = int(original.sum()) + 3  # some of the original's cells listed by no patch
    lists = [[np.sort(rng.choice(n_cells, rng.integers(0, 9), replace=False)) for _ in range(n_patches)]
             for _ in range(n_options)]
    cells = np.concatenate([lists[k][i] for k in range(n_options) for i in range(n_patches)]).astype(np.int32)
    offsets = np.concatenate([[0], np.cumsum([len(lists[k][i]) for k in range(n_options)
                                              for i in range(n_patches)])]).astype(np.int64)
    bonus = (rng.integers(0, 3, n_options) * 0.25 if seed % 2 else np.zeros(n_options)).astype(np.float64)
    bit_weight, rate_sweeps = (0.004, 2) if seed % 3 else (0.0, 0)
    start = rng.integers(0, n_options, n_patches)
    choice, expected_choice = start.astype(np.int64), start.astype(np.int64)
    found = occupancy._greedy_choices(original, n_original, cells, offsets, n_options, n_patches, choice, 3, bonus,
                                      bit_weight, rate_sweeps)
    expected = reference_greedy(original, n_original, [[set(c.tolist()) for c in row] for row in lists], n_options,
                                expected_choice, 3, bonus, bit_weight, rate_sweeps)
    assert found == expected
    assert np.array_equal(choice, expected_choice)
