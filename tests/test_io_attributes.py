"""Attributes and metadata through every format: LAS fields and CRS, SemanticKITTI labels, chunked I/O, convert."""

import struct
import subprocess
import sys
import warnings
from pathlib import Path

import laspy
import numpy as np
import pytest

from mapsqueeze.errors import CrsNotWrittenWarning, FieldRenamedWarning, InvalidPointCloudError
from mapsqueeze.io import (
    PointCloud,
    dropped_fields,
    iter_point_clouds,
    read_point_cloud,
    write_point_chunks,
    write_points,
)

UTM = np.array([500000.0, 4000000.0, 50.0])


def geokey_vlr(epsg: int) -> laspy.VLR:
    """A GeoKeyDirectory VLR declaring a projected CRS (ProjectedCSTypeGeoKey 3072 = epsg)."""
    keys = [1, 1, 0, 1, 3072, 0, 1, epsg]
    return laspy.VLR("LASF_Projection", 34735, "GeoKeyDirectoryTag", struct.pack(f"<{len(keys)}H", *keys))


def make_laz(path: Path, n: int = 2000, seed: int = 0) -> laspy.LasData:
    """A LAZ in point format 3 with intensity, returns, classification, GPS time, RGB, an extra dim and a CRS."""
    rng = np.random.default_rng(seed)
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales, header.offsets = np.array([0.001, 0.001, 0.01]), UTM
    header.vlrs.append(geokey_vlr(32632))
    header.add_extra_dims([laspy.ExtraBytesParams("laser", np.uint8, "laser number")])
    las = laspy.LasData(header)
    xyz = UTM + rng.uniform(0, 60, (n, 3))
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = rng.integers(0, 4000, n).astype(np.uint16)
    las.return_number = rng.integers(1, 4, n)
    las.number_of_returns = np.full(n, 3)
    las.classification = rng.choice([2, 5, 6], n)
    las.gps_time = 1e5 + np.sort(rng.random(n)) * 10
    las.red, las.green, las.blue = (rng.integers(0, 65536, n).astype(np.uint16) for _ in range(3))
    las.laser = rng.integers(0, 64, n).astype(np.uint8)
    las.write(str(path))
    return las


LAS_FIELDS = ("intensity", "return_number", "number_of_returns", "classification", "gps_time", "red", "green",
              "blue", "laser")


def test_las_reads_every_field_and_the_crs(tmp_path):
    source = make_laz(tmp_path / "a.laz")
    cloud = read_point_cloud(tmp_path / "a.laz")
    for name in LAS_FIELDS:
        np.testing.assert_array_equal(cloud.attributes[name], np.asarray(source[name]), err_msg=name)
    las = cloud.metadata["las"]
    assert cloud.metadata["crs"] == "EPSG:32632"
    assert las["point_format"] == 3 and las["scales"] == [0.001, 0.001, 0.01] and las["offsets"] == list(UTM)
    assert las["extra_bytes"]["laser"]["description"] == "laser number"


