"""The decoder's numpy patch planes (geometry.patchesnumpy) give the bytes of the encoder's compiled kernel
(geometry.patches) on real decoded tiles and on degenerate patches, with and without the box crop."""

import numpy as np
import pytest

from mapsqueeze.codec.postfilter import PATCH_LEVELS, PATCH_RADIUS_M, PATCH_STRENGTH
from mapsqueeze.geometry import patches, patchesnumpy
from mapsqueeze.io import read_points
from mapsqueeze.model import load_model


def assert_same_bytes(points, patch, copies, upper=None, strength=PATCH_STRENGTH):
    compiled = patches.patch_planes(points, patch, strength, copies, PATCH_RADIUS_M, upper)
    ported = patchesnumpy.patch_planes(points, patch, strength, copies, PATCH_RADIUS_M, upper)
    assert ported.dtype == np.float32 and ported.shape == compiled.shape
    assert ported.tobytes() == compiled.tobytes()
    return ported


@pytest.mark.parametrize("model_name", ["e1", "e2"])
def test_real_decoded_tiles_give_the_compiled_kernels_bytes(kitti_submap, model_name):
    """A 40 m tile of the real KITTI submap through the shipped model's encoder and decoder: the uncropped output
    at 1 and 2 extra points per point, whole and cropped to the tile's box (part of it leaves the box)."""
    model = load_model(model_name)
    points = read_points(kitti_submap)
    low = points.min(axis=0)
    local = points - low
    local = local[(local < np.asarray(model.config.tile_size)).all(axis=1)]
    embedding = model.encode(local)
    decoded = model.decode(embedding.points, embedding.features)
    patch = int(np.prod(model.config.upsampling_factors[-PATCH_LEVELS:]))
    upper = local.max(axis=0)
    for copies in (1, 2):
        whole = assert_same_bytes(decoded, patch, copies)
        cropped = assert_same_bytes(decoded, patch, copies, upper)
        assert len(decoded) * (1 + copies) == len(whole) > len(cropped) > 0


def test_degenerate_patches_give_the_compiled_kernels_bytes():
    """Patches of one repeated point, of zeros and negative zeros, on a line, on an exact plane, at UTM
    coordinates, patches of 1 and 2 points, 0 to 2 copies, a box that crops some and a box that crops all."""
    rng = np.random.default_rng(3)
    patch = 125
    line = np.outer(np.linspace(-1.0, 1.0, patch), [1.0, 2.0, 3.0])
    plane = np.column_stack([rng.uniform(0, 1, (patch, 2)), np.full(patch, 0.5)])
    utm = rng.normal(0, 3, (patch, 3)) + [500_000.0, 4_000_000.0, 50.0]
    cases = [np.tile([[1.0, 2.0, 3.0]], (patch, 1)), np.zeros((patch, 3)), np.full((patch, 3), -0.0), line, plane,
             utm, rng.normal(0, 2, (patch * 40, 3))]
    for points in cases + [np.concatenate(cases[:-1])]:
        for copies in (0, 1, 2):
            for upper in (None, np.array([0.9, 1.5, 2.5]), np.full(3, -1.0)):
                assert_same_bytes(points, patch, copies, upper)
    small = rng.normal(0, 1, (60, 3))
    for size in (1, 2, 3):
        assert_same_bytes(small, size, 2, np.ones(3), strength=1.0)
    assert len(assert_same_bytes(np.zeros((patch, 3)), patch, 1, np.full(3, -1.0))) == 0


def test_blocks_of_patches_number_the_disk_samples_across_the_cloud(monkeypatch):
    """The port reworks a cloud in blocks of whole patches; the disk samples stay numbered by the cloud's rows."""
    points = np.random.default_rng(4).normal(0, 1, (64 * 9, 3))
    whole = patchesnumpy.patch_planes(points, 64, PATCH_STRENGTH, 2, PATCH_RADIUS_M)
    monkeypatch.setattr(patchesnumpy, "_BLOCK_POINTS", 128)
    assert patchesnumpy.patch_planes(points, 64, PATCH_STRENGTH, 2, PATCH_RADIUS_M).tobytes() == whole.tobytes()
    assert_same_bytes(points, 64, 2)


