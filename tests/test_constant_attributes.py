"""Attributes holding one value over the map (LAS fields such as user_data or point_source_id): stored in the schema
as that value (container version 8), no per-tile stream, decoded exactly; other files keep version 7 and their
bytes."""

import struct
import zlib

import laspy
import numpy as np
import pytest

import mapsqueeze
from mapsqueeze.codec import attributes as attribute_coding
from mapsqueeze.codec.attributes import CONSTANT, ValueRange
from mapsqueeze.codec.container import open_container
from mapsqueeze.codec.entropy import ByteReader
from mapsqueeze.errors import ContainerError
from mapsqueeze.io import read_point_cloud

UTM = np.array([500000.0, 4000000.0, 40.0])
TILE_X = 40.0


def two_tile_street(n: int = 24000, seed: int = 0):
    """Ground and a wall over two tiles along x (the map is 76 m long); LAS fields: intensity varying,
    classification 2 in the first tile and 2 or 6 in the second, user_data, point_source_id and gps_time
    constant."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0, 76, n), rng.uniform(0, 36, n), rng.normal(0, 0.02, n)])
    wall = np.column_stack([rng.uniform(0, 76, n // 3), 30 + rng.normal(0, 0.02, n // 3),
                            rng.uniform(0, 8, n // 3)])
    local = np.concatenate([ground, wall])
    intensity = np.clip(np.where(local[:, 0] > 18, 150.0, 40.0) + rng.normal(0, 8, len(local)), 0, 255)
    classification = np.where((local[:, 0] > TILE_X) & (local[:, 2] > 1), 6, 2).astype(np.uint8)
    fields = {"intensity": intensity.astype(np.uint16), "classification": classification,
              "user_data": np.zeros(len(local), np.uint8), "point_source_id": np.full(len(local), 7, np.uint16),
              "gps_time": np.full(len(local), 123456.789)}
    return local + UTM, fields


def write_laz(path, points, fields):
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = np.full(3, 0.001), UTM
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    for name, values in fields.items():
        setattr(las, name, values)
    las.write(str(path))


def old_layout(monkeypatch, compress):
    """`compress()` as the writer before constant attributes: every attribute coded per tile."""
    with monkeypatch.context() as patch:
        patch.setattr(attribute_coding.ValueRange, "of", classmethod(
            lambda cls, values: ValueRange(values.dtype, float(values.min()), float(values.max()), None)))
        return compress()


@pytest.fixture(scope="module")
def laz_map(tmp_path_factory):
    folder = tmp_path_factory.mktemp("constant")
    points, fields = two_tile_street()
    write_laz(folder / "map.laz", points, fields)
    mapsqueeze.compress_file(folder / "map.laz", folder / "map.msq")
    return folder


def test_laz_constant_fields_decode_exactly_and_other_fields_as_before(laz_map, monkeypatch):
    data = (laz_map / "map.msq").read_bytes()
    assert data[4:6] == struct.pack("<H", 8)
    cloud = read_point_cloud(laz_map / "map.laz")
    assert data == mapsqueeze.compress(cloud.points, attributes=cloud.attributes, metadata=cloud.metadata)
    kinds = {spec.name: spec.kind for spec in mapsqueeze.info(data).attribute_schema.specs}
    flags = {"scan_direction_flag", "edge_of_flight_line", "synthetic", "key_point", "withheld", "overlap",
             "scanner_channel"}  # the LAS bit fields, all 0 here
    constants = {"user_data", "point_source_id", "gps_time", "return_number", "number_of_returns", "scan_angle",
                 *flags}
    assert {name for name, kind in kinds.items() if kind == CONSTANT} == constants
    assert "point_source_id (uint16, constant 7)" in mapsqueeze.info(data).attribute_summary()

    mapsqueeze.decompress_file(laz_map / "map.msq", laz_map / "out.laz")
    decoded = read_point_cloud(laz_map / "out.laz")
    for name in constants:
        values, expected = decoded.attributes[name], cloud.attributes[name][:1]
        assert values.dtype == expected.dtype and len(values) == len(decoded.points), name
        assert (values.view(f"u{values.dtype.itemsize}") == expected.view(f"u{values.dtype.itemsize}")).all(), name
    first_tile = decoded.points[:, 0] < decoded.points[:, 0].min() + TILE_X - 4
    assert (decoded.attributes["classification"][first_tile] == 2).all()
    assert set(np.unique(decoded.attributes["classification"][~first_tile])) == {2, 6}

    old = old_layout(monkeypatch, lambda: mapsqueeze.compress(cloud.points, attributes=cloud.attributes,
                                                               metadata=cloud.metadata))
    assert old[4:6] == struct.pack("<H", 7)
    # the schema: 16 bytes of low and step less the value's (1 + 1 + 1 + 2 + 2 + 8: return and return count,
    # user_data, point_source_id, scan_angle, gps_time; 1 each for the 7 bit fields); each of 2 tiles: the tables of
    # 11 categorical fields (a one-value palette, 2 bytes, two one-value histograms of 4) and of 2 continuous ones
    # (three histograms)
    assert len(old) - len(data) == (13 * 16 - 15 - 7) + 2 * (11 * (2 + 2 * 4) + 2 * 3 * 4) == 454
    old_decoded, new_decoded = mapsqueeze.decompress_cloud(old), mapsqueeze.decompress_cloud(data)
    np.testing.assert_array_equal(old_decoded.points, new_decoded.points)
    assert list(new_decoded.attributes) == list(old_decoded.attributes)
    for name, values in old_decoded.attributes.items():
        np.testing.assert_array_equal(new_decoded.attributes[name], values, err_msg=name)
        assert new_decoded.attributes[name].dtype == values.dtype


def test_non_constant_streams_keep_their_bytes(laz_map):
    cloud = read_point_cloud(laz_map / "map.laz")
    coded_only = {name: cloud.attributes[name] for name in ("intensity", "classification")}
    plain = mapsqueeze.compress(cloud.points, attributes=coded_only)
    with_constants = (laz_map / "map.msq").read_bytes()
    assert plain[4:6] == struct.pack("<H", 7)

    def streams(data):
        reader, stream = open_container(data)
        with stream:
            return [reader.attribute_stream(position) for position in range(len(reader.entries))]

    assert len(streams(plain)) == 2 and streams(plain) == streams(with_constants)


def test_constants_only_have_no_streams_and_chunks_merge_exactly():
    rng = np.random.default_rng(1)
    points = np.column_stack([rng.uniform(0, 70, 3000), rng.uniform(0, 30, 3000), rng.uniform(0, 2, 3000)]) + UTM
    attributes = {"user_data": np.zeros(3000, np.uint8), "offset": np.full(3000, -2**62 - 1, np.int64)}
    plain = mapsqueeze.compress(points)
    data = mapsqueeze.compress(points, attributes=attributes)
    reader, stream = open_container(data)
    with stream:
        assert reader.version == 8 and reader.attribute_entries == [] and len(reader.entries) == 2
    # the section: u32 length, schema (voxel, count, two constant records, no metadata), CRC; no tile index entries
    assert len(data) - len(plain) == 4 + (8 + 1 + (1 + 9 + 1 + 3 + 1 + 1) + (1 + 6 + 1 + 3 + 1 + 8) + 1) + 4
    decoded = mapsqueeze.decompress_cloud(data)
    assert decoded.attributes["offset"].dtype == np.int64 and (decoded.attributes["offset"] == -2**62 - 1).all()
    assert decoded.attributes["user_data"].dtype == np.uint8 and (decoded.attributes["user_data"] == 0).all()
    assert len(decoded.attributes["offset"]) == len(decoded.points)
    dense = mapsqueeze.decompress_cloud(data, n_points=5000)
    assert len(dense.attributes["offset"]) == 5000

    big = np.uint64(2**63)
    assert ValueRange.of(np.array([big, big + np.uint64(1)])).constant is None  # equal as float64
    assert ValueRange.of(np.array([0.0, -0.0])).constant is None  # equal as numbers, not bit for bit
    first, second = ValueRange.of(np.full(3, 5, np.uint16)), ValueRange.of(np.full(2, 5, np.uint16))
    assert first.merge(second).constant == np.uint16(5).tobytes()
    assert first.merge(ValueRange.of(np.array([5, 6], np.uint16))).constant is None


def schema_section(data: bytes) -> tuple[int, bytes]:
    """(offset of the attribute section, its index bytes) of a file whose schema codes constants only."""
    reader, stream = open_container(data)
    with stream:
        start = reader.entries[-1].offset + reader.entries[-1].length
    (size,) = struct.unpack_from("<I", data, start)
    return start, data[start + 4:start + 4 + size]


def with_section(data: bytes, start: int, index: bytes) -> bytes:
    return data[:start] + struct.pack("<I", len(index)) + index + struct.pack("<I", zlib.crc32(index))


def with_version(data: bytes, version: int) -> bytes:
    """The file with another version number (the CRC after the header and table redone)."""
    out = bytearray(data)
    out[4:6] = struct.pack("<H", version)
    lengths = ByteReader(bytes(out[6:30]), "preamble")
    lengths.varint()
    body, table = lengths.varint(), lengths.varint()
    end = 6 + 24 - lengths.remaining + body + table
    struct.pack_into("<I", out, end, zlib.crc32(bytes(out[:end])))
    return bytes(out)


def test_bad_constant_records_are_one_line_errors(tmp_path, run_cli):
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(0, 30, 500), rng.uniform(0, 30, 500), rng.uniform(0, 2, 500)]) + UTM
    data = mapsqueeze.compress(points, attributes={"gain": np.full(500, 1.5, np.float32)})
    start, index = schema_section(data)
    record = index.index(b"gain")
    dtype_at, value_at = record + 4 + 1, record + 4 + 1 + 3 + 1
    assert index[dtype_at:dtype_at + 3] == b"<f4" and index[value_at - 1] == CONSTANT
    assert np.frombuffer(index[value_at:value_at + 4], np.float32)[0] == 1.5
    cases = {
        "version 7": (with_version(data, 7), r"bad attribute 'gain' \(kind 2\)"),
        "truncated value": (with_section(data, start, index[:value_at + 2]), "truncated"),
        "value one byte short": (with_section(data, start, index[:value_at + 3] + index[value_at + 4:]),
                                 "truncated|metadata|bytes"),
        "dtype too wide": (with_section(data, start, index[:dtype_at - 1] + b"\x04<f16" + index[dtype_at + 3:]),
                           "constant attribute 'gain' of dtype <f16"),
        "dtype not numeric": (with_section(data, start, index[:dtype_at] + b"<U1" + index[dtype_at + 3:]),
                              "bad attribute 'gain'"),
        "dtype numpy parses as Python": (with_section(data, start, index[:dtype_at - 1] + b"\x04u2,)"
                                                      + index[dtype_at + 3:]), "bad attribute name or dtype"),
        "dtype of a bad literal": (with_section(data, start, index[:dtype_at] + b"053" + index[dtype_at + 3:]),
                                   "bad attribute name or dtype"),
        "not finite": (with_section(data, start, index[:value_at] + np.float32(np.nan).tobytes()
                                    + index[value_at + 4:]), "not finite"),
        "unknown kind": (with_section(data, start, index[:value_at - 1] + b"\x03" + index[value_at:]),
                         "bad attribute 'gain'"),
        "section cut": (data[:-3], "attribute section"),
    }
    for case, (crafted, message) in cases.items():
        with pytest.raises(ContainerError, match=message) as error:
            mapsqueeze.decompress_cloud(crafted)
        assert "\n" not in str(error.value), case
    (tmp_path / "wide.msq").write_bytes(cases["dtype too wide"][0])
    code, _, err = run_cli("decompress", str(tmp_path / "wide.msq"), "-o", str(tmp_path / "out.ply"))
    assert code == 2 and err.count("\n") == 1 and err.startswith("error: ") and "dtype <f16" in err
    for position in range(len(index)):  # every byte of the schema changed, the section CRC redone
        crafted = bytearray(index)
        crafted[position] ^= 0x5A
        try:
            decoded = mapsqueeze.decompress_cloud(with_section(data, start, bytes(crafted)))
        except ContainerError as error:
            assert "\n" not in str(error)
        else:
            assert all(len(values) == len(decoded.points) for values in decoded.attributes.values())