def test_las_round_trip_keeps_fields_format_scales_and_crs_records(tmp_path):
    make_laz(tmp_path / "a.laz")
    cloud = read_point_cloud(tmp_path / "a.laz")
    write_points(tmp_path / "b.laz", cloud.points, attributes=cloud.attributes, metadata=cloud.metadata)
    again = laspy.read(tmp_path / "b.laz")
    original = laspy.read(tmp_path / "a.laz")
    assert again.header.point_format.id == 3
    np.testing.assert_array_equal(again.header.scales, original.header.scales)
    np.testing.assert_array_equal(again.header.offsets, original.header.offsets)
    np.testing.assert_array_equal(again.X, original.X)
    for name in LAS_FIELDS:
        np.testing.assert_array_equal(np.asarray(again[name]), np.asarray(original[name]), err_msg=name)
    geokeys = [vlr for vlr in again.header.vlrs if vlr.record_id == 34735]
    assert len(geokeys) == 1 and read_point_cloud(tmp_path / "b.laz").metadata["crs"] == "EPSG:32632"
    assert again.header.point_format.dimension_by_name("laser").description.strip("\0") == "laser number"


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_evlrs_are_written_back_after_the_points(tmp_path, suffix):
    """A WKT CRS (and any other record) stored as an EVLR is written back as one, with the WKT bit; before, the
    streaming writer dropped header.evlrs and kept the WKT bit, a file that declares a WKT it does not hold."""
    wkt = 'PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84"],UNIT["metre",1]]'
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = np.full(3, 0.001), UTM
    header.global_encoding.wkt = True
    las = laspy.LasData(header)
    xyz = UTM + np.random.default_rng(2).uniform(0, 30, (300, 3))
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.evlrs = laspy.vlrs.vlrlist.VLRList([laspy.vlrs.known.WktCoordinateSystemVlr(wkt),
                                            laspy.VLR("acme", 7, "notes", b"a long record" * 10)])
    las.write(str(tmp_path / f"a{suffix}"))
    cloud = read_point_cloud(tmp_path / f"a{suffix}")
    assert cloud.metadata["crs"] == wkt
    write_points(tmp_path / f"b{suffix}", cloud.points, attributes=cloud.attributes, metadata=cloud.metadata)
    again = laspy.read(tmp_path / f"b{suffix}")
    assert again.header.global_encoding.wkt and len(again.points) == 300
    assert [(vlr.user_id, vlr.record_id) for vlr in again.evlrs] == [("LASF_Projection", 2112), ("acme", 7)]
    assert again.evlrs[0].string.strip("\0") == wkt and again.evlrs[1].record_data_bytes() == b"a long record" * 10
    np.testing.assert_array_equal(again.X, las.X)
    assert read_point_cloud(tmp_path / f"b{suffix}").metadata["crs"] == wkt


def test_las_evlrs_make_the_file_version_1_4(tmp_path):
    """EVLRs read from a LAS 1.4 file in point format 3 keep version 1.4 even where the metadata says 1.2."""
    cloud = PointCloud(UTM + np.random.default_rng(3).uniform(0, 30, (100, 3)), {}, {"las": {
        "version": "1.2", "point_format": 3, "evlrs": [{"user_id": "acme", "record_id": 1, "description": "",
                                                        "data": "AAEC"}]}})
    write_points(tmp_path / "a.las", cloud.points, metadata=cloud.metadata)
    again = laspy.read(tmp_path / "a.las")
    assert str(again.header.version) == "1.4" and again.evlrs[0].record_data_bytes() == bytes([0, 1, 2])


def test_las_point_format_is_the_first_whose_fields_hold_the_values(tmp_path):
    """Classification 40 (a PLY or PCD label) needs point format 6 (0..255; formats 0-5 hold 0..31): the format is
    chosen by the values, where before the write was refused. A LAS file's own format stays where it holds them."""
    points = UTM + np.random.default_rng(4).uniform(0, 30, (200, 3))
    classification = np.arange(200, dtype=np.uint16) % 41
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert write_points(tmp_path / "a.las", points, attributes={"classification": classification}) \
            == ("classification",)
    again = laspy.read(tmp_path / "a.las")
    assert again.header.point_format.id == 6 and str(again.header.version) == "1.4"
    np.testing.assert_array_equal(again.classification, classification)
    write_points(tmp_path / "b.las", points, attributes={"classification": classification % 32})
    assert laspy.read(tmp_path / "b.las").header.point_format.id == 0
    las3 = {"las": {"version": "1.2", "point_format": 3}}
    write_points(tmp_path / "c.las", points, attributes={"classification": classification}, metadata=las3)
    assert laspy.read(tmp_path / "c.las").header.point_format.id == 6
    write_points(tmp_path / "d.las", points, attributes={"classification": classification % 32}, metadata=las3)
    assert laspy.read(tmp_path / "d.las").header.point_format.id == 3