def test_points_that_are_not_whole_patches_are_refused():
    with pytest.raises(ValueError, match="patches"):
        patchesnumpy.patch_planes(np.zeros((10, 3)), 4, PATCH_STRENGTH, 1, PATCH_RADIUS_M)
    assert patchesnumpy.patch_planes(np.zeros((0, 3)), 4, PATCH_STRENGTH, 1, PATCH_RADIUS_M).shape == (0, 3)


def test_chosen_options_give_the_bytes_of_the_compiled_kernel_patch_by_patch(kitti_submap):
    """Patch choices (`postfilter.apply_patch_choices`): every option of PATCH_OPTIONS on the patches of a real e1
    decoded tile, each patch alone with its disk samples numbered from its first point, cropped and whole."""
    from mapsqueeze.codec.postfilter import PATCH_OPTIONS

    model = load_model("e1")
    points = read_points(kitti_submap)
    local = points - points.min(axis=0)
    local = local[(local < np.asarray(model.config.tile_size)).all(axis=1)]
    embedding = model.encode(local)
    decoded = model.decode(embedding.points, embedding.features)
    patch = int(np.prod(model.config.upsampling_factors))
    choices = np.random.default_rng(6).integers(0, len(PATCH_OPTIONS), len(decoded) // patch)
    for upper in (local.max(axis=0), None):
        expected = np.concatenate([patches.patch_planes(decoded[i * patch:(i + 1) * patch], patch,
                                                        *PATCH_OPTIONS[option], upper)
                                   for i, option in enumerate(choices)])
        chosen = patchesnumpy.patch_planes_chosen(decoded, patch, PATCH_OPTIONS, choices, upper)
        assert chosen.dtype == np.float32 and chosen.tobytes() == expected.tobytes()
    assert len(patchesnumpy.patch_planes_chosen(np.zeros((0, 3)), patch, PATCH_OPTIONS, [])) == 0
    with pytest.raises(ValueError, match="choices"):
        patchesnumpy.patch_planes_chosen(decoded, patch, PATCH_OPTIONS, choices[1:])


def test_patch_options_return_only_the_rows_they_wrote():
    """`patches.patch_options` allocates room for every point and copy and keeps those inside the box: the rows
    past the last patch's end are not points (their bytes are whatever the allocation held)."""
    from mapsqueeze.codec.postfilter import PATCH_OPTIONS

    points = np.random.default_rng(8).normal(0, 1, (64 * 20, 3))
    chosen, ends = patches.patch_options(points, 64, PATCH_OPTIONS, np.full(3, 1.0))
    assert len(chosen) == ends[-1] < len(points) * sum(1 + option[1] for option in PATCH_OPTIONS)
    for index, option in enumerate(PATCH_OPTIONS):
        expected = np.concatenate([patches.patch_planes(points[i * 64:(i + 1) * 64], 64, *option, np.full(3, 1.0))
                                   for i in range(20)])
        first = ends[index * 20 - 1] if index else 0
        assert chosen[first:ends[index * 20 + 19]].tobytes() == expected.tobytes()


def test_running_sums_add_the_rows_one_after_the_other_from_zero():
    """`_running_sum` (numpy's reduction over the outer axis) adds row by row from 0.0 like the kernel: the bytes
    of a loop over the rows, on values of 12 orders of magnitude (any other order rounds differently) and on signed
    zeros."""
    rng = np.random.default_rng(5)
    for rows, columns in ((625, (6, 52)), (125, (3, 7)), (1, (3, 2)), (3, (2,)), (1000, (1,))):
        values = rng.standard_normal((rows, *columns)) * 10.0 ** rng.integers(-3, 9, (rows, *columns))
        values[:, ..., 0] = -0.0
        looped = np.zeros(columns)
        for row in values:
            looped += row
        assert patchesnumpy._running_sum(values).tobytes() == looped.tobytes()
    assert patchesnumpy._running_sum(np.full((4, 3), -0.0)).tobytes() == np.zeros(3).tobytes()  # 0.0 + -0.0
