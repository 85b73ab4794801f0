"""The density rule at the faces between occupied tiles (codec.seams): a decode that piles points up just inside a
shared face is thinned to the density behind it; faces on the map's edge and surfaces along a face are left alone.

A small randomly initialised model (8 x 8 x 4 m tiles) codes the map; its decoder is replaced by one that grows an
even ground over the tile plus a sheet of extra points in the 5 cm inside each x side of the tile's box, the
pile-up of the shipped models at the faces of a multi-tile map (BENCHMARKS.md, "Seams at tile faces").
"""

import numpy as np
import pytest

import mapsqueeze
from mapsqueeze.codec.container import open_container
from mapsqueeze.codec.seams import NEAR_BAND_M, InternalFace, internal_faces, thin_at_faces
from mapsqueeze.model import ModelConfig, build_model, load_model, save_model

TILE = (8.0, 8.0, 4.0)
SHEET_M = 0.05


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    config = ModelConfig.for_rate("e1", tile_size=TILE, map_size=8.0, max_input_points=2000)
    return load_model(save_model(build_model(config, seed=1), tmp_path_factory.mktemp("model") / "tiny"))


def ground(rng: np.random.Generator, n: int, x_range: tuple[float, float]) -> np.ndarray:
    """n points of a 2 cm-rough ground at z = 0.5 m over x_range and y in [0.05, 7.95] m."""
    return np.column_stack([rng.uniform(*x_range, n), rng.uniform(0.05, 7.95, n), rng.normal(0.5, 0.02, n)])


def piled_up_decode(points, features, n_points=None):
    """Tile-local output: an even ground of 40,000 points over x in [0, 8] m and 4,000 more in a sheet in the
    SHEET_M inside each x side (0 and 8 m; the crop to the tile's box drops what lies beyond it)."""
    rng = np.random.default_rng(7)
    sheets = np.concatenate([ground(rng, 2000, (0.0, SHEET_M)), ground(rng, 2000, (8.0 - SHEET_M, 8.0))])
    return np.concatenate([ground(rng, 40_000, (0.0, 8.0)), sheets]).astype(np.float32)


def band_density(points: np.ndarray, x0: float, x1: float) -> float:
    """Points per metre of x in [x0, x1)."""
    return np.count_nonzero((points[:, 0] >= x0) & (points[:, 0] < x1)) / (x1 - x0)


def test_a_pile_up_inside_a_shared_face_is_thinned_to_the_density_behind_it(model, monkeypatch):
    rng = np.random.default_rng(0)
    two_tiles = ground(rng, 12_000, (0.01, 15.99)) + [500_000.0, 4_000_000.0, 50.0]
    data = mapsqueeze.compress(two_tiles, model=model, fallback=False, post_filter="off")
    reader, stream = open_container(data)
    stream.close()
    assert sorted(entry.index[0] for entry in reader.entries) == [0, 1]
    face = reader.header.origin[0] + TILE[0]
    monkeypatch.setattr(model, "decode", piled_up_decode)
    decoded = mapsqueeze.decompress(data, model=model, workers=1) - [500_000.0, 4_000_000.0, 50.0]
    face -= 500_000.0
    behind = band_density(decoded, face - 0.5, face - 0.2)
    assert behind > 1000
    for x0 in (face - SHEET_M, face):  # the sheets of both tiles at the shared face: gone
        assert band_density(decoded, x0, x0 + SHEET_M) < 1.3 * behind
    low, high = decoded[:, 0].min(), decoded[:, 0].max()
    for x0 in (low, high - SHEET_M):  # the sheets at the map's edges: kept
        assert band_density(decoded, x0, x0 + SHEET_M) > 1.5 * behind
    np.testing.assert_array_equal(decoded, mapsqueeze.decompress(data, model=model, workers=2)
                                  - [500_000.0, 4_000_000.0, 50.0])


def test_only_shared_faces_reached_by_the_tile_s_points_count(model):
    rng = np.random.default_rng(1)
    data = mapsqueeze.compress(ground(rng, 12_000, (0.01, 15.99)) + [500_000.0, 4_000_000.0, 50.0], model=model,
                               fallback=False)
    reader, stream = open_container(data)
    stream.close()
    occupied = {entry.index for entry in reader.entries}
    tile_size = np.asarray(TILE)
    for entry in reader.entries:
        faces = internal_faces(entry, occupied, tile_size)
        assert [(face.axis, face.upper) for face in faces] == [(0, entry.index[0] == 0)]
        assert internal_faces(entry, {entry.index}, tile_size) == ()  # alone in its file: no shared face


def test_a_surface_along_a_face_is_kept_and_the_rule_is_a_deterministic_subset():
    rng = np.random.default_rng(2)
    wall = np.column_stack([rng.normal(7.98, 0.01, 3000), rng.uniform(0, 8, 3000), rng.uniform(0, 4, 3000)])
    floor = ground(rng, 20_000, (0.0, 8.0))
    pile = ground(rng, 3000, (8.0 - SHEET_M, 8.0))
    cloud = np.concatenate([floor, pile, wall]).astype(np.float32)
    face = (InternalFace(axis=0, upper=True, plane_m=8.0),)
    thinned = thin_at_faces(cloud, face)
    kept = {row.tobytes() for row in thinned}
    assert all(row.tobytes() in kept for row in cloud[-3000:][cloud[-3000:, 2] > 1.0])  # the wall above the floor
    near_floor = (np.abs(thinned[:, 0] - 8.0) < NEAR_BAND_M) & (thinned[:, 2] < 0.6)
    assert np.count_nonzero(near_floor) < len(pile)  # the pile on the floor: thinned
    np.testing.assert_array_equal(thinned, thin_at_faces(cloud, face))
    assert thin_at_faces(cloud, ()) is cloud


def test_attributes_follow_the_thinned_points(model, monkeypatch):
    rng = np.random.default_rng(3)
    two_tiles = ground(rng, 12_000, (0.01, 15.99))
    monkeypatch.setattr(model, "decode", piled_up_decode)  # the encoder's attribute support: the tile before the rule
    data = mapsqueeze.compress(two_tiles + [500_000.0, 4_000_000.0, 50.0], model=model, fallback=False,
                               post_filter="off", attributes={"intensity": (two_tiles[:, 0] * 10).astype(np.uint16)}, workers=1)
    cloud = mapsqueeze.decompress_cloud(data, model=model, workers=1)
    np.testing.assert_array_equal(cloud.points, mapsqueeze.decompress(data, model=model, workers=1))
    assert len(cloud.attributes["intensity"]) == len(cloud.points) < 2 * 44_000
    assert np.abs(cloud.attributes["intensity"] - (cloud.points[:, 0] - 500_000.0) * 10).max() < 20  # 1 m voxels