def test_las_field_that_cannot_hold_the_values_is_written_as_an_extra_dimension(tmp_path, run_cli):
    """A float intensity (PCL's PointXYZI; KITTI's 0..1 reflectance) is no LAS intensity (an integer in 0..65535):
    it is written exactly as the extra dimension intensity_float32, with a FieldRenamedWarning (one warning line in
    the CLI); a float intensity of whole numbers in range stays the standard field."""
    points = UTM + np.random.default_rng(5).uniform(0, 30, (300, 3))
    intensity = np.random.default_rng(6).random(300).astype(np.float32)
    with pytest.warns(FieldRenamedWarning, match="attribute 'intensity' \\(float32\\) is not; written as the extra "
                                                 "dimension 'intensity_float32'"):
        stored = write_points(tmp_path / "a.laz", points, attributes={"intensity": intensity, "ring": np.zeros(300)})
    assert stored == ("intensity_float32", "ring")
    cloud = read_point_cloud(tmp_path / "a.laz")
    np.testing.assert_array_equal(cloud.attributes["intensity_float32"], intensity)
    assert not cloud.attributes["intensity"].any()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_points(tmp_path / "b.las", points, attributes={"intensity": np.round(intensity * 1000)})
    np.testing.assert_array_equal(laspy.read(tmp_path / "b.las").intensity, np.round(intensity * 1000))
    with pytest.warns(FieldRenamedWarning) as caught:  # with labels beyond 31: format 6, intensity alone moved
        write_points(tmp_path / "c.las", points, attributes={"intensity": intensity,
                                                             "classification": np.full(300, 44, np.uint8)})
    assert len(caught) == 1 and laspy.read(tmp_path / "c.las").header.point_format.id == 6
    np.testing.assert_array_equal(laspy.read(tmp_path / "c.las").classification, 44)
    write_points(tmp_path / "scan.ply", points, attributes={"intensity": intensity})
    code, out, err = run_cli("convert", str(tmp_path / "scan.ply"), str(tmp_path / "scan.las"))
    assert code == 0 and "wrote 300 points" in out
    assert err.count("\n") == 1 and err.startswith("warning: scan.las: LAS intensity is an integer in 0..65535")
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "scan.las").attributes["intensity_float32"], intensity)


def test_las_array_extra_dimensions_are_written_back_as_arrays(tmp_path):
    """A k-element extra-bytes dimension (a normal as 3 x float32; a scaled 2 x int16) is read as the columns name_0
    .. name_{k-1} and written back as one array dimension with its description, type, scales and offsets, in the
    order of the dimensions; before, it came back as k scalar dimensions."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = np.full(3, 0.001), UTM
    header.add_extra_dims([laspy.ExtraBytesParams("normal", "3f4", "unit normal"),
                           laspy.ExtraBytesParams("amp", np.uint8, "amplitude"),
                           laspy.ExtraBytesParams("slope", "2i2", "slope", scales=np.array([0.01, 0.01]),
                                                  offsets=np.array([0.0, 1.0]))])
    las = laspy.LasData(header)
    rng = np.random.default_rng(8)
    xyz = UTM + rng.uniform(0, 30, (400, 3))
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.normal = rng.standard_normal((400, 3)).astype(np.float32)
    las.amp = rng.integers(0, 255, 400)
    las.slope = np.round(rng.uniform(-3, 3, (400, 2)), 2)
    las.write(str(tmp_path / "a.laz"))
    cloud = read_point_cloud(tmp_path / "a.laz")
    assert {"normal_0", "normal_2", "slope_1", "amp"} <= set(cloud.attributes)
    write_points(tmp_path / "b.laz", cloud.points, attributes=cloud.attributes, metadata=cloud.metadata)
    again = laspy.read(tmp_path / "b.laz")
    assert [(d.name, d.num_elements, d.description.strip("\0")) for d in again.point_format.extra_dimensions] == \
        [("normal", 3, "unit normal"), ("amp", 1, "amplitude"), ("slope", 2, "slope")]
    for name in ("normal", "amp", "slope"):
        np.testing.assert_array_equal(np.asarray(again[name]), np.asarray(las[name]), err_msg=name)
    slope = again.point_format.dimension_by_name("slope")
    np.testing.assert_allclose(slope.scales, [0.01, 0.01])
    np.testing.assert_allclose(slope.offsets, [0, 1])
    np.testing.assert_array_equal(np.asarray(again.points.array["slope"]), np.asarray(las.points.array["slope"]))


def test_las_extra_dimension_no_data_values_are_kept(tmp_path):
    """The no-data value an extra dimension declares (plain, scaled, array) is read into the metadata and written
    back; laspy's dimension list leaves it out, so it was lost before."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = np.full(3, 0.001), UTM
    header.add_extra_dims([laspy.ExtraBytesParams("deviation", "u2", "dev", no_data=[65535]),
                           laspy.ExtraBytesParams("temp", "i2", "temp", scales=[0.1], offsets=[0.0], no_data=[-32768]),
                           laspy.ExtraBytesParams("normal", "3f4", "normal", no_data=[0.0, 0.0, -1.0]),
                           laspy.ExtraBytesParams("amp", "u1", "amplitude")])
    las = laspy.LasData(header)
    rng = np.random.default_rng(9)
    xyz = UTM + rng.uniform(0, 30, (100, 3))
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.deviation = np.where(rng.random(100) < 0.3, 65535, 5)
    las.temp = np.round(rng.uniform(-5, 5, 100), 1)
    las.normal = rng.standard_normal((100, 3)).astype(np.float32)
    las.write(str(tmp_path / "a.las"))
    cloud = read_point_cloud(tmp_path / "a.las")
    assert cloud.metadata["las"]["extra_bytes"]["deviation"]["no_data"] == [65535]
    assert "no_data" not in cloud.metadata["las"]["extra_bytes"]["amp"]
    write_points(tmp_path / "b.laz", cloud.points, attributes=cloud.attributes, metadata=cloud.metadata)
    (vlr,) = [vlr for vlr in laspy.read(tmp_path / "b.laz").header.vlrs
              if isinstance(vlr, laspy.vlrs.known.ExtraBytesVlr)]
    written = {struct.format_name(): struct.no_data for struct in vlr.extra_bytes_structs}
    assert written["deviation"].tolist() == [65535] and written["temp"].tolist() == [-32768]
    assert written["normal"].tolist() == [0.0, 0.0, -1.0] and written["amp"] is None


