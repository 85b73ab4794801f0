"""Attribute fields on the decoded geometry (codec.attributes, codec.attrfield): no voxel positions coded, exact
values on the support, nearest-voxel values elsewhere, context-coded labels, crafted streams, version 2 files."""

import hashlib
import struct
from pathlib import Path

import numpy as np
import pytest

import mapsqueeze
from mapsqueeze.codec.attrfield import LevelsOfDetail, decode_categories, decode_integers, support_voxels
from mapsqueeze.codec.attributes import (
    CATEGORICAL,
    CONTINUOUS,
    AttributeSchema,
    AttributeSpec,
    decode_tile_attributes,
    encode_tile_attributes,
)
from mapsqueeze.codec.container import open_container
from mapsqueeze.codec.entropy import ByteReader, ByteWriter, SymbolReader, SymbolWriter
from mapsqueeze.errors import ContainerError

TILE = np.array([40.0, 40.0, 16.0])
DATA = Path(__file__).parent / "data"


def surface(n: int = 20000, seed: int = 0) -> np.ndarray:
    """A gently curved ground with a wall, metres in a 40 x 40 x 16 m tile frame."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0, 39, n), rng.uniform(0, 39, n), np.zeros(n)])
    ground[:, 2] = 1 + 0.02 * ground[:, 0]
    wall = np.column_stack([rng.uniform(0, 39, n // 4), np.full(n // 4, 30.0), rng.uniform(1, 8, n // 4)])
    return np.concatenate([ground, wall])


def schema(*specs: AttributeSpec, voxel_m: float = 0.5) -> AttributeSchema:
    return AttributeSchema(voxel_m, specs, {})


INTENSITY = AttributeSpec("intensity", np.dtype(np.float32), CONTINUOUS, 0.0, 1.0)
LABEL = AttributeSpec("label", np.dtype(np.uint8), CATEGORICAL)


def test_levels_code_integers_and_categories_exactly():
    points = surface(5000)
    codes, _ = support_voxels(points, TILE, 0.5)
    lod = LevelsOfDetail(codes)
    assert sorted(lod.order.tolist()) == list(range(len(codes))) and (np.diff(lod.levels) <= 0).all()
    assert (lod.levels == 0).mean() > 0.5  # most voxels share their 2x2x2 cell with an earlier one
    rng = np.random.default_rng(1)
    integers = rng.integers(-50, 400, len(codes))
    categories = rng.integers(0, 5, len(codes))
    from mapsqueeze.codec.attrfield import encode_categories, encode_integers, read_category_tables, \
        read_integer_tables
    writer, symbols = ByteWriter(), SymbolWriter()
    encode_integers(writer, symbols, lod, integers)
    encode_categories(writer, symbols, lod, categories, 5)
    reader = ByteReader(writer.getvalue(), "tables")
    integer_tables, category_tables = read_integer_tables(reader), read_category_tables(reader)
    stream = SymbolReader(symbols.getvalue(), "symbols")
    np.testing.assert_array_equal(decode_integers(stream, lod, integer_tables), integers)
    np.testing.assert_array_equal(decode_categories(stream, lod, category_tables, 5), categories)
    stream.finish()


def test_no_voxel_positions_are_coded():
    """A constant field over thousands of support voxels costs a few bytes: positions come from the geometry."""
    support = surface()
    n_voxels = len(support_voxels(support, TILE, 0.25)[0])
    assert n_voxels > 5000
    values = {"intensity": np.full(len(support), 7.0), "label": np.full(len(support), 3)}
    stream = encode_tile_attributes(support, support, values, schema(INTENSITY, LABEL, voxel_m=0.25), TILE)
    assert len(stream) < 40, len(stream)


def test_values_on_the_support_and_nearest_voxel_values_elsewhere():
    """The support voxels decode to the median of the input values nearest to their decoded points; other points
    take the value of their nearest support voxel."""
    original = surface(8000)
    rng = np.random.default_rng(2)
    support = original[rng.choice(len(original), 4000, replace=False)] + rng.normal(0, 0.03, (4000, 3))
    support = np.clip(support, 0, TILE - 1e-3).astype(np.float32)
    brightness = np.where(original[:, 0] > 20, 180.0, 40.0) + np.where(original[:, 1] > 29.5, 30.0, 0.0)
    labels = np.where(original[:, 1] > 29.5, 6, np.where(original[:, 0] > 20, 2, 1)).astype(np.uint8)
    coded = schema(INTENSITY, LABEL, voxel_m=0.5)
    stream = encode_tile_attributes(support, original, {"intensity": brightness, "label": labels}, coded, TILE)
    on_support = decode_tile_attributes(stream, support, None, coded, TILE, "tile")
    from pykdtree.kdtree import KDTree
    nearest = KDTree(original).query(support.astype(np.float64), k=1)[1].astype(np.int64)
    assert np.abs(on_support["intensity"] - brightness[nearest]).mean() < 0.1 * np.abs(brightness - 110).mean()
    assert (on_support["label"] == labels[nearest]).mean() > 0.97
    elsewhere = original[::7]
    decoded = decode_tile_attributes(stream, support, elsewhere, coded, TILE, "tile")
    from_support = KDTree(support.astype(np.float64)).query(elsewhere, k=1)[1].astype(np.int64)
    assert (decoded["label"] == on_support["label"][from_support]).mean() > 0.95
    assert (decoded["label"] == labels[::7]).mean() > 0.95


def test_labels_cost_little_where_they_are_coherent():
    """Context coding: a labelled surface (3 classes in large regions) costs well under a bit per voxel."""
    support = surface()
    labels = np.where(support[:, 1] > 29.5, 50, np.where(support[:, 0] > 20, 40, 10)).astype(np.uint8)
    coded = schema(LABEL, voxel_m=0.25)
    stream = encode_tile_attributes(support, support, {"label": labels}, coded, TILE)
    n_voxels = len(support_voxels(support, TILE, 0.25)[0])
    assert 8 * len(stream) < 0.1 * n_voxels, (len(stream), n_voxels)
    decoded = decode_tile_attributes(stream, support, None, coded, TILE, "tile")
    assert (decoded["label"] == labels).mean() > 0.98


def test_crafted_streams_give_a_clean_error():
    support = surface(4000)
    values = {"intensity": support[:, 0] * 3, "label": (support[:, 0] // 10).astype(np.uint8)}
    coded = schema(INTENSITY, LABEL)
    stream = encode_tile_attributes(support, support, values, coded, TILE)
    other = surface(4000, seed=5)[:3000]
    with pytest.raises(ContainerError, match="does not match the decoded tile"):
        decode_tile_attributes(stream, other, None, coded, TILE, "tile")  # a support that differs
    cases = [stream[:-4], stream + b"\0\0\0\0", stream[:5], stream[:-1]]
    rng = np.random.default_rng(3)
    for _ in range(40):
        corrupt = bytearray(stream)
        corrupt[rng.integers(0, len(stream))] ^= 1 << int(rng.integers(0, 8))
        cases.append(bytes(corrupt))
    for case in cases:
        try:
            decoded = decode_tile_attributes(case, support, None, coded, TILE, "tile")
        except ContainerError:
            continue
        assert set(decoded) == {"intensity", "label"} and len(decoded["label"]) == len(support)


def test_version_2_files_still_decode_as_they_did():
    """A version 2 file (attribute voxels coded in the stream) decodes to the attributes the version 2 decoder
    gave (digests taken with it, commit 52f2721)."""
    data = (DATA / "attributes_v2.msq").read_bytes()
    reader, stream = open_container(data)
    with stream:
        assert reader.version == 2
    cloud = mapsqueeze.decompress_cloud(data, workers=1)
    assert len(cloud.points) == 255471
    digests = {name: hashlib.sha256(values.tobytes()).hexdigest() for name, values in cloud.attributes.items()}
    assert digests == {"intensity": "c12e5a221fb4c61df678e22b5a1089c1f2f0911a51634fc8f5d3312b904548b2",
                       "classification": "84a4155f2abd0de42b09350903dbae57df59f352bed8e260c04b1b0eb80a26f9"}


def test_container_version_7_and_its_attributes_follow_the_decoded_geometry():
    """The written version is 7 (attribute streams on the decoded geometry since version 3); a decoded point's
    values are those of the nearest voxel of the default decode."""
    from test_attributes import street

    points, intensity, classification, _ = street(6000, 2000)
    data = mapsqueeze.compress(points, attributes={"intensity": intensity, "cls": classification})
    assert struct.unpack("<H", data[4:6])[0] == 7
    default = mapsqueeze.decompress_cloud(data)
    sparse = mapsqueeze.decompress_cloud(data, n_points=3000)
    from pykdtree.kdtree import KDTree
    nearest = KDTree(default.points).query(sparse.points, k=1)[1].astype(np.int64)
    assert (sparse.attributes["cls"] == default.attributes["cls"][nearest]).mean() > 0.97
    assert np.abs(sparse.attributes["intensity"].astype(float) -
                  default.attributes["intensity"][nearest].astype(float)).mean() < 3


def test_rate_control_counts_the_attribute_streams_of_the_chosen_codings():
    """Under --bpp each attempt's attribute streams follow its tile choices (cached per tile and coding)."""
    from test_attributes import street

    points, intensity, classification, _ = street(3000, 1000)
    attributes = {"intensity": intensity, "cls": classification}
    free = mapsqueeze.compress(points, attributes=attributes)
    budget = 8 * len(free) / len(points) * 0.6
    data = mapsqueeze.compress(points, attributes=attributes, bpp=budget)
    assert 8 * len(data) / len(points) <= budget < 8 * len(free) / len(points)
    cloud = mapsqueeze.decompress_cloud(data)
    assert len(cloud.attributes["cls"]) == len(cloud.attributes["intensity"]) == len(cloud.points) > 0


