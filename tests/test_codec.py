"""The .msq codec: container integrity, embedding coders, whole-map round trips, --bbox, determinism, CLI errors.

A small randomly initialised model (8 x 8 x 4 m tiles, r_s = 2 m) saved to a tmp dir keeps the network fast; the
codec does not care whether the weights are trained.
"""

import struct
import sys
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

import mapsqueeze
from mapsqueeze.api import RATE_TARGET_MODELS
from mapsqueeze.codec import decompress as decompress_module
from mapsqueeze.codec.compress import compress_chunks
from mapsqueeze.codec.container import TileCoding, open_container
from mapsqueeze.codec.embedding import (
    CellGrid,
    Precision,
    QuantModel,
    Quantiser,
    dequantise,
    quantise,
)
from mapsqueeze.codec.entropy import (
    ByteReader,
    ByteWriter,
    Histogram,
    SymbolReader,
    SymbolWriter,
    decode_gaps,
    encode_gaps,
)
from mapsqueeze.codec.latent import LATENT_CODECS, LatentLayout
from mapsqueeze.codec.octreetile import decode_octree_tile
from mapsqueeze.codec.rawtile import RAW_STEP_M, decode_raw_tile, encode_raw_tile
from mapsqueeze.codec.seams import internal_faces
from mapsqueeze.errors import ContainerError, DecodeLimitError, InvalidPointCloudError, MapsqueezeError, ModelError
from mapsqueeze.io import read_point_cloud, read_points, write_points
from mapsqueeze.model import ModelConfig, build_model, load_model, save_model

UTM = np.array([500_000.123, 4_000_000.456, 50.0])
TILE = np.array([8.0, 8.0, 4.0])


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory):
    config = ModelConfig.for_rate("e1", tile_size=tuple(TILE), map_size=8.0, max_input_points=2000)
    return save_model(build_model(config, seed=1), tmp_path_factory.mktemp("model") / "tiny")


@pytest.fixture(scope="module")
def model(model_dir):
    return load_model(model_dir)


def make_map(seed: int = 0, n_ground: int = 6000) -> np.ndarray:
    """A 20 x 14 m ground with a wall and a sparse post, at UTM coordinates: 3 x 2 x 2 tiles of 8 x 8 x 4 m."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0, 20, n_ground), rng.uniform(0, 14, n_ground),
                              rng.normal(0.5, 0.03, n_ground)])
    wall = np.column_stack([rng.uniform(2, 18, 2000), rng.normal(10.0, 0.02, 2000), rng.uniform(0.5, 6.0, 2000)])
    post = np.column_stack([rng.normal(19, 0.05, 4), rng.normal(1, 0.05, 4), rng.uniform(4.5, 7.5, 4)])
    return np.concatenate([ground, wall, post]) + UTM


@pytest.fixture(scope="module")
def map_points():
    return make_map()


@pytest.fixture(scope="module")
def compressed(map_points, model):
    return mapsqueeze.compress(map_points, model=model, precision="q")


@pytest.fixture(scope="module")
def network_only(map_points, model):
    """The paper's mode: without the octree fallback, which beats the untrained network on every tile, and the
    decode post-filter."""
    return mapsqueeze.compress(map_points, model=model, precision="q", fallback=False, post_filter="off")


def read_all_payloads(data: bytes) -> None:
    """Open a container and CRC-check every payload (what decompress does before decoding each tile)."""
    reader, stream = open_container(data)
    with stream:
        for position in range(len(reader.entries)):
            reader.payload(position)


# --- entropy coding building blocks ----------------------------------------------------------------------------

@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(-300, 300), min_size=1, max_size=400), st.integers(0, 2**40))
def test_histogram_stream_round_trips(values, big):
    values = np.array(values)
    histogram = Histogram.fit(values)
    gaps = np.abs(values) * 1000 + big
    symbols = SymbolWriter()
    symbols.histogram(values, histogram)
    encode_gaps(symbols, gaps, Histogram.fit(np.array([int(g).bit_length() for g in gaps])))
    header = ByteWriter()
    histogram.write(header)
    read_back = Histogram.read(ByteReader(header.getvalue(), "test"))
    reader = SymbolReader(symbols.getvalue(), "test")
    np.testing.assert_array_equal(reader.histogram(read_back, len(values)), values)
    np.testing.assert_array_equal(
        decode_gaps(reader, len(gaps), Histogram.fit(np.array([int(g).bit_length() for g in gaps]))), gaps)
    reader.finish()


def test_varints_round_trip_and_an_overlong_one_is_refused():
    writer = ByteWriter()
    for value in (0, 1, 127, 128, 300, 2**40):
        writer.varint(value)
    reader = ByteReader(writer.getvalue(), "test")
    assert [reader.varint() for _ in range(6)] == [0, 1, 127, 128, 300, 2**40]
    reader.expect_end()
    for overlong in (b"\x80\x00", b"\x81\x80\x00"):
        with pytest.raises(ContainerError, match="overlong varint"):
            ByteReader(overlong, "test").varint()


def test_a_histogram_constriction_cannot_normalise_is_a_container_error():
    """Histogram.read accepts alphabets up to 2^24 values; one constriction rejects is a corrupt file, not a crash."""
    with pytest.raises(ContainerError, match="entropy table of 16,777,215 values is not usable"):
        Histogram(0, 2**24 - 1, np.array([5], dtype=np.uint8)).model()


def test_a_histogram_whose_model_was_built_pickles_and_still_codes():
    """Dask ships the map's header (its histograms) to the workers after the coordinator has coded with them."""
    import pickle

    values = np.array([0, 1, 1, 2, 2, 2, 5, 9, 9, 9])
    histogram = Histogram.fit(values)
    symbols = SymbolWriter()
    symbols.histogram(values, histogram)  # builds and caches the constriction model
    copy = pickle.loads(pickle.dumps(histogram))
    assert (copy.low, copy.width) == (histogram.low, histogram.width)
    np.testing.assert_array_equal(copy.codes, histogram.codes)
    reader = SymbolReader(symbols.getvalue(), "test")
    np.testing.assert_array_equal(reader.histogram(copy, len(values)), values)
    reader.finish()


def test_histogram_codes_skewed_data_near_its_entropy():
    rng = np.random.default_rng(0)
    values = np.round(rng.laplace(0, 4, 20000)).astype(int)
    histogram = Histogram.fit(values)
    symbols = SymbolWriter()
    symbols.histogram(values, histogram)
    _, counts = np.unique(values, return_counts=True)
    entropy_bits = -(counts * np.log2(counts / counts.sum())).sum()
    assert len(symbols.getvalue()) * 8 < 1.03 * entropy_bits