LAS_FLAGS = {3: ("scan_direction_flag", "edge_of_flight_line", "synthetic", "key_point", "withheld"),
             6: ("scan_direction_flag", "edge_of_flight_line", "synthetic", "key_point", "withheld", "overlap",
                 "scanner_channel")}


@pytest.mark.parametrize("point_format", [3, 6])
def test_las_bit_flags_are_read_and_written_back_exactly(tmp_path, point_format):
    """The bit fields (scan direction, edge of flight line, synthetic, key-point, withheld; in formats 6-10 overlap
    and scanner channel) are uint8 attributes, kept exactly through LAS -> PLY -> LAS; the classification beside
    them is unchanged."""
    n, rng = 500, np.random.default_rng(1)
    header = laspy.LasHeader(version="1.4", point_format=point_format)
    header.scales, header.offsets = np.full(3, 0.001), UTM
    las = laspy.LasData(header)
    xyz = UTM + rng.uniform(0, 30, (n, 3))
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.classification = rng.choice([2, 6, 31], n)
    flags = {name: rng.integers(0, 4 if name == "scanner_channel" else 2, n) for name in LAS_FLAGS[point_format]}
    for name, values in flags.items():
        las[name] = values
    las.write(str(tmp_path / "a.las"))
    cloud = read_point_cloud(tmp_path / "a.las")
    for name, values in flags.items():
        assert cloud.attributes[name].dtype == np.uint8
        np.testing.assert_array_equal(cloud.attributes[name], values, err_msg=name)
    write_points(tmp_path / "a.ply", cloud.points, attributes=cloud.attributes)
    plain = read_point_cloud(tmp_path / "a.ply")
    write_points(tmp_path / "b.las", plain.points, attributes=plain.attributes, metadata=cloud.metadata)
    again = laspy.read(tmp_path / "b.las")
    assert again.header.point_format.id == point_format
    for name in (*flags, "classification"):
        np.testing.assert_array_equal(np.asarray(again[name]), np.asarray(las[name]), err_msg=name)


def test_las_point_format_follows_the_fields_when_there_is_no_metadata(tmp_path):
    n = 50
    points = np.random.default_rng(0).random((n, 3))
    write_points(tmp_path / "rgb.las", points, attributes={"red": np.ones(n, np.uint16), "gps_time": np.ones(n)})
    assert laspy.read(tmp_path / "rgb.las").header.point_format.id == 3
    write_points(tmp_path / "plain.las", points, attributes={"intensity": np.ones(n, np.uint16)})
    assert laspy.read(tmp_path / "plain.las").header.point_format.id == 0