def test_the_attribute_support_is_decoded_on_the_cpu_whatever_the_model_device():
    """A model on another device gives the support of the CPU decoder (its last-bit rounding differs, which could
    move points across voxels) without building its own network."""
    from devicesim import simulated_device
    from test_attributes import street

    from mapsqueeze.codec.container import TileCoding
    from mapsqueeze.codec.decompress import attribute_support, decode_payload
    from mapsqueeze.model import load_model

    points, intensity, _, _ = street(6000, 2000)
    data = mapsqueeze.compress(points, attributes={"intensity": intensity}, fallback=False)
    reader, stream = open_container(data)
    with stream:
        position = next(i for i, e in enumerate(reader.entries) if e.coding is TileCoding.network)
        entry, payload = reader.entries[position], reader.payload(position)
        with simulated_device() as device:
            cpu, other = load_model("e1"), load_model("e1", device=device)  # not the CPU; never built here
        expected = decode_payload(reader.header, entry, payload, cpu, None, "tile", 1 << 23)
        support = attribute_support(reader.header, entry, payload, other, "tile")
    assert other._network is None
    assert support.shape == expected.shape and np.array_equal(support, expected)


def test_a_support_rounded_differently_is_repaired_and_a_different_one_refused():
    """A decoder whose rounding moves a voxel's only point across a face (count unchanged, codes not) gets the
    encoder's values back; a point moved beyond the tolerance gives a clean error, never shifted values."""
    rng = np.random.default_rng(5)
    support = surface(6000) + [0, 0.1, 0]  # below z = 8 m; the wall off the voxel faces
    lone = np.array([[20.0 - 2e-6, 10.25, 12.25]])  # alone in its voxel, just below its face x = 20
    support = np.concatenate([support, lone]).astype(np.float64)
    values = {"intensity": rng.uniform(0, 255, len(support)), "label": rng.integers(0, 4, len(support))}
    coded = schema(INTENSITY, LABEL, voxel_m=0.5)
    stream = encode_tile_attributes(support, support, values, coded, TILE)
    expected = decode_tile_attributes(stream, support, None, coded, TILE, "tile")
    rounded = support.copy()
    rounded[-1, 0] = 20.0 + 2e-6  # across the face: the voxel x in [19.5, 20) empties, [20, 20.5) fills
    assert len(support_voxels(rounded, TILE, 0.5)[0]) == len(support_voxels(support, TILE, 0.5)[0])
    repaired = decode_tile_attributes(stream, rounded, None, coded, TILE, "tile")
    for name in expected:
        assert np.array_equal(repaired[name], expected[name])
    repaired = decode_tile_attributes(stream, rounded, None, coded, TILE, "tile", crc_optional=True)
    for name in expected:  # a version 3 or 4 stream with the CRC is repaired alike
        assert np.array_equal(repaired[name], expected[name])
    rounded[-1, 0] = 20.01  # 1 cm across: not a rounding difference
    with pytest.raises(ContainerError, match="does not match"):
        decode_tile_attributes(stream, rounded, None, coded, TILE, "tile")
    with pytest.raises(ContainerError, match="does not match.*read without the CRC"):
        decode_tile_attributes(stream, rounded, None, coded, TILE, "tile", crc_optional=True)