def test_varints_and_reader_bounds():
    writer = ByteWriter()
    for value in (0, 1, 127, 128, 2**40):
        writer.varint(value)
    writer.svarint(-5)
    reader = ByteReader(writer.getvalue(), "test")
    assert [reader.varint() for _ in range(5)] == [0, 1, 127, 128, 2**40]
    assert reader.svarint() == -5
    with pytest.raises(ContainerError, match="test: truncated"):
        reader.raw(1)
    with pytest.raises(ContainerError, match="out of range"):
        ByteReader(b"\x80\x01", "test").varint(limit=100)


# --- embedding coders ------------------------------------------------------------------------------------------

def synthetic_embedding(rng, grid: CellGrid, m: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Points nearest-to-centre-like inside distinct cells of the grid, 3-D features of unit scale."""
    cells = rng.choice(grid.n_cells, m, replace=False)
    points = grid.centres(grid.cell_coords(cells)) + rng.uniform(-0.5, 0.5, (m, 3)) * grid.cell_m * 0.9
    return points.astype(np.float32), rng.normal(0, [1.0, 0.5, 2.0], (m, 3)).astype(np.float32)


def test_q_coder_round_trips_bit_exactly_to_the_dequantised_embedding():
    rng = np.random.default_rng(1)
    grid = CellGrid(2.0, (40.0, 40.0, 15.0))
    tiles = [synthetic_embedding(rng, grid, m) for m in (300, 50, 1)]
    quantiser = Quantiser.fit(np.concatenate([f for _, f in tiles]), 0.02)
    quantised = [quantise(p, f, grid, quantiser) for p, f in tiles]
    model = QuantModel.fit(quantised, grid, quantiser)
    header = ByteWriter()
    model.write(header)
    read_model = QuantModel.read(ByteReader(header.getvalue(), "header"), grid, len(quantiser.feature_mean))
    for (points, features), q in zip(tiles, quantised):
        expected_points, expected_features = dequantise(q, grid, quantiser)
        decoded = read_model.decode(model.encode(q), len(points), "tile")
        got_points, got_features = dequantise(decoded, grid, read_model.quantiser)
        assert got_points.tobytes() == expected_points.tobytes()
        assert got_features.tobytes() == expected_features.tobytes()
        # The lattice is close to the input: at most half a step per coordinate.
        distance, _ = cKDTree(got_points).query(points)
        assert distance.max() <= np.sqrt(3) * 0.02 / 2 + 1e-6
        # Features: at most half a step per principal axis away (plus float16 rounding of the stored transform).
        feature_error = np.linalg.norm(np.sort(got_features, axis=0) - np.sort(features, axis=0), axis=1)
        assert np.median(feature_error) <= np.sqrt(3) * quantiser.feature_step / 2 + 1e-2


@pytest.mark.parametrize(("step_std", "expected"), [(0.3, np.int8), (1e-3, np.int16), (1e-6, np.int32),
                                                    (1e-10, np.int64)])
def test_compact_quantised_tiles_fit_the_same_histograms(step_std, expected):
    """A map-wide fit holds its tiles compact (offsets, features in the smallest integer type: int8 to int32, or
    int64 where nothing smaller holds them); the histograms (or the error of one too wide) are the int64 tiles'."""
    rng = np.random.default_rng(2)
    grid = CellGrid(2.0, (40.0, 40.0, 15.0))
    tiles = [synthetic_embedding(rng, grid, m) for m in (300, 50, 1)]
    quantiser = Quantiser.fit(np.concatenate([f for _, f in tiles]), 0.02, step_std)
    quantised = [quantise(p, f, grid, quantiser) for p, f in tiles]
    compact = [q.compact() for q in quantised]
    assert {q.features.dtype for q in compact} == {np.dtype(expected)}
    assert all(q.offsets.itemsize < 8 for q in compact)
    for full, small in zip(quantised, compact):
        assert all(np.array_equal(getattr(full, name), getattr(small, name))
                   for name in ("cells", "offsets", "features"))

    def header(tiles_held):  # or the error of a histogram too wide to fit
        writer = ByteWriter()
        try:
            QuantModel.fit(tiles_held, grid, quantiser).write(writer)
        except ValueError as exc:
            return str(exc)
        return writer.getvalue()

    assert header(quantised) == header(compact)


def test_q_coder_keeps_duplicate_cells():
    grid = CellGrid(2.0, (40.0, 40.0, 15.0))
    points = np.array([[1.0, 1.0, 1.0], [1.5, 1.2, 0.9], [39.9, 39.9, 14.9]], dtype=np.float32)
    features = np.zeros((3, 3), dtype=np.float32)
    quantiser = Quantiser.fit(features, 0.02)
    q = quantise(points, features, grid, quantiser)
    model = QuantModel.fit([q], grid, quantiser)
    decoded = model.decode(model.encode(q), 3, "tile")
    np.testing.assert_array_equal(decoded.cells, q.cells)
    np.testing.assert_array_equal(decoded.offsets, q.offsets)


@pytest.mark.parametrize("name", ["f32", "f16"])
def test_float_coders_round_trip(name):
    precision = Precision[name]
    rng = np.random.default_rng(2)
    layout = LatentLayout(2.0, (40.0, 40.0, 15.0), 3)
    points, features = synthetic_embedding(rng, CellGrid(2.0, layout.tile_size), 100)
    codec = LATENT_CODECS[precision].fit([(points, features)], layout)
    payload = codec.encode(points, features)
    assert len(payload) == 1 + 100 * 6 * (4 if precision is Precision.f32 else 2)
    got_points, got_features = codec.decode(payload, 100, "tile")
    if precision is Precision.f32:
        assert got_points.tobytes() == points.tobytes() and got_features.tobytes() == features.tobytes()
    else:
        np.testing.assert_array_equal(got_features, features.astype(np.float16).astype(np.float32))
        np.testing.assert_allclose(got_points, points, atol=0.02)


def pinned_embeddings() -> list[tuple[np.ndarray, np.ndarray]]:
    """Three tiles' embeddings (150, 400 and 1 points) of fixed random numbers, tile-local metres and features."""
    rng = np.random.default_rng(5)
    tiles = []
    for count in (150, 400, 1):
        points = (rng.random((count, 3)) * [40.0, 40.0, 15.0]).astype(np.float32)
        features = (rng.normal(size=(count, 3)) * [1.5, 0.8, 0.3] + [0.2, -0.1, 0.0]).astype(np.float32)
        tiles.append((points, features))
    return tiles


@pytest.mark.parametrize(("name", "steps", "compact", "digest"), [
    ("f32", {}, True, "ea4d8b510d1a4007a17bcf227e7696d0cc1b21f5c681333640463aa06ea4f96a"),
    ("f16", {}, True, "7a9d65e3918f723db1bb8ef1d3cb6a12cca3aaf2eb41835967c757e77f2f3b16"),
    # q at the steps of format version 6's first writer (0.01 x r_s, 0.2 std) in the header state of versions 1 to
    # 6: the coding itself is unchanged
    ("q", {"position_step_m": 0.02, "feature_step_std": 0.2}, False,
     "2bcde87386437f20ccbaf010c2415113fabbb7f5f9c4def85eba1334cac66160"),
    ("q", {}, False, "9912c53afdf8f04cab04c1c36aa112905d4528176d1d76fa8bb5a39109725487"),  # the default steps
    # the compact header state of version 7 (no channel count, one position step): the same payloads
    ("q", {"position_step_m": 0.02, "feature_step_std": 0.2}, True,
     "910a6bdef3e5a88f45ca9f543275690e70dd489e296338c4890aea128daad04d"),
    ("q", {}, True, "d7035a7d9d0f435a9f45a65f0ef962bb7ead638b5dd3a06db0a5723345c7befc"),
])
def test_latent_codec_bytes_are_pinned(name, steps, compact, digest):
    """Header state and tile payloads of each precision must not drift: pinned digests, changed only with the
    format or the default q steps; the codec read back from its header state decodes what the fitted one encoded."""
    import hashlib

    layout = LatentLayout(2.0, (40.0, 40.0, 15.0), 3)
    tiles = pinned_embeddings()
    codec = LATENT_CODECS[Precision[name]].fit(tiles, layout, **steps)
    writer = ByteWriter()
    codec.write(writer, compact)
    payloads = [codec.encode(points, features) for points, features in tiles]
    assert hashlib.sha256(writer.getvalue() + b"".join(payloads)).hexdigest() == digest
    read = LATENT_CODECS[Precision[name]].read(ByteReader(writer.getvalue(), "header"), layout, compact)
    for (points, _), payload in zip(tiles, payloads):
        expected, got = codec.decode(payload, len(points), "tile"), read.decode(payload, len(points), "tile")
        assert expected[0].tobytes() == got[0].tobytes() and expected[1].tobytes() == got[1].tobytes()


@pytest.mark.parametrize("name", ["f32", "f16", "q"])
def test_latent_refit_keeps_decoded_points(name):
    """A codec refitted over a subset of the tiles (the tiles that keep the network) decodes them to the same
    embedding as the codec fitted over all tiles; q refits its histograms to the subset only."""
    layout = LatentLayout(2.0, (40.0, 40.0, 15.0), 3)
    tiles = pinned_embeddings()
    codec = LATENT_CODECS[Precision[name]].fit(tiles, layout)
    refitted = codec.refit(tiles[1:])
    for points, features in tiles[1:]:
        expected = codec.decode(codec.encode(points, features), len(points), "tile")
        got = refitted.decode(refitted.encode(points, features), len(points), "tile")
        assert expected[0].tobytes() == got[0].tobytes() and expected[1].tobytes() == got[1].tobytes()
    if name == "q":
        assert refitted.model.quantiser is codec.model.quantiser
        assert len(refitted.encode(*tiles[1])) < len(codec.encode(*tiles[1]))
    else:
        assert refitted is codec


def test_raw_tile_is_near_exact():
    rng = np.random.default_rng(3)
    points = rng.uniform(0, 1, (500, 3)) * TILE
    decoded = decode_raw_tile(encode_raw_tile(points, TILE), TILE, 500, "tile")
    distance, _ = cKDTree(decoded).query(points)
    assert len(decoded) == 500 and distance.max() <= np.sqrt(3) * RAW_STEP_M / 2 + 1e-6


# --- whole maps ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fallback", [True, False])
def test_round_trip_of_a_multi_tile_map(map_points, compressed, network_only, model, fallback):
    data = compressed if fallback else network_only
    reader, stream = open_container(data)
    stream.close()
    assert len(reader.entries) >= 6
    assert any(e.coding is TileCoding.raw for e in reader.entries)  # the 4-point post: raw (<= 4 points a centre)
    assert any(e.coding is (TileCoding.octree if fallback else TileCoding.network) for e in reader.entries)
    assert fallback or not any(e.coding is TileCoding.octree for e in reader.entries)
    decoded = mapsqueeze.decompress(data, model=model)
    assert decoded.dtype == np.float64 and np.isfinite(decoded).all()
    assert len(mapsqueeze.decompress(data, model=model, n_points=len(map_points))) == len(map_points)
    # Decoded points stay inside the boxes of their tiles' input points.
    low, high = map_points.min(axis=0), map_points.max(axis=0)
    assert (decoded >= low - 1e-3).all() and (decoded <= high + 1e-3).all()
    info = mapsqueeze.info(data)
    assert info.n_points == len(map_points) and info.file_bytes == len(data)
    assert info.bits_per_point < 2.0


def test_decoded_points_outside_a_tile_are_dropped_not_clamped_onto_its_faces(network_only, model):
    """The network grows surfaces past a tile's box: those points go, the count comes from the ones inside."""
    reader, stream = open_container(network_only)
    with stream:
        position = next(p for p, e in enumerate(reader.entries) if e.coding is TileCoding.network)
        entry = reader.entries[position]
        extent = entry.frame_extent_m(np.asarray(reader.header.tile_size)).astype(np.float32)
        rng = np.random.default_rng(0)
        inside = (rng.uniform(0.05, 0.95, (3000, 3)) * extent).astype(np.float32)
        outside = inside[:1000] + np.float32(2.0) * extent  # beyond the upper faces

        class GrownPastTheFaces:
            config = model.config  # the decode limit counts its native output

            def decode(self, points, features, n_points=None):
                assert n_points is None  # the native output, cropped before resampling
                return np.concatenate([inside, outside])

        local = decompress_module.decode_payload(reader.header, entry, reader.payload(position),
                                                 GrownPastTheFaces(), 2000, "tile")
    assert len(local) == 2000
    assert cKDTree(inside).query(local)[0].max() == 0  # every point is one grown inside, none clamped onto a face


def test_a_map_no_larger_than_a_tile_is_one_tile_wherever_it_lies(model):
    rng = np.random.default_rng(3)
    patch = np.column_stack([rng.uniform(0, 8, 3000), rng.uniform(0, 8, 3000), rng.normal(2.0, 0.05, 3000)])
    for offset in ([0.0, 0.0, 0.0], [-4.0, -4.0, -2.0], [3.3, -7.1, 1.9]):  # across world multiples of the tile
        data = mapsqueeze.compress(patch + UTM + offset, model=model)
        assert mapsqueeze.info(data).n_tiles == 1


@pytest.mark.parametrize("precision", ["f32", "f16"])
def test_float_precisions_round_trip(map_points, model, precision):
    data = mapsqueeze.compress(map_points, model=model, precision=precision, fallback=False)
    assert mapsqueeze.info(data).precision == precision
    assert len(mapsqueeze.decompress(data, model=model, n_points=len(map_points))) == len(map_points)


def test_other_densities(compressed, model, map_points):
    assert len(mapsqueeze.decompress(compressed, model=model, n_points=1234)) == 1234
    denser = mapsqueeze.decompress(compressed, model=model, density=50.0)
    assert len(denser) > 0
    with pytest.raises(InvalidPointCloudError):
        mapsqueeze.decompress(compressed, model=model, density=5.0, n_points=10)
    with pytest.raises(DecodeLimitError, match="per tile"):
        mapsqueeze.decompress(compressed, model=model, n_points=10**12)


def test_bbox_decodes_only_intersecting_tiles(compressed, model, monkeypatch):
    decoded_tiles = []
    original = decompress_module.decode_payload

    def spy(header, entry, *args):
        decoded_tiles.append(entry.index)
        return original(header, entry, *args)

    monkeypatch.setattr(decompress_module, "decode_payload", spy)
    box = np.concatenate([UTM + [1.0, 1.0, 0.0], UTM + [6.0, 6.0, 3.0]])  # inside the first tile column
    points = mapsqueeze.decompress(compressed, model=model, bbox=box, workers=1)  # the spy sees this process only
    reader, stream = open_container(compressed)
    stream.close()
    boxes = [decompress_module.tile_world_bounds(reader.header, entry) for entry in reader.entries]
    expected = [entry.index for entry, tile_box in zip(reader.entries, boxes)
                if decompress_module._intersects(tile_box, box.reshape(2, 3))]
    assert decoded_tiles == expected and 0 < len(expected) < len(reader.entries)
    assert len(points) > 0 and (points >= box[:3]).all() and (points <= box[3:]).all()


def test_identical_bytes_on_repeated_runs(map_points, compressed, model_dir):
    assert mapsqueeze.compress(map_points, model=load_model(model_dir), precision="q") == compressed


def test_refined_encoding_keeps_the_format_and_is_deterministic(map_points, network_only, model, tmp_path):
    options = {"refine_steps": 3, "fallback": False, "post_filter": "off"}  # network_only's, plus refinement
    refined = mapsqueeze.compress(map_points, model=model, precision="q", **options)
    assert refined != network_only
    assert mapsqueeze.compress(map_points, model=model, **options) == refined
    plain_info, refined_info = mapsqueeze.info(network_only), mapsqueeze.info(refined)
    assert (refined_info.n_tiles, refined_info.tile_modes) == (plain_info.n_tiles, plain_info.tile_modes)
    decoded = mapsqueeze.decompress(refined, model=model, n_points=len(map_points))
    assert len(decoded) == len(map_points)
    write_points(tmp_path / "map.npy", map_points)
    mapsqueeze.compress_file(tmp_path / "map.npy", tmp_path / "map.msq", model=model, **options)
    assert (tmp_path / "map.msq").read_bytes() == refined
    for bad in (-1, 1.5, True, 10**6):
        with pytest.raises(MapsqueezeError, match="refinement steps"):
            mapsqueeze.compress(map_points, model=model, refine_steps=bad)


@pytest.mark.parametrize("suffix", [".ply", ".laz", ".npy"])
def test_compress_file_streams_chunks_and_gives_the_in_memory_bytes(map_points, compressed, model, tmp_path, suffix):
    from mapsqueeze.codec.compress import compress_chunks
    from mapsqueeze.io import iter_points

    source = tmp_path / f"map{suffix}"
    write_points(source, map_points)
    expected = compressed if suffix != ".laz" else mapsqueeze.compress(read_points(source), model=model)
    spill = tmp_path / "spill"
    spill.mkdir()
    # chunks much smaller than a tile: every tile is assembled from several chunks' spill appends
    streamed = compress_chunks(lambda: iter_points(source, chunk_points=997), model, Precision.q, spill_dir=spill)
    assert streamed == expected
    assert list(spill.iterdir()) == []  # spill files removed
    cloud = read_point_cloud(source)  # LAS carries its standard fields and header: compress_file codes them too
    full = mapsqueeze.compress(cloud.points, model=model, attributes=cloud.attributes, metadata=cloud.metadata)
    assert (full == expected) == (suffix != ".laz")
    mapsqueeze.compress_file(source, tmp_path / "map.msq", model=model)
    assert (tmp_path / "map.msq").read_bytes() == full


@pytest.mark.parametrize("suffix", [".ply", ".las", ".npy", ".pcd"])
def test_decompress_file_streams_tiles_to_the_output(compressed, model, tmp_path, suffix):
    from mapsqueeze.io import LAS_SCALE_M

    (tmp_path / "map.msq").write_bytes(compressed)
    spill = tmp_path / "spill"
    spill.mkdir()
    n = mapsqueeze.decompress_file(tmp_path / "map.msq", tmp_path / f"out{suffix}", model=model, spill_dir=spill)
    expected = mapsqueeze.decompress(compressed, model=model)
    written = read_points(tmp_path / f"out{suffix}")
    assert n == len(expected) == len(written) and list(spill.iterdir()) == []
    np.testing.assert_allclose(written, expected, rtol=0, atol=LAS_SCALE_M if suffix == ".las" else 0)


def test_compress_file_reports_a_bad_chunk(model, tmp_path):
    points = make_map()
    points[7000] = np.nan
    source = tmp_path / "bad.npy"
    np.save(source, points)
    with pytest.raises(InvalidPointCloudError) as excinfo:
        mapsqueeze.compress_file(source, tmp_path / "bad.msq", model=model)
    assert str(excinfo.value) == (f"{source}: 1 of {len(points):,} points has NaN or infinite coordinates (the "
                                  "first: point 7,000, counting from 0)")
    assert not (tmp_path / "bad.msq").exists()
    with pytest.raises(InvalidPointCloudError) as excinfo:  # the points of the map given in chunks
        compress_chunks(lambda: [points[:5000], points[5000:]], model)
    assert str(excinfo.value) == ("map: 1 of points 5,000 to 8,003 has NaN or infinite coordinates (the first: point "
                                  "7,000, counting from 0; any later points are not checked)")


def test_utm_coordinates_keep_codec_precision(model):
    rng = np.random.default_rng(4)
    sparse = UTM + rng.uniform(0, 1, (40, 3)) * [30.0, 20.0, 7.0]  # a few points per tile: all coded raw
    data = mapsqueeze.compress(sparse, model=model)
    assert mapsqueeze.info(data).n_raw_tiles == mapsqueeze.info(data).n_tiles
    decoded = mapsqueeze.decompress(data)  # raw tiles need no model
    distance, _ = cKDTree(decoded).query(sparse)
    assert len(decoded) == len(sparse) and distance.max() <= np.sqrt(3) * RAW_STEP_M / 2 + 1e-6


def test_empty_map_is_refused_and_one_point_map_gives_a_tiny_file(model):
    with pytest.raises(InvalidPointCloudError, match="empty"):
        mapsqueeze.compress(np.zeros((0, 3)), model=model)
    data = mapsqueeze.compress(UTM[None, :], model=model)
    assert len(data) < 300
    np.testing.assert_allclose(mapsqueeze.decompress(data), UTM[None, :], atol=RAW_STEP_M)


def test_wrong_model_is_refused(network_only, tmp_path):
    other = save_model(build_model(ModelConfig.for_rate("e1", tile_size=tuple(TILE), map_size=8.0), seed=2),
                       tmp_path / "other")
    with pytest.raises(ModelError, match="compressed with model"):
        mapsqueeze.decompress(network_only, model=other)


# --- per-tile modes, rate control, default count, version 1 files ----------------------------------------------

def test_mode_rules_pick_the_cheapest_within_budget():
    from mapsqueeze.codec.modes import Candidate, choose, choose_for_error, choose_for_rate

    def candidate(n_bytes, d_e):
        return Candidate(TileCoding.octree, b"", n_bytes, d_e, f"{n_bytes}")

    network = Candidate(TileCoding.network, b"", 100, 0.20, "network")
    tile = [network, candidate(90, 0.15), candidate(150, 0.05), candidate(40, 0.40)]
    assert choose(tile, 100).label == "90"  # lowest D_e at no more bytes than the network's
    assert choose_for_error(tile, 0.16).label == "90" and choose_for_error(tile, 0.01).label == "150"
    dense = [Candidate(TileCoding.network, b"", 100, 0.05, "network"), candidate(400, 0.04), candidate(30, 0.5)]
    choice = choose_for_rate([tile, dense], [1000, 5000], budget_bytes=150)
    assert sum(c.n_bytes for c in choice) <= 150 and choice[1].label == "network"
    assert [c.label for c in choose_for_rate([tile, dense], [1000, 5000], 10)] == ["40", "30"]  # nothing fits


def test_rate_targets_are_met(map_points, model):
    loose = mapsqueeze.compress(map_points, model=model, max_error=10.0)
    tight = mapsqueeze.compress(map_points, model=model, max_error=0.01)
    assert len(loose) < len(tight)
    assert set(mapsqueeze.info(tight).tile_modes) == {"raw"}  # only raw coding (1 cm steps) reaches 1 cm
    decoded = mapsqueeze.decompress(tight, model=model)
    assert cKDTree(decoded).query(map_points)[0].max() <= np.sqrt(3) * RAW_STEP_M / 2 + 1e-6
    smallest = 8 * len(mapsqueeze.compress(map_points, model=model, bpp=1e-6)) / len(map_points)  # nothing fits
    sizes = []
    for bpp in (1.5 * smallest, 3 * smallest):
        sizes.append(len(mapsqueeze.compress(map_points, model=model, bpp=bpp)))
        assert smallest < 8 * sizes[-1] / len(map_points) <= bpp
    assert sizes[0] < sizes[1]
    with pytest.raises(MapsqueezeError, match="not both"):
        mapsqueeze.compress(map_points, model=model, max_error=0.1, bpp=1.0)


def test_a_bpp_budget_nothing_meets_gets_the_smallest_file_of_the_shipped_models(map_points):
    """With no model and a budget no coding meets, the file kept among e0..e3 is the smallest of theirs (the
    lowest-D_e one, kept before, is 4.7x the smallest here without the octree)."""
    for fallback in (True, False):
        chosen = mapsqueeze.compress(map_points, bpp=1e-9, fallback=fallback)
        sizes = [len(mapsqueeze.compress(map_points, model=name, bpp=1e-9, fallback=fallback))
                 for name in RATE_TARGET_MODELS]
        assert len(chosen) == min(sizes), (fallback, len(chosen), sizes)


@pytest.mark.parametrize("target", [{"fallback": False}, {"max_error": 0.1}, {"bpp": 1.0}])
def test_compress_holds_per_tile_only_what_the_mode_decision_needs(map_points, model, monkeypatch, target):
    """Without a rate budget each tile's choice is made as its candidates come and only it is kept (the embedding
    and the patch choices, uint8, only for a network tile); a budget weighs every tile's candidates at the end, so
    it keeps them all."""
    from mapsqueeze.codec import compress as compress_module

    held, assemble = [], compress_module._assemble

    def spy(encoded, *args):
        held.append([(list(tile.candidates), tile.choice, tile.points, tile.patch_choices) for tile in encoded])
        return assemble(encoded, *args)

    monkeypatch.setattr(compress_module, "_assemble", spy)
    mapsqueeze.compress(map_points, model=model, **target)
    tiles = held[0]
    if "bpp" in target:
        assert min(len(candidates) for candidates, *_ in tiles if len(candidates) > 1) == 7
        return
    assert all(candidates == [choice] for candidates, choice, *_ in tiles)
    network = [choice.coding is TileCoding.network for _, choice, *_ in tiles]
    assert any(network) != ("max_error" in target) and not all(network)  # no network tile under 10 cm here
    for is_network, (_, _, points, search) in zip(network, tiles):
        assert (points is not None) == is_network and (search is not None) == is_network
        assert search is None or search.choices.dtype == np.uint8


def test_default_decode_is_each_tiles_native_count(network_only, model):
    reader, stream = open_container(network_only)
    with stream:
        assert reader.version == 7 and reader.header.default_count.name == "native"
        occupied, tile_size = {entry.index for entry in reader.entries}, np.asarray(reader.header.tile_size)
        native = sum(len(decompress_module.decode_payload(reader.header, entry, reader.payload(position), model, None,
                                                          entry.label(position), faces=internal_faces(
                                                              entry, occupied, tile_size)))
                     for position, entry in enumerate(reader.entries))
    decoded = mapsqueeze.decompress(network_only, model=model)
    assert len(decoded) == native > reader.header.n_points
    assert mapsqueeze.info(network_only).default_count == "native"
    with pytest.raises(DecodeLimitError, match="native count"):  # the limit holds for native counts too
        mapsqueeze.decompress(network_only, model=model, max_tile_points=max(e.n_points for e in reader.entries))
    with pytest.raises(DecodeLimitError, match="native count"):  # and for the native output a count is drawn from
        mapsqueeze.decompress(network_only, model=model, n_points=len(reader.entries),
                              max_tile_points=max(e.n_points for e in reader.entries))


def as_version_1(data: bytes) -> bytes:
    """The same geometry-only file (no post-filter) in the version 1 layout (docs/format.md): fixed-width header
    fields, no default-count byte (the input count by default), no post-filter byte, payload offsets in the table."""
    reader, stream = open_container(data)
    with stream:
        header, payloads = reader.header, [reader.payload(p) for p in range(len(reader.entries))]
    name = header.model_id.encode()
    body = ByteWriter()
    body.raw(struct.pack("<B", len(name)) + name + bytes.fromhex(header.weights_sha256))
    body.pack("Bd3d3dQIBd", header.precision, header.subsampling_dist_m, *header.tile_size, *header.origin,
              header.n_points, header.n_tiles, header.n_features, header.raw_step_m)
    header.latent.write(body, compact=False)
    table, offset = ByteWriter(), 0
    for entry, payload in zip(reader.entries, payloads):
        assert entry.post_filter == 0
        for value in entry.index:
            table.svarint(value)
        table.varint(entry.n_points)
        table.pack("6HB", *entry.bounds_lo, *entry.bounds_hi, entry.coding)
        table.varint(offset)
        table.varint(len(payload))
        table.pack("I", zlib.crc32(payload))
        offset += len(payload)
    head = struct.pack("<4sHHI", b"MSQZ", 1, 0, len(body.getvalue())) + body.getvalue()
    entries = table.getvalue()
    return b"".join([head, struct.pack("<I", zlib.crc32(head)), struct.pack("<I", len(entries)), entries,
                     struct.pack("<I", zlib.crc32(entries)), *payloads])


def test_version_1_files_decode_to_the_input_count(network_only, map_points, model):
    old = as_version_1(network_only)
    reader, stream = open_container(old)
    stream.close()
    assert reader.version == 1 and reader.header.default_count.name == "input"
    decoded = mapsqueeze.decompress(old, model=model)
    assert len(decoded) == len(map_points)
    np.testing.assert_array_equal(decoded, mapsqueeze.decompress(network_only, model=model,
                                                                  n_points=len(map_points)))


# --- corruption ----------------------------------------------------------------------------------------------

def test_every_truncation_is_detected(compressed):
    for length in range(len(compressed)):
        with pytest.raises(ContainerError):
            read_all_payloads(compressed[:length])


def test_every_single_byte_corruption_is_detected(compressed):
    for position in range(len(compressed)):
        corrupt = bytearray(compressed)
        corrupt[position] ^= 0x5A
        with pytest.raises(ContainerError):
            read_all_payloads(bytes(corrupt))


def test_corrupt_tile_is_named_by_decompress(compressed, model):
    reader, stream = open_container(compressed)
    stream.close()
    last = reader.entries[-1]
    corrupt = bytearray(compressed)
    corrupt[last.offset + last.length // 2] ^= 0xFF
    index = ",".join(str(v) for v in last.index)
    with pytest.raises(ContainerError, match=rf"tile {len(reader.entries) - 1} \(index {index}\): payload CRC"):
        mapsqueeze.decompress(bytes(corrupt), model=model)
    with pytest.raises(ContainerError, match="not a .msq"):
        mapsqueeze.decompress(b"PK\x03\x04" + bytes(compressed[4:]), model=model)


def test_payload_checks_catch_forged_crcs(network_only, compressed):
    """A payload rewritten with a matching CRC but garbage content still gives ContainerError, not garbage."""
    reader, stream = open_container(network_only)
    stream.close()
    position = next(p for p, e in enumerate(reader.entries) if e.coding is TileCoding.network)
    entry = reader.entries[position]
    with pytest.raises(ContainerError, match=f"tile {position}"):
        reader.header.latent.decode(b"\x07" + b"\xff" * (entry.length - 1), entry.n_points, f"tile {position}")
    assert zlib.crc32(network_only[entry.offset:entry.offset + entry.length]) == entry.crc32
    reader, stream = open_container(compressed)
    with stream:
        position = next(p for p, e in enumerate(reader.entries) if e.coding is TileCoding.octree)
        entry, tile_size = reader.entries[position], np.asarray(reader.header.tile_size)
        payload = bytearray(reader.payload(position))
    for forged in (payload[:5] + b"\xff" * (len(payload) - 5),  # garbage levels
                   struct.pack("<fB", 1e-9, 20) + payload[5:],  # absurd leaf
                   payload[:5] + b"\x80" * 12):  # malformed leaf count
        with pytest.raises(ContainerError, match=f"tile {position}"):
            decode_octree_tile(bytes(forged), tile_size, entry.n_points, f"tile {position}")


# --- command line ----------------------------------------------------------------------------------------------

def run_cli(monkeypatch, capsys, *args):
    from mapsqueeze.cli import main

    monkeypatch.setattr(sys, "argv", ["mapsqueeze", *map(str, args)])
    with pytest.raises(SystemExit) as exit_info:
        main()
    return exit_info.value.code, capsys.readouterr()


def test_cli_round_trip_and_errors(tmp_path, map_points, model_dir, monkeypatch, capsys):
    source, msq, out = tmp_path / "map.ply", tmp_path / "map.msq", tmp_path / "out.npy"
    write_points(source, map_points)
    code, _ = run_cli(monkeypatch, capsys, "compress", source, "-o", msq, "--model", model_dir, "--refine", "2")
    assert code in (0, None) and msq.read_bytes() == mapsqueeze.compress(map_points, model=model_dir, refine_steps=2)
    code, _ = run_cli(monkeypatch, capsys, "compress", source, "-o", msq, "--model", model_dir)
    assert code in (0, None) and msq.is_file()
    code, captured = run_cli(monkeypatch, capsys, "info", msq)
    assert code in (0, None) and "bits per point" in captured.out and "octree" in captured.out
    box = ",".join(str(v) for v in np.concatenate([UTM, UTM + [7.0, 7.0, 3.0]]))
    code, _ = run_cli(monkeypatch, capsys, "decompress", msq, "-o", out, "--model", model_dir, f"--bbox={box}")
    assert code in (0, None) and len(read_points(out)) > 0
    truncated = tmp_path / "truncated.msq"
    truncated.write_bytes(msq.read_bytes()[:-10])
    for args in (["decompress", truncated, "-o", out, "--model", model_dir],
                 ["decompress", msq, "-o", out, "--bbox", "1,2,3"],
                 ["compress", source, "-o", msq, "--precision", "f8", "--model", model_dir],
                 ["compress", source, "-o", msq, "--refine", "-1", "--model", model_dir],
                 ["compress", source, "-o", msq, "--max-error", "0.1", "--bpp", "1", "--model", model_dir],
                 ["compress", source, "-o", msq, "--bpp", "-1", "--model", model_dir],
                 ["compress", source, "-o", msq, "--max-error", "nan", "--model", model_dir],
                 ["compress", tmp_path / "missing.ply", "-o", msq],
                 ["info", source]):
        code, captured = run_cli(monkeypatch, capsys, *args)
        lines = captured.err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), (args, captured.err)


def test_streaming_refuses_an_overfull_tile_before_reading_it_back(model, tmp_path, monkeypatch):
    from mapsqueeze.codec import compress as compress_module
    from mapsqueeze.codec import tilejobs

    monkeypatch.setattr(tilejobs, "MAX_POINTS_PER_TILE", 1000)
    source = tmp_path / "map.npy"
    np.save(source, make_map())
    monkeypatch.setattr(compress_module, "embed_job", lambda *a: pytest.fail("tile read back and encoded"))
    with pytest.raises(InvalidPointCloudError, match="more than the 1,000"):
        mapsqueeze.compress_file(source, tmp_path / "map.msq", model=model)


def _region_chunks(points: np.ndarray, parts: int) -> list[np.ndarray]:
    """The map sorted by x and cut into `parts` chunks: a file that holds its map region by region."""
    return np.array_split(points[np.argsort(points[:, 0], kind="stable")], parts)


def test_streaming_encodes_tiles_as_the_map_is_read(map_points, model, monkeypatch):
    from mapsqueeze.codec import compress as compress_module
    from mapsqueeze.codec.compress import compress_chunks

    chunks = _region_chunks(map_points, 6)
    expected = mapsqueeze.compress(np.concatenate(chunks), model=model, precision="q")
    events = []
    embed_job = compress_module.embed_job

    def pass_chunks():
        for number, chunk in enumerate(chunks):
            events.append(("chunk", number))
            yield chunk

    def recorded(job, item):
        events.append(("tile", item[0]))
        return embed_job(job, item)

    monkeypatch.setattr(compress_module, "embed_job", recorded)
    streamed = compress_chunks(pass_chunks, model, Precision.q, workers=1)
    assert streamed == expected
    second_pass = events[events.index(("chunk", 0), 1):]
    tiles = [position for position, event in enumerate(second_pass) if event[0] == "tile"]
    assert len(tiles) == mapsqueeze.info(streamed).n_tiles
    assert tiles[0] < second_pass.index(("chunk", len(chunks) - 1))  # a tile encoded before the last chunk is read


def test_streaming_refuses_points_of_a_tile_already_encoded(map_points, model):
    from mapsqueeze.codec.compress import compress_chunks

    chunks = _region_chunks(map_points, 2)
    changed = chunks[1].copy()
    changed[0] = chunks[0][0]  # the same count, one point moved into a tile the first chunk completed
    passes = iter([chunks, [chunks[0], changed]])
    with pytest.raises(InvalidPointCloudError, match="input changed between the two reading passes"):
        compress_chunks(lambda: iter(next(passes)), model, Precision.q, workers=1)


def test_decompress_file_refuses_an_unknown_output_format_before_decoding(compressed, tmp_path, monkeypatch):
    from mapsqueeze.errors import PointCloudFormatError

    (tmp_path / "map.msq").write_bytes(compressed)
    monkeypatch.setattr(decompress_module, "decode_payload", lambda *a: pytest.fail("decoded before the check"))
    with pytest.raises(PointCloudFormatError, match="unknown point-cloud extension"):
        mapsqueeze.decompress_file(tmp_path / "map.msq", tmp_path / "out.xyz")
    assert not (tmp_path / "out.xyz").exists()


def test_raw_tile_payload_bytes_are_pinned():
    """The raw payload format must not drift: a pinned digest, to be changed only with the format."""
    import hashlib

    points = (np.random.default_rng(5).random((3000, 3)) * [40, 40, 15]).astype(np.float32)
    payload = encode_raw_tile(points, np.array([40.0, 40.0, 15.0]))
    assert hashlib.sha256(payload).hexdigest() == "13a0c695d538bab2986c8cdcf74f4b206e1569b71857788b8f9fa52df52c5760"


def test_version_option_prints_the_package_version(run_cli):
    import mapsqueeze

    code, out, err = run_cli("--version")
    assert (code, out, err) == (0, f"mapsqueeze {mapsqueeze.__version__}\n", "")


def test_bbox_decode_of_a_real_map_holds_at_least_the_original_count_in_the_box(kitti_submap):
    """By default every tile decodes to the network's whole output inside the tile, so a box gets at least as many
    points as the original had there (decoding to the input's count left boxes of the KITTI submap 10-25 % short)."""
    points = read_points(kitti_submap)
    data = mapsqueeze.compress(points, model="e1", workers=1)
    lower, upper = points.min(axis=0), points.max(axis=0)
    centre, half = (lower + upper) / 2, (upper - lower) / 4
    for shift in (np.zeros(3), np.array([half[0], 0.0, 0.0]), np.array([0.0, -half[1], 0.0])):
        box = np.concatenate([centre + shift - half, centre + shift + half])
        box[2], box[5] = lower[2] - 1, upper[2] + 1
        original = int(((points >= box[:3]) & (points <= box[3:])).all(axis=1).sum())
        decoded = mapsqueeze.decompress(data, bbox=tuple(box), workers=1)
        assert ((decoded >= box[:3]) & (decoded <= box[3:])).all()
        assert len(decoded) >= original > 1000


@pytest.mark.parametrize("leaf", [0.1, 0.4, 1.6])
def test_own_leaf_distances_are_the_nearest_leaf_distances_wherever_known(leaf):
    """Points on a wall, a floor and scattered ones, also on leaf faces and near the box's upper faces: every known
    own-leaf distance is exactly the k-d tree's nearest-centre distance, and most points are known."""
    from mapsqueeze.codec.octreetile import encode_octree_tile, own_leaf_distances
    from mapsqueeze.codec.tilepoints import octree_points

    rng = np.random.default_rng(3)
    tile_size, extent = np.array([8.0, 8.0, 4.0]), np.array([7.5, 8.0, 3.3])
    points = np.concatenate([rng.uniform(0, 1, (4000, 3)) * extent,
                             np.column_stack([rng.uniform(0, 7.5, 2000), np.full(2000, 4.0), rng.uniform(0, 3.3, 2000)]),
                             np.round(rng.uniform(0, 1, (500, 3)) * extent / leaf) * leaf]).astype(np.float32)
    centres = octree_points(decode_octree_tile(encode_octree_tile(points, tile_size, leaf), tile_size, len(points),
                                               "test"), extent, None)
    nearest = cKDTree(centres.astype(np.float64)).query(points.astype(np.float64))[0]
    own = own_leaf_distances(points, tile_size, leaf, extent)
    known = ~np.isnan(own)
    assert np.array_equal(own[known], nearest[known])
    assert known.mean() > 0.3
    assert not known[-500:].all()  # points on leaf faces are left to the search


def test_candidate_distortion_estimates_on_samples_and_is_exact_where_candidates_are_close():
    """D_e estimates from SAMPLE_POINTS points a side are within 2 % of the exact D_e; candidates whose estimates
    are close get exact values, the others (and those only close to candidates that do not compete) keep their
    estimates; those that do not compete get NaN without being decoded; exact=True gives d_euclidean throughout."""
    from mapsqueeze.codec.distortion import SAMPLE_POINTS, CandidateDistortion, sample_indices
    from mapsqueeze.metrics import d_euclidean

    rng = np.random.default_rng(5)
    tile = np.column_stack([rng.uniform(0, 30, 60_000), rng.uniform(0, 30, 60_000), rng.normal(0, 0.3, 60_000)])
    noisy = [(tile[::2] + rng.normal(0, sigma, (30_000, 3))).astype(np.float32) for sigma in (0.05, 0.0505, 0.2)]
    exact = [d_euclidean(tile, decoded) for decoded in noisy]
    estimates = []
    for decoded in noisy:
        alone = CandidateDistortion(tile)
        alone.add(decoded)
        estimates.append(alone.settle()[0])
    assert all(abs(e / x - 1) < 0.02 and e != x for e, x in zip(estimates, exact))
    together = CandidateDistortion(tile)
    for decoded in noisy:
        together.add(decoded)
    assert together.settle() == [exact[0], exact[1], estimates[2]]  # the first two are within CLOSE
    rivals = CandidateDistortion(tile)
    for decoded, competing in zip(noisy, (True, False, True)):
        rivals.add(lambda decoded=decoded: decoded, competing=competing)
    rivals.add(lambda: pytest.fail("a candidate that does not compete is decoded"), competing=False)
    values = rivals.settle()  # the second does not compete: NaN, and no close pair is left
    assert values[0] == estimates[0] and values[2] == estimates[2] and np.isnan(values[1]) and np.isnan(values[3])
    exactly = CandidateDistortion(tile, exact=True)
    for decoded in noisy:
        exactly.add(decoded)
    assert exactly.settle() == exact
    picked = sample_indices(100_000)
    assert len(picked) == SAMPLE_POINTS and np.all(np.diff(picked) > 0) and picked[-1] < 100_000
    assert np.array_equal(picked, sample_indices(100_000)) and np.array_equal(sample_indices(500), np.arange(500))


@pytest.mark.parametrize("tile_size", [TILE, np.array([40.0, 40.0, 15.0]), np.array([1.0, 0.9, 0.5])])
def test_octree_payloads_of_all_leaves_at_once_are_each_leafs_own(tile_size):
    """encode_octree_tiles (one sort for every leaf) gives encode_octree_tile's payload at each leaf, built directly,
    and the leaf centres its payload decodes to."""
    from mapsqueeze.codec.octreetile import OCTREE_LEAVES_M, encode_octree_tiles, octree_depth
    from mapsqueeze.geometry.morton import morton_codes
    from mapsqueeze.baselines.octree import arithmetic_encode, occupancy_levels

    rng = np.random.default_rng(8)
    points = np.concatenate([rng.uniform(0, 1, (5000, 3)) * tile_size,
                             np.round(rng.uniform(0, 1, (500, 3)) * tile_size / 0.4) * 0.4])  # on leaf faces
    points = np.clip(points, 0, tile_size)
    coded = encode_octree_tiles(points, tile_size, OCTREE_LEAVES_M)
    assert [leaf for leaf, _, _ in coded] == [float(np.float32(leaf)) for leaf in OCTREE_LEAVES_M]
    for leaf, payload, centres in coded:
        edge = float(np.float32(leaf))
        depth = octree_depth(tile_size, edge)
        codes = np.unique(morton_codes(np.clip(np.floor(points / edge), 0, (1 << depth) - 1).astype(np.int64), depth))
        writer = ByteWriter()
        writer.pack("fB", edge, depth)
        writer.varint(len(codes))
        writer.raw(arithmetic_encode(occupancy_levels(codes, depth)))
        assert payload == writer.getvalue()
        assert np.array_equal(centres, decode_octree_tile(payload, tile_size, len(points), "test"))


@pytest.mark.parametrize("tile_size", [TILE, np.array([40.0, 40.0, 15.0]), np.array([1.0, 0.9, 0.5])])
def test_octree_payloads_under_a_byte_bound_stop_after_the_first_too_large(tile_size, real_data):
    """encode_octree_tiles with max_bytes: the payloads of encode_octree_tiles without it, coarsest first up to and
    including the first larger than max_bytes + OCTREE_GROWTH_SLACK_BYTES, none finer; payloads grow with the
    fineness (what the stop relies on) on random and on real points."""
    from mapsqueeze.codec.octreetile import OCTREE_GROWTH_SLACK_BYTES, OCTREE_LEAVES_M, encode_octree_tiles

    rng = np.random.default_rng(9)
    clouds = [np.clip(rng.uniform(0, 1, (n, 3)) * tile_size, 0, tile_size) for n in (1, 40, 3000)]
    if tile_size[0] == 40.0:
        real = read_points(real_data / "submaps" / "kitti_hdl64_6scans.ply")
        clouds.append(np.clip(real - real.min(axis=0), 0, tile_size))
    for points in clouds:
        full = encode_octree_tiles(points, tile_size, OCTREE_LEAVES_M)
        sizes = [len(payload) for _, payload, _ in full]  # finest first
        assert all(finer >= coarser - OCTREE_GROWTH_SLACK_BYTES for finer, coarser in zip(sizes, sizes[1:]))
        for bound in sorted({0, *sizes, max(sizes) + 100}):
            kept = encode_octree_tiles(points, tile_size, OCTREE_LEAVES_M, bound)
            first_over = next((i for i in range(len(full) - 1, -1, -1)
                               if sizes[i] > bound + OCTREE_GROWTH_SLACK_BYTES), -1)
            expected = full[first_over:] if first_over >= 0 else full
            assert [(leaf, payload) for leaf, payload, _ in kept] == [(leaf, payload) for leaf, payload, _ in expected]
            assert all(np.array_equal(a[2], b[2]) for a, b in zip(kept, expected))


def test_keep_inside_keeps_the_points_in_the_closed_box_and_clamps_when_none_is():
    from mapsqueeze.codec.tilepoints import keep_inside

    extent = np.array([40.0, 40.0, 15.0])
    upper = extent.astype(np.float32)
    rng = np.random.default_rng(4)
    cloud = (rng.uniform(-1, 1, (20_000, 3)) * 0.05 + rng.choice([0.0, 1.0], (20_000, 3)) * upper).astype(np.float32)
    cloud[:3] = [[0, 0, 0], upper, [np.nan, 1, 1]]  # both corners are inside, NaN is not
    cloud[3] = [np.nextafter(np.float32(0), np.float32(-1)), 1, 1]
    cloud[4] = [1, 1, np.nextafter(upper[2], np.float32(99))]
    inside = np.array([all(0 <= v <= u for v, u in zip(point, upper)) for point in cloud.tolist()])
    assert inside[:2].all() and not inside[2:5].any() and 0 < inside.mean() < 1
    assert np.array_equal(keep_inside(cloud, extent), cloud[inside])
    outside = cloud[~inside & ~np.isnan(cloud).any(axis=1)]
    assert np.array_equal(keep_inside(outside, extent), np.clip(outside, np.float32(0), upper))