def test_las_through_ply_and_back_keeps_every_field(tmp_path):
    make_laz(tmp_path / "a.laz")
    cloud = read_point_cloud(tmp_path / "a.laz")
    write_points(tmp_path / "a.ply", cloud.points, attributes=cloud.attributes)
    via_ply = read_point_cloud(tmp_path / "a.ply")
    for name, values in cloud.attributes.items():
        np.testing.assert_array_equal(via_ply.attributes[name], values, err_msg=name)
        assert via_ply.attributes[name].dtype == values.dtype


@pytest.mark.parametrize("name", ["a.ply", "a.las", "a.laz", "a.npy", "a.pcd.bin", "a.bin"])
def test_chunked_reading_keeps_attributes(tmp_path, name):
    n = 3001
    rng = np.random.default_rng(3)
    attributes = {"intensity": rng.integers(0, 255, n).astype(np.float32), "ring": np.arange(n) % 32}
    if name.endswith(".bin") and not name.endswith(".pcd.bin"):
        attributes = {"reflectance": rng.random(n).astype(np.float32), "label": (np.arange(n) % 20).astype(np.uint16),
                      "instance": (np.arange(n) % 7).astype(np.uint16)}
    if name.endswith((".las", ".laz")):
        attributes["intensity"] = attributes["intensity"].astype(np.uint16)
    write_points(tmp_path / name, rng.random((n, 3)), attributes=attributes)
    whole = read_point_cloud(tmp_path / name)
    chunks = list(iter_point_clouds(tmp_path / name, chunk_points=700))
    assert len(chunks) == 5
    for key, values in whole.attributes.items():
        np.testing.assert_array_equal(np.concatenate([c.attributes[key] for c in chunks]), values)
    if not name.endswith(".npy"):  # .npy stores no names
        assert set(attributes) <= set(whole.attributes)


@pytest.mark.parametrize("name", ["a.ply", "a.las", "a.pcd", "a.bin", "a.ply-ascii", "a.npy"])
def test_chunked_writing_keeps_attributes_and_metadata(tmp_path, name):
    n = 2500
    rng = np.random.default_rng(4)
    points = rng.random((n, 3)) * 30
    attributes = {"reflectance": rng.random(n).astype(np.float32), "label": (np.arange(n) % 9).astype(np.uint16)}
    format = "ply-ascii" if name.endswith("ply-ascii") else None
    path = tmp_path / name.replace(".ply-ascii", ".ply")
    count = write_point_chunks(path, lambda: (PointCloud(points[i:i + 600], {k: v[i:i + 600] for k, v in
                                                                             attributes.items()})
                                              for i in range(0, n, 600)), format=format)
    assert count == n
    cloud = read_point_cloud(path)
    restored = cloud.attributes if not name.endswith(".npy") else {
        "reflectance": cloud.attributes["column3"], "label": cloud.attributes["column4"]}
    for key, values in attributes.items():
        np.testing.assert_allclose(restored[key], values, rtol=1e-6)