def without_crc(stream: bytes) -> bytes:
    """The stream in the layout of versions 3 and 4 written before the support's CRC: the same bytes less the CRC
    after the voxel count."""
    reader = ByteReader(stream, "stream")
    reader.varint()
    count_end = len(stream) - reader.remaining
    return stream[:count_end] + stream[count_end + 4:]


def test_streams_without_the_support_crc_decode_where_the_version_allows_them():
    """Versions 3 and 4 (crc_optional) read both layouts to the same values; newer versions refuse the layout
    without the CRC, and a stream of it that does not parse exactly on the decoded support gives one clean error."""
    support = surface(6000)
    values = {"intensity": support[:, 0] * 3 + support[:, 1], "label": (support[:, 0] // 10).astype(np.uint8)}
    coded = schema(INTENSITY, LABEL)
    stream = encode_tile_attributes(support, support, values, coded, TILE)
    old = without_crc(stream)
    elsewhere = surface(3000, seed=9)
    for points in (None, elsewhere):
        expected = decode_tile_attributes(stream, support, points, coded, TILE, "tile")
        for layout in (stream, old):
            decoded = decode_tile_attributes(layout, support, points, coded, TILE, "tile", crc_optional=True)
            assert set(decoded) == set(expected)
            for name in expected:
                assert decoded[name].dtype == expected[name].dtype and np.array_equal(decoded[name], expected[name])
    with pytest.raises(ContainerError, match=r"support \(\d+ voxels, CRC [0-9a-f]{8}\) does not match"):
        decode_tile_attributes(old, support, None, coded, TILE, "tile")
    with pytest.raises(ContainerError, match="read without the CRC .*voxel count is not the decoded tile's"):
        decode_tile_attributes(old, surface(4000, seed=5)[:3000], None, coded, TILE, "tile", crc_optional=True)
    for bad in (old + b"\0\0\0\0", old[:-4], old[:6]):
        with pytest.raises(ContainerError, match="read without the CRC"):
            decode_tile_attributes(bad, support, None, coded, TILE, "tile", crc_optional=True)


def test_crafted_streams_of_either_layout_give_a_clean_error_where_both_are_read():
    support = surface(4000)
    values = {"intensity": support[:, 0] * 3, "label": (support[:, 0] // 10).astype(np.uint8)}
    coded = schema(INTENSITY, LABEL)
    stream = encode_tile_attributes(support, support, values, coded, TILE)
    rng = np.random.default_rng(4)
    cases = []
    for layout in (stream, without_crc(stream)):
        cases += [layout[:-1], layout[:3], layout + b"\1"]
        for _ in range(40):
            corrupt = bytearray(layout)
            corrupt[rng.integers(0, len(layout))] ^= 1 << int(rng.integers(0, 8))
            cases.append(bytes(corrupt))
    errors = 0
    for case in cases:
        try:
            decoded = decode_tile_attributes(case, support, None, coded, TILE, "tile", crc_optional=True)
        except ContainerError:
            errors += 1
            continue
        assert set(decoded) == {"intensity", "label"} and len(decoded["label"]) == len(support)
    assert errors >= len(cases) // 2