def test_semantic_kitti_labels_beside_the_scan_and_in_labels_folder(tmp_path):
    n = 100
    label, instance = (np.arange(n) % 30).astype(np.uint16), (np.arange(n) // 10).astype(np.uint16)
    write_points(tmp_path / "000000.bin", np.random.default_rng(0).random((n, 3)),
                 attributes={"reflectance": np.zeros(n, np.float32), "label": label, "instance": instance})
    packed = np.fromfile(tmp_path / "000000.label", dtype="<u4")
    np.testing.assert_array_equal(packed, label.astype(np.uint32) | (instance.astype(np.uint32) << 16))
    cloud = read_point_cloud(tmp_path / "000000.bin")
    np.testing.assert_array_equal(cloud.attributes["label"], label)
    np.testing.assert_array_equal(cloud.attributes["instance"], instance)
    (tmp_path / "seq" / "velodyne").mkdir(parents=True)
    (tmp_path / "seq" / "labels").mkdir()
    (tmp_path / "000000.bin").rename(tmp_path / "seq" / "velodyne" / "000000.bin")
    (tmp_path / "000000.label").rename(tmp_path / "seq" / "labels" / "000000.label")
    cloud = read_point_cloud(tmp_path / "seq" / "velodyne" / "000000.bin")
    np.testing.assert_array_equal(cloud.attributes["label"], label)
    (tmp_path / "seq" / "labels" / "000000.label").write_bytes(b"\0" * 8)
    with pytest.raises(Exception, match="labels hold 2 entries"):
        read_point_cloud(tmp_path / "seq" / "velodyne" / "000000.bin")


def test_dropped_fields_and_attribute_dtype_mismatch(tmp_path):
    assert dropped_fields(["reflectance", "ring", "label"], tmp_path / "a.bin") == ["ring"]
    assert dropped_fields(["ring"], tmp_path / "a.ply") == []
    chunks = [PointCloud(np.zeros((2, 3)), {"a": np.zeros(2, np.float32)}),
              PointCloud(np.zeros((2, 3)), {"a": np.zeros(2, np.float64)})]
    with pytest.raises(InvalidPointCloudError, match="chunks differ"):
        write_point_chunks(tmp_path / "a.ply", lambda: iter(chunks))


def test_cli_convert_warns_once_about_dropped_fields(tmp_path):
    cli = Path(sys.executable).parent / "mapsqueeze"
    if not cli.exists():
        pytest.skip("CLI not installed")
    n = 40
    write_points(tmp_path / "a.ply", np.random.default_rng(0).random((n, 3)),
                 attributes={"reflectance": np.ones(n, np.float32), "ring": np.zeros(n, np.uint8),
                             "laser": np.zeros(n, np.uint8)})
    result = subprocess.run([str(cli), "convert", str(tmp_path / "a.ply"), str(tmp_path / "a.bin")],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stderr.count("\n") == 1 and "ring, laser" in result.stderr and "warning" in result.stderr
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "a.bin").attributes["reflectance"], 1.0)


def test_cli_warns_that_npy_keeps_attributes_as_unnamed_columns(run_cli, tmp_path):
    """.npy stores attributes as float64 columns 3, 4, ... without names or dtypes: one warning line maps each name
    to its column (before, intensity and label came back as column3, column4 unsaid); none for a file whose
    attributes are already those columns."""
    n = 50
    write_points(tmp_path / "a.ply", np.random.default_rng(1).random((n, 3)),
                 attributes={"intensity": np.ones(n, np.float32), "label": np.full(n, 7, np.uint16)})
    code, out, err = run_cli("convert", str(tmp_path / "a.ply"), str(tmp_path / "a.npy"))
    assert code == 0 and err == ("warning: a.npy holds attributes as unnamed float64 columns: intensity as column3, "
                                 "label as column4\n")
    assert list(read_point_cloud(tmp_path / "a.npy").attributes) == ["column3", "column4"]
    code, out, err = run_cli("convert", str(tmp_path / "a.npy"), str(tmp_path / "b.npy"))
    assert code == 0 and err == ""


def test_cli_warns_when_the_output_cannot_hold_the_crs(run_cli, tiny_model_dir, tmp_path):
    """convert and decompress to a format without a place for the CRS (all but LAS/LAZ) say it is not written."""
    import mapsqueeze

    make_laz(tmp_path / "a.laz", n=300)
    code, _, err = run_cli("convert", str(tmp_path / "a.laz"), str(tmp_path / "a.ply"))
    assert code == 0 and err == "warning: a.ply cannot hold the CRS (EPSG:32632); not written\n"
    code, _, err = run_cli("convert", str(tmp_path / "a.laz"), str(tmp_path / "b.laz"))
    assert code == 0 and err == ""
    mapsqueeze.compress_file(tmp_path / "a.laz", tmp_path / "a.msq", model=tiny_model_dir)
    code, _, err = run_cli("decompress", str(tmp_path / "a.msq"), "-o", str(tmp_path / "d.ply"), "--model",
                           str(tiny_model_dir), "--no-attributes")
    assert code == 0 and err == "warning: d.ply cannot hold the CRS (EPSG:32632); not written\n"
    code, _, err = run_cli("decompress", str(tmp_path / "a.msq"), "-o", str(tmp_path / "d.bin"), "--model",
                           str(tiny_model_dir))  # UTM in a float32 format: the error alone, no warnings before it
    assert code == 2 and err.count("\n") == 1 and err.startswith("error: ") and "float32" in err


@pytest.mark.parametrize("crs, shown", [(32632, "32632"), ('PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84"]]', "a WKT")])
def test_cli_decompress_warns_of_a_crs_the_api_stored_as_any_value(run_cli, tiny_model_dir, tmp_path, crs, shown):
    """metadata["crs"] given to the API may be any JSON value: the warning names it, it does not fail."""
    import mapsqueeze

    points = np.random.default_rng(0).uniform(0, 5, (300, 3))
    (tmp_path / "a.msq").write_bytes(mapsqueeze.compress(points, model=tiny_model_dir, metadata={"crs": crs}))
    code, _, err = run_cli("decompress", str(tmp_path / "a.msq"), "-o", str(tmp_path / "d.ply"), "--model",
                           str(tiny_model_dir))
    assert code == 0 and err == f"warning: d.ply cannot hold the CRS ({shown}); not written\n", err


WKT_UTM32 = ('PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84",DATUM["WGS_1984",'
             'SPHEROID["WGS 84",6378137,298.257223563]],'
             'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],'
             'PARAMETER["central_meridian",9],PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],'
             'UNIT["metre",1],AUTHORITY["EPSG","32632"]]')


@pytest.mark.parametrize("name", ["d.las", "d.laz"])
def test_cli_decompress_writes_a_wkt_crs_given_through_the_api_to_las(run_cli, tiny_model_dir, tmp_path, name):
    """A WKT given as metadata["crs"] to the API, without LAS records, is written to LAS/LAZ as a WKT record (global
    encoding's WKT bit set) and read back as the same CRS; no warning."""
    import mapsqueeze

    points = np.random.default_rng(0).uniform(0, 5, (300, 3))
    (tmp_path / "a.msq").write_bytes(mapsqueeze.compress(points, model=tiny_model_dir,
                                                         metadata={"crs": WKT_UTM32}))
    code, _, err = run_cli("decompress", str(tmp_path / "a.msq"), "-o", str(tmp_path / name), "--model",
                           str(tiny_model_dir))
    assert code == 0 and err == "", err
    header = laspy.read(tmp_path / name).header
    assert [vlr.record_id for vlr in header.vlrs if vlr.user_id == "LASF_Projection"] == [2112]
    assert header.global_encoding.wkt
    assert read_point_cloud(tmp_path / name).metadata["crs"] == WKT_UTM32


def test_cli_decompress_warns_that_las_cannot_take_an_epsg_code_alone(run_cli, tiny_model_dir, tmp_path):
    """An EPSG code given as metadata["crs"] to the API has no LAS record to be written as (that needs its WKT or
    GeoTIFF keys): the LAS is written without it, and a warning says so."""
    import mapsqueeze

    points = np.random.default_rng(0).uniform(0, 5, (300, 3))
    (tmp_path / "a.msq").write_bytes(mapsqueeze.compress(points, model=tiny_model_dir,
                                                         metadata={"crs": "EPSG:32632"}))
    code, _, err = run_cli("decompress", str(tmp_path / "a.msq"), "-o", str(tmp_path / "d.las"), "--model",
                           str(tiny_model_dir))
    assert code == 0 and err == ("warning: d.las cannot hold the CRS (EPSG:32632) as given: LAS takes a WKT or the "
                                 "LAS records it was read from; not written\n"), err
    assert "crs" not in read_point_cloud(tmp_path / "d.las").metadata


@pytest.mark.parametrize("output", ["d.las", "d.ply", "d.pcd"])
def test_api_writes_warn_of_a_crs_they_drop(tiny_model_dir, tmp_path, output):
    """Through the API too (decompress_file, streamed PLY included, and write_points), a CRS the output cannot hold
    is a CrsNotWrittenWarning, not a silent loss; the CLI prints the same warning as its one line."""
    import mapsqueeze

    points = np.random.default_rng(0).uniform(0, 5, (300, 3))
    (tmp_path / "a.msq").write_bytes(mapsqueeze.compress(points, model=tiny_model_dir,
                                                         metadata={"crs": "EPSG:32632"}))
    with pytest.warns(CrsNotWrittenWarning, match=f"{output} cannot hold the CRS \\(EPSG:32632\\)"):
        mapsqueeze.decompress_file(tmp_path / "a.msq", tmp_path / output, model=tiny_model_dir)
    with pytest.warns(CrsNotWrittenWarning, match="w.ply cannot hold the CRS"):
        write_points(tmp_path / "w.ply", points, metadata={"crs": "EPSG:32632"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_points(tmp_path / "w.laz", points, metadata={"crs": WKT_UTM32})


def coloured_cloud(n: int = 600, seed: int = 3) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Points on a 12 x 12 m ground with 8-bit colour (uint8, every value 0..255 present) and a uint16 intensity."""
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(0, 12, n), rng.uniform(0, 12, n), rng.normal(0.5, 0.03, n)])
    channels = {name: np.roll(np.arange(n) % 256, shift).astype(np.uint8)
                for shift, name in enumerate(("red", "green", "blue"))}
    return points, {**channels, "intensity": rng.integers(0, 4000, n).astype(np.uint16)}


def test_cli_convert_scales_8_bit_colour_to_the_16_bits_of_las(run_cli, tmp_path):
    """PLY uchar colour (0..255) becomes LAS's 16-bit colour (x 257: 0 -> 0, 255 -> 65535); LAS colour goes to PLY
    and PCD as the uint16 it is, so LAS -> PLY -> LAS keeps it exactly."""
    points, attributes = coloured_cloud()
    write_points(tmp_path / "rgb.ply", points, attributes=attributes)
    assert run_cli("convert", str(tmp_path / "rgb.ply"), str(tmp_path / "out.las"))[0] == 0
    las = laspy.read(tmp_path / "out.las")
    for name in ("red", "green", "blue"):
        np.testing.assert_array_equal(np.asarray(las[name]), attributes[name].astype(np.uint16) * 257, err_msg=name)
    assert np.asarray(las.red).min() == 0 and np.asarray(las.red).max() == 65535
    np.testing.assert_array_equal(np.asarray(las.intensity), attributes["intensity"])  # not a colour: as it is
    for name in ("back.ply", "back.pcd"):
        assert run_cli("convert", str(tmp_path / "out.las"), str(tmp_path / name))[0] == 0
        back = read_point_cloud(tmp_path / name)
        for channel in ("red", "green", "blue"):
            assert back.attributes[channel].dtype == np.uint16
            np.testing.assert_array_equal(back.attributes[channel], np.asarray(las[channel]))
    assert run_cli("convert", str(tmp_path / "back.ply"), str(tmp_path / "again.las"))[0] == 0
    np.testing.assert_array_equal(np.asarray(laspy.read(tmp_path / "again.las").points.array),
                                  np.asarray(las.points.array))


def test_decompress_to_las_scales_a_ply_s_8_bit_colour(run_cli, tiny_model_dir, tmp_path):
    """A coloured PLY compressed and decompressed to .las holds the decoded 8-bit colour x 257, as .ply holds it
    x 1; 8-bit colour written into LAS unscaled (the former behaviour) would peak at 255."""
    import mapsqueeze

    points, attributes = coloured_cloud()
    write_points(tmp_path / "rgb.ply", points, attributes=attributes)
    mapsqueeze.compress_file(tmp_path / "rgb.ply", tmp_path / "rgb.msq", model=tiny_model_dir)
    for name in ("d.ply", "d.las"):
        code, _, err = run_cli("decompress", str(tmp_path / "rgb.msq"), "-o", str(tmp_path / name), "--model",
                               str(tiny_model_dir))
        assert code == 0 and err == ""
    ply, las = read_point_cloud(tmp_path / "d.ply"), laspy.read(tmp_path / "d.las")
    assert ply.attributes["red"].dtype == np.uint8 and ply.attributes["red"].max() > 200
    for name in ("red", "green", "blue"):
        np.testing.assert_array_equal(np.asarray(las[name]), ply.attributes[name].astype(np.uint16) * 257)
    np.testing.assert_array_equal(np.asarray(las.intensity), ply.attributes["intensity"])
