"""Point-cloud I/O: round trips of every format, precision, real files from the shared folder, typed errors, CLI."""

import os
import subprocess
import sys
from pathlib import Path

import laspy
import numpy as np
import plyfile
import pytest

from mapsqueeze.errors import InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.io import (
    FLOAT32_MAX_ERROR_M,
    LAS_SCALE_M,
    SUPPORTED_FORMATS,
    PointCloud,
    atomic_output,
    atomic_write_bytes,
    drop_zero_points,
    iter_point_clouds,
    lzf,
    read_point_cloud,
    read_points,
    validate_points,
    write_points,
)

NUSCENES_SWEEP = "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
UTM_OFFSET_M = np.array([500000.123, 4000000.456, 50.0])
LAS_ERROR_M = LAS_SCALE_M / 2 + 1e-9  # rounding to the grid, plus float64 slack at UTM magnitudes
EXTENSION = {"bin": ".bin", "pcd.bin": ".pcd.bin", "ply": ".ply", "ply-ascii": ".ply", "pcd": ".pcd",
             "pcd-ascii": ".pcd", "las": ".las", "laz": ".laz", "npy": ".npy"}


def local_cloud(num_points: int = 500, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-40.0, 40.0, (num_points, 3))


def generic_attributes(num_points: int, seed: int = 1) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "intensity": rng.integers(0, 256, num_points).astype(np.uint16),
        "ring": rng.integers(0, 64, num_points).astype(np.uint8),
        "time_s": rng.random(num_points),
    }


def attributes_for(fmt: str, num_points: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(2)
    if fmt == "bin":
        return {"reflectance": rng.random(num_points).astype(np.float32)}
    if fmt == "pcd.bin":
        return {"intensity": rng.integers(0, 256, num_points).astype(np.float32),
                "ring": rng.integers(0, 32, num_points).astype(np.uint8)}  # written as float32, read as uint8
    return generic_attributes(num_points)


def coordinate_tolerance_m(fmt: str, points: np.ndarray) -> float:
    if fmt in ("las", "laz"):
        return LAS_ERROR_M
    if fmt == "npy":
        return 0.0
    return float(np.abs(points).max()) * 2.0**-24  # float32 half-ulp; float64 PLY/PCD must be exact


def assert_single_line_naming(excinfo, path: Path) -> None:
    message = str(excinfo.value)
    assert path.name in message and "\n" not in message, message


def test_drop_zero_points_leaves_out_exactly_the_rows_at_the_origin():
    rng = np.random.default_rng(3)
    points = rng.choice([0.0, -0.0, 1.5, np.nan, -2.0], (5000, 3))
    points[:3] = [[0.0, 0.0, 0.0], [-0.0, 0.0, -0.0], [0.0, 0.0, 1e-300]]
    zero = np.array([all(value == 0 for value in row) for row in points.tolist()])
    assert zero[:2].all() and not zero[2] and 0 < zero.sum() < len(points)
    kept, n_zero = drop_zero_points(points)
    assert n_zero == zero.sum() and kept.tobytes() == points[~zero].tobytes()
    whole = np.nan_to_num(points[3:], nan=7.0)
    for dtype in (np.float32, np.int32):
        kept, n_zero = drop_zero_points(whole.astype(dtype))
        assert n_zero == zero[3:].sum() and np.array_equal(kept, whole[~zero[3:]].astype(dtype))
    nonzero = points[~zero]
    assert drop_zero_points(nonzero)[0] is nonzero and drop_zero_points(nonzero)[1] == 0
    with pytest.raises(InvalidPointCloudError, match="all 2 points lie at"):
        drop_zero_points(points[:2])
    assert len(drop_zero_points(points[:2], allow_empty=True)[0]) == 0


# ---- round trips -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", SUPPORTED_FORMATS)
def test_round_trip_local_cloud(tmp_path, fmt):
    points = local_cloud()
    attributes = attributes_for(fmt, len(points))
    path = tmp_path / f"cloud{EXTENSION[fmt]}"
    stored = write_points(path, points, format=fmt, attributes=attributes)
    assert stored == tuple(attributes)
    cloud = read_point_cloud(path, format=fmt)
    assert cloud.points.dtype == np.float64 and cloud.points.shape == points.shape
    assert np.abs(cloud.points - points).max() <= coordinate_tolerance_m(fmt, points)
    if fmt == "npy":  # attribute names are not stored in .npy: columns 3.. come back as column3, ...
        restored = {name: cloud.attributes[f"column{3 + index}"] for index, name in enumerate(attributes)}
    else:
        restored = cloud.attributes
    for name, values in attributes.items():
        np.testing.assert_array_equal(restored[name], values)
        if fmt not in ("npy", "las", "laz"):
            assert restored[name].dtype == values.dtype
    np.testing.assert_array_equal(read_points(path, format=fmt), cloud.points)


@pytest.mark.parametrize("fmt", ["ply", "ply-ascii", "pcd", "pcd-ascii", "las", "laz", "npy"])
def test_utm_coordinates_keep_precision(tmp_path, fmt):
    points = local_cloud(300) + UTM_OFFSET_M
    points[0] = UTM_OFFSET_M
    path = tmp_path / f"utm{EXTENSION[fmt]}"
    write_points(path, points, format=fmt)
    restored = read_points(path, format=fmt)
    error = np.abs(restored - points).max()
    assert error <= (LAS_ERROR_M if fmt in ("las", "laz") else 0.0), error
    assert abs(restored[0, 0] - 500000.123) <= LAS_ERROR_M


@pytest.mark.parametrize("dtype", ["<f4", ">f4", "<f8", "<f2", "<i2", "<u1", ">i4", "<u8"])
def test_npy_reads_floats_as_metres_and_refuses_integers(tmp_path, dtype):
    """A float .npy is read as metres whatever its width or byte order; an integer one (unit unknown) is refused."""
    table = np.array([[1.5, 2.0, 3.25, 7.0], [4.0, 5.5, 6.0, 8.0]], dtype=dtype)
    np.save(tmp_path / "a.npy", table)
    if np.dtype(dtype).kind == "f":
        cloud = read_point_cloud(tmp_path / "a.npy")
        assert cloud.points.dtype == np.float64
        np.testing.assert_array_equal(cloud.points, table[:, :3].astype(np.float64))
        np.testing.assert_array_equal(cloud.attributes["column3"], table[:, 3])
        return
    with pytest.raises(PointCloudFormatError, match=rf"a.npy: .npy holds {np.dtype(dtype)} integers, whose unit is "
                                                    r"unknown; x, y, z must be floats in metres"):
        read_point_cloud(tmp_path / "a.npy")


def test_ply_uses_float64_only_when_float32_would_lose_a_millimetre(tmp_path):
    write_points(tmp_path / "local.ply", local_cloud())
    write_points(tmp_path / "utm.ply", local_cloud() + UTM_OFFSET_M)
    local_types = {prop.val_dtype for prop in plyfile.PlyData.read(str(tmp_path / "local.ply"))["vertex"].properties}
    utm_types = {prop.val_dtype for prop in plyfile.PlyData.read(str(tmp_path / "utm.ply"))["vertex"].properties}
    assert local_types == {"f4"} and utm_types == {"f8"}
    assert np.abs(read_points(tmp_path / "local.ply") - local_cloud()).max() <= FLOAT32_MAX_ERROR_M


def test_las_header_uses_documented_scale_and_offset(tmp_path):
    points = local_cloud() + UTM_OFFSET_M
    write_points(tmp_path / "utm.laz", points)
    header = laspy.read(tmp_path / "utm.laz").header
    np.testing.assert_allclose(header.scales, LAS_SCALE_M)
    np.testing.assert_array_equal(header.offsets, np.floor(points.min(axis=0)))
    assert (tmp_path / "utm.laz").stat().st_size < 0.8 * write_and_size(tmp_path / "utm.las", points)


def test_las_axis_wider_than_214_km_takes_a_coarser_scale(tmp_path):
    """An axis spanning more than 2^31 steps of 0.1 mm (a 300 km corridor map) is written at 1 mm, the others at 0.1
    mm; before, the write was refused."""
    rng = np.random.default_rng(7)
    points = np.column_stack([rng.uniform(0, 300e3, 500), rng.uniform(0, 1e3, 500), rng.uniform(0, 50, 500)])
    points += UTM_OFFSET_M
    write_points(tmp_path / "corridor.las", points)
    header = laspy.read(tmp_path / "corridor.las").header
    np.testing.assert_allclose(header.scales, [1e-3, LAS_SCALE_M, LAS_SCALE_M])
    error = np.abs(read_points(tmp_path / "corridor.las") - points).max(axis=0)
    assert (error <= np.array([5e-4, 5e-5, 5e-5]) + 1e-9).all(), error


def write_and_size(path: Path, points: np.ndarray) -> int:
    write_points(path, points)
    return path.stat().st_size


@pytest.mark.parametrize("fmt", ["bin", "pcd.bin"])
def test_float32_formats_refuse_utm_coordinates_and_leave_no_file(tmp_path, fmt):
    path = tmp_path / f"scan{EXTENSION[fmt]}"
    with pytest.raises(InvalidPointCloudError, match="float32") as excinfo:
        write_points(path, local_cloud() + UTM_OFFSET_M)
    assert_single_line_naming(excinfo, path)
    assert list(tmp_path.iterdir()) == []


def test_nuscenes_ring_is_read_as_whole_laser_numbers(tmp_path, tiny_model_dir):
    """The ring column of a nuScenes sweep (float32 0..31, the laser of each point) is read as uint8, so that it is
    coded as categories and decodes to ring numbers, not to quantised medians such as 4.84375; a column with a
    fraction stays float32."""
    import mapsqueeze

    rng = np.random.default_rng(6)
    points = rng.uniform(0.5, 3.5, (600, 3))
    ring = np.floor(points[:, 2] * 8).astype(np.float32)  # 4..27, in layers as a spinning LiDAR's
    write_points(tmp_path / "sweep.pcd.bin", points, attributes={"intensity": np.full(600, 7, np.float32),
                                                                  "ring": ring})
    cloud = read_point_cloud(tmp_path / "sweep.pcd.bin")
    assert cloud.attributes["ring"].dtype == np.uint8 and cloud.attributes["intensity"].dtype == np.float32
    np.testing.assert_array_equal(cloud.attributes["ring"], ring)
    mapsqueeze.compress_file(tmp_path / "sweep.pcd.bin", tmp_path / "sweep.msq", model=tiny_model_dir)
    decoded = mapsqueeze.decompress_cloud(tmp_path / "sweep.msq", model=tiny_model_dir)
    assert set(np.unique(decoded.attributes["ring"])) <= set(ring.tolist())
    write_points(tmp_path / "half.pcd.bin", points, attributes={"ring": ring + 0.5})
    assert read_point_cloud(tmp_path / "half.pcd.bin").attributes["ring"].dtype == np.float32


def test_extension_detection_and_format_override(tmp_path):
    points = local_cloud(50)
    write_points(tmp_path / "sweep.pcd.bin", points)
    assert (tmp_path / "sweep.pcd.bin").stat().st_size == 50 * 5 * 4  # nuScenes layout, not KITTI
    assert set(read_point_cloud(tmp_path / "sweep.pcd.bin").attributes) == {"intensity", "ring"}
    write_points(tmp_path / "scan.bin", points)
    assert (tmp_path / "scan.bin").stat().st_size == 50 * 4 * 4
    write_points(tmp_path / "CLOUD.PLY", points)
    assert read_points(tmp_path / "CLOUD.PLY").shape == (50, 3)
    write_points(tmp_path / "cloud.dat", points, format="laz")
    assert np.abs(read_points(tmp_path / "cloud.dat", format=".LAZ") - points).max() <= LAS_ERROR_M


def test_write_reports_attributes_a_format_cannot_store(tmp_path):
    attributes = {"intensity": np.ones(50, np.float32), "ring": np.zeros(50, np.float32)}
    assert write_points(tmp_path / "scan.bin", local_cloud(50), attributes=attributes) == ()
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "scan.bin").attributes["reflectance"], 0.0)


def test_pcd_reads_multi_count_and_padding_fields(tmp_path):
    header = ("VERSION 0.7\nFIELDS x y z _ normal\nSIZE 4 4 4 1 4\nTYPE F F F U F\nCOUNT 1 1 1 2 3\n"
              "WIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n")
    (tmp_path / "multi.pcd").write_text(header + "1 2 3 0 0 0.1 0.2 0.3\n4 5 6 0 0 0.4 0.5 0.6\n")
    cloud = read_point_cloud(tmp_path / "multi.pcd")
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [4, 5, 6]])
    assert sorted(cloud.attributes) == ["normal_0", "normal_1", "normal_2"]
    np.testing.assert_allclose(cloud.attributes["normal_2"], [0.3, 0.6], rtol=1e-6)


def test_pcd_binary_compressed_reads_multi_count_padding_and_every_type(tmp_path, binary_compressed_pcd):
    """Each field for every point in turn, COUNT > 1 fields and padding included: the same cloud as DATA binary."""
    rng = np.random.default_rng(4)
    records = np.zeros(300, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("_", "u1", (2,)),
                                   ("normal", "<f4", (3,)), ("ring", "u1"), ("t", "<i8"), ("label", "<u4")])
    for axis in ("x", "y", "z"):
        records[axis] = rng.uniform(-50, 50, 300)
    records["_"], records["normal"] = 255, rng.normal(size=(300, 3))
    records["ring"], records["t"], records["label"] = np.arange(300) % 64, -np.arange(300) * 10**12, 7
    compressed = read_point_cloud(binary_compressed_pcd(tmp_path / "multi.pcd", records))
    header = (tmp_path / "multi.pcd").read_bytes().split(b"DATA")[0] + b"DATA binary\n"
    (tmp_path / "binary.pcd").write_bytes(header + records.tobytes())
    binary = read_point_cloud(tmp_path / "binary.pcd")
    assert list(compressed.attributes) == list(binary.attributes) == ["normal_0", "normal_1", "normal_2", "ring",
                                                                      "t", "label"]
    np.testing.assert_array_equal(compressed.points, binary.points)
    np.testing.assert_array_equal(compressed.points[:, 2], records["z"])
    for name, values in binary.attributes.items():
        assert compressed.attributes[name].dtype == values.dtype
        np.testing.assert_array_equal(compressed.attributes[name], values)
    np.testing.assert_array_equal(compressed.attributes["normal_1"], records["normal"][:, 1])
    np.testing.assert_array_equal(compressed.attributes["t"], records["t"])


def organised_pcd(path: Path, points: np.ndarray, intensity: np.ndarray, data: str, height: int = 4,
                  compressed_writer=None) -> None:
    """Write x, y, z (float32) and intensity (uint16) as an organised PCD (`height` rows) with DATA `data`, NaN rows
    as they are (write_points refuses them); binary_compressed through `compressed_writer` (the fixture)."""
    records = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<u2")])
    records["x"], records["y"], records["z"] = points.T
    records["intensity"] = intensity
    if data == "binary_compressed":
        compressed_writer(path, records, height)
        return
    if data == "binary":
        body = records.tobytes()
    else:
        body = "".join(f"{x!r} {y!r} {z!r} {i}\n" for x, y, z, i in records.tolist()).encode()  # NaN: "nan"
    header = (f"VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 2\nTYPE F F F U\nCOUNT 1 1 1 1\n"
              f"WIDTH {len(points) // height}\nHEIGHT {height}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\n"
              f"DATA {data}\n")
    path.write_bytes(header.encode() + body)


PCD_DATA = ["binary", "ascii", "binary_compressed"]


@pytest.mark.parametrize("data", PCD_DATA)
def test_pcd_points_with_nan_coordinates_are_left_out_with_their_attributes(tmp_path, data, binary_compressed_pcd):
    """Organised PCDs (PCL, ROS drivers) mark a missing return by NaN x, y, z; a NaN in one coordinate counts too."""
    points = local_cloud(400).astype(np.float32)
    intensity = np.arange(400, dtype=np.uint16)
    missing = np.zeros(400, bool)
    missing[::7] = True
    points[missing] = np.nan
    points[[5, 90], [1, 2]] = np.nan  # one NaN coordinate is enough
    missing[[5, 90]] = True
    organised_pcd(tmp_path / "scan.pcd", points, intensity, data, compressed_writer=binary_compressed_pcd)
    cloud = read_point_cloud(tmp_path / "scan.pcd")
    assert cloud.nan_points_dropped == missing.sum() == 60
    np.testing.assert_array_equal(cloud.points, points[~missing].astype(np.float64))
    np.testing.assert_array_equal(cloud.attributes["intensity"], intensity[~missing])
    np.testing.assert_array_equal(read_points(tmp_path / "scan.pcd"), cloud.points)
    assert read_point_cloud(tmp_path / "scan.pcd", attributes=False).nan_points_dropped == 60
    organised_pcd(tmp_path / "dense.pcd", points[~missing], intensity[~missing], data, height=1,
                  compressed_writer=binary_compressed_pcd)
    assert read_point_cloud(tmp_path / "dense.pcd").nan_points_dropped == 0
    chunks = list(iter_point_clouds(tmp_path / "scan.pcd", chunk_points=64))  # 340 points kept: 64 x 5 + 20
    assert [len(chunk) for chunk in chunks] == [64] * 5 + [20]
    assert [chunk.nan_points_dropped for chunk in chunks] == [60] + [0] * 5
    np.testing.assert_array_equal(np.concatenate([chunk.points for chunk in chunks]), cloud.points)
    np.testing.assert_array_equal(np.concatenate([chunk.attributes["intensity"] for chunk in chunks]),
                                  cloud.attributes["intensity"])


PCL_COLOURS = np.array([0xFFFF0000, 0xFF00FF00, 0xFF0000FF, 0xFF808040], np.uint32)  # 0xAARRGGBB, alpha 255


def pcl_rgb_records(n: int, kind: str) -> np.ndarray:
    """x, y, z and PCL's packed colour: `rgb` a float32 as pcl::PointXYZRGB writes it (alpha 255: each a NaN
    bit pattern) or `rgba` a uint32 (alpha 0..255)."""
    colours = PCL_COLOURS[np.arange(n) % len(PCL_COLOURS)]
    if kind == "rgba":
        colours = (colours & 0x00FFFFFF) | (np.arange(n, dtype=np.uint32) % 256 << 24)
    records = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), (kind, "<f4" if kind == "rgb" else "<u4")])
    records["x"], records["y"], records["z"] = local_cloud(n).T
    records[kind] = colours.view(records.dtype[kind])
    return records


def pcl_pcd(path: Path, records: np.ndarray, data: str, binary_compressed_pcd) -> Path:
    """records as a PCD with DATA `data`; ascii as PCL writes it (an `rgb` float's bits as an unsigned integer)."""
    if data == "binary_compressed":
        return binary_compressed_pcd(path, records)
    names = records.dtype.names
    kinds = [records.dtype[name] for name in names]
    header = (f"VERSION 0.7\nFIELDS {' '.join(names)}\nSIZE {' '.join(str(k.itemsize) for k in kinds)}\n"
              f"TYPE {' '.join(k.kind.upper() for k in kinds)}\nCOUNT {' '.join('1' for _ in names)}\n"
              f"WIDTH {len(records)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(records)}\nDATA {data}\n")
    if data == "binary":
        body = records.tobytes()
    else:
        colour = names[3]
        body = "".join(f"{x!r} {y!r} {z!r} {c}\n" for x, y, z, c in zip(
            records["x"].tolist(), records["y"].tolist(), records["z"].tolist(),
            records[colour].view("<u4").tolist())).encode()
    path.write_bytes(header.encode() + body)
    return path


@pytest.mark.parametrize("kind", ["rgb", "rgba"])
@pytest.mark.parametrize("data", PCD_DATA)
def test_pcd_packed_colour_reads_as_red_green_blue(tmp_path, kind, data, binary_compressed_pcd):
    """PCL's packed colour field (`rgb` float32, NaN when alpha is 255; `rgba` uint32) is read as its bytes: uint8
    red, green, blue (and alpha for rgba), not as a number (whose median and quantisation mix the channels)."""
    records = pcl_rgb_records(40, kind)
    cloud = read_point_cloud(pcl_pcd(tmp_path / "rgb.pcd", records, data, binary_compressed_pcd))
    packed = records[kind].view("<u4")
    expected = {"red": packed >> 16 & 255, "green": packed >> 8 & 255, "blue": packed & 255}
    if kind == "rgba":
        expected["alpha"] = packed >> 24
    assert list(cloud.attributes) == list(expected)
    for name, values in expected.items():
        assert cloud.attributes[name].dtype == np.uint8
        np.testing.assert_array_equal(cloud.attributes[name], values, err_msg=name)


def test_pcd_ascii_rgb_written_as_float_values_is_read_as_floats_throughout(tmp_path):
    """An ascii `rgb` column written as the floats' values (not PCL's integers) is read as floats in every row,
    including a value that happens to be whole: 1.0 is the bits 0x3F800000, not the integer 1."""
    bits = np.array([0x00FF0000, 0x3F800000, 0x000000FF, 0], dtype=np.uint32)
    floats = bits.view("<f4")
    body = "".join(f"{i} 0 0 {value!r}\n" for i, value in enumerate(floats.astype(np.float64).tolist()))
    assert "1.0" in body.split("\n")[1]
    path = tmp_path / "float_rgb.pcd"
    path.write_text("VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 4\n"
                    "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA ascii\n" + body)
    cloud = read_point_cloud(path)
    np.testing.assert_array_equal(cloud.attributes["red"], bits >> 16 & 255)
    np.testing.assert_array_equal(cloud.attributes["green"], bits >> 8 & 255)
    np.testing.assert_array_equal(cloud.attributes["blue"], bits & 255)


@pytest.mark.parametrize("alpha", [False, True])
@pytest.mark.parametrize("name", ["a.pcd", "a.pcd-ascii"])
def test_pcd_writes_uint8_colour_packed_as_pcl_does(tmp_path, name, alpha):
    """uint8 red, green, blue are written as PCL's `rgb` float32 (alpha 255, as pcl::PointXYZRGB; an unsigned integer
    in ascii, as PCL writes it), with alpha as `rgba` uint32; read back they are the same."""
    rng = np.random.default_rng(3)
    attributes = {channel: rng.integers(0, 256, 50).astype(np.uint8) for channel in ("red", "green", "blue")}
    if alpha:
        attributes["alpha"] = rng.integers(0, 256, 50).astype(np.uint8)
    path = tmp_path / name.replace("-ascii", "")
    write_points(path, local_cloud(50), attributes=attributes, format=name.split(".")[1])
    header = path.read_bytes().split(b"DATA")[0].decode()
    assert ("FIELDS x y z rgba\n" if alpha else "FIELDS x y z rgb\n") in header
    assert ("TYPE F F F U\n" if alpha else "TYPE F F F F\n") in header
    cloud = read_point_cloud(path)
    assert list(cloud.attributes) == list(attributes)
    for channel, values in attributes.items():
        np.testing.assert_array_equal(cloud.attributes[channel], values, err_msg=channel)


def test_pcl_rgb_pcd_compresses(tmp_path, tiny_model_dir):
    """A pcl::PointXYZRGB PCD (its rgb floats are NaN bit patterns) compresses, its colours decoded as uint8 red,
    green, blue from the input's colours."""
    import mapsqueeze

    records = pcl_rgb_records(600, "rgb")
    records["x"], records["y"], records["z"] = np.random.default_rng(5).uniform(0.5, 3.5, (3, 600))
    records["rgb"] = PCL_COLOURS[(records["x"] > 2).astype(int)].view("<f4")  # red and green halves
    source = pcl_pcd(tmp_path / "rgb.pcd", records, "binary", None)
    mapsqueeze.compress_file(source, tmp_path / "rgb.msq", model=tiny_model_dir, attribute_options=
                             mapsqueeze.AttributeOptions(voxel_m=0.5))
    decoded = mapsqueeze.decompress_cloud(tmp_path / "rgb.msq", model=tiny_model_dir)
    assert {name: values.dtype for name, values in decoded.attributes.items()} == dict.fromkeys(
        ("red", "green", "blue"), np.uint8)
    colours = np.column_stack([decoded.attributes[name] for name in ("red", "green", "blue")])
    assert {tuple(colour) for colour in colours.tolist()} <= {(255, 0, 0), (0, 255, 0)}


@pytest.mark.parametrize("data", PCD_DATA)
def test_pcd_infinite_or_only_nan_coordinates_are_refused(tmp_path, data, binary_compressed_pcd):
    points = local_cloud(400).astype(np.float32)
    points[::7] = np.nan
    points[[12, 30], [0, 2]] = [np.inf, -np.inf]
    organised_pcd(tmp_path / "inf.pcd", points, np.zeros(400), data, compressed_writer=binary_compressed_pcd)
    with pytest.raises(InvalidPointCloudError) as infinite:
        read_point_cloud(tmp_path / "inf.pcd")
    assert str(infinite.value) == (f"{tmp_path / 'inf.pcd'}: 2 of 400 points have infinite coordinates (the first: "
                                   "point 12, counting from 0; NaN marks a missing return in PCD, infinity does not)")
    organised_pcd(tmp_path / "nan.pcd", np.full((8, 3), np.nan, np.float32), np.zeros(8), data,
                  compressed_writer=binary_compressed_pcd)
    with pytest.raises(InvalidPointCloudError, match=r"nan.pcd: no points: all 8 points have NaN coordinates"):
        read_point_cloud(tmp_path / "nan.pcd")


def test_nan_coordinates_stay_refused_outside_pcd(tmp_path):
    """NaN marks a missing return in PCD only: a PLY, .npy or .bin with NaN is refused (see
    test_non_finite_points_are_counted_and_numbered_in_the_file_not_the_chunk for the message)."""
    points = local_cloud(50)
    points[3] = np.nan
    for name in ("a.ply", "a.npy", "a.bin"):
        write_raw(tmp_path / name, points)
        with pytest.raises(InvalidPointCloudError, match="1 of 50 points has NaN or infinite coordinates"):
            read_point_cloud(tmp_path / name)


def test_ply_vertex_list_properties_are_skipped(tmp_path):
    vertices = np.array([(1.0, 2.0, 3.0, 7, [1, 2]), (4.0, 5.0, 6.0, 8, [3])],
                        dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("label", "i4"), ("neighbours", object)])
    element = plyfile.PlyElement.describe(vertices, "vertex", val_types={"neighbours": "i4"})
    plyfile.PlyData([element], text=True).write(str(tmp_path / "lists.ply"))
    cloud = read_point_cloud(tmp_path / "lists.ply")
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [4, 5, 6]])
    assert list(cloud.attributes) == ["label"] and cloud.attributes["label"].tolist() == [7, 8]


# ---- real files --------------------------------------------------------------------------------------------------

REAL_FILES = [
    ("kitti_seq00_scans/000000.bin", 124_668, {"reflectance"}),
    (NUSCENES_SWEEP, 34_688, {"intensity", "ring"}),
    ("submaps/kitti_hdl64_6scans.ply", 101_924, set()),
    ("submaps/nuscenes_hdl32_1scan.ply", 11_777, set()),
    ("submaps/ouster_os2_128_1scan.ply", 50_194, set()),
]


@pytest.mark.parametrize(("relative", "expected_count", "expected_attributes"), REAL_FILES)
def test_real_files_read_plausibly(real_data, shared_file, relative, expected_count, expected_attributes):
    path = shared_file(real_data / relative)
    cloud = read_point_cloud(path)
    assert len(cloud) == expected_count
    assert set(cloud.attributes) == expected_attributes
    assert np.abs(cloud.points).max() < 150.0  # a LiDAR scan or a 40 m submap, in metres around the sensor
    if relative.startswith("submaps/"):
        extent = cloud.points.max(axis=0) - cloud.points.min(axis=0)
        assert np.all(extent[:2] > 30.0) and np.all(extent[:2] <= 40.0 + 1e-3) and extent[2] <= 15.0 + 1e-3
    if "reflectance" in cloud.attributes:
        assert 0.0 <= cloud.attributes["reflectance"].min() and cloud.attributes["reflectance"].max() <= 1.0
    if "ring" in cloud.attributes:
        assert set(np.unique(cloud.attributes["ring"])) <= set(range(32))


# ---- bad input -------------------------------------------------------------------------------------------------

def write_ply_vertices(path: Path, vertices: np.ndarray, element: str = "vertex") -> None:
    plyfile.PlyData([plyfile.PlyElement.describe(vertices, element)]).write(str(path))


def pcd_text(points: int, width: int, data: str, body: bytes) -> bytes:
    header = (f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {width}\nHEIGHT 1\n"
              f"POINTS {points}\nDATA {data}\n")
    return header.encode() + body


def lzf_body(stream: bytes, uncompressed: int, compressed: int | None = None) -> bytes:
    """A binary_compressed body: the sizes (compressed: len(stream) unless given), then the LZF stream."""
    compressed = len(stream) if compressed is None else compressed
    return compressed.to_bytes(4, "little") + uncompressed.to_bytes(4, "little") + stream


def make_bad_file(tmp_path: Path, case: str) -> Path:
    """Create the bad input `case`; returns its path."""
    xyz = local_cloud(10).astype(np.float32)
    if case == "missing":
        return tmp_path / "missing.ply"
    if case == "directory":
        (tmp_path / "folder.ply").mkdir()
        return tmp_path / "folder.ply"
    files = {
        "unknown extension": ("cloud.xyz", b"1 2 3\n"),
        "bin size not a multiple of 16": ("scan.bin", np.zeros(10, "<f4").tobytes() + b"\0\0"),
        "pcd.bin size not a multiple of 20": ("sweep.pcd.bin", np.zeros(12, "<f4").tobytes()),
        "empty bin": ("empty.bin", b""),
        "nan in bin": ("nan.bin", np.array([[1, 2, 3, 0], [np.nan, 2, 3, 0]], "<f4").tobytes()),
        "inf in npy": ("inf.npy", None),
        "npy with two columns": ("two.npy", None),
        "npy of objects": ("objects.npy", None),
        "npy of integers": ("ints.npy", None),
        "absurd coordinates in npy": ("far.npy", None),
        "ply garbage": ("garbage.ply", b"not a ply file at all\n"),
        "pcd garbage": ("garbage.pcd", bytes(range(128, 256)) + b"\n"),
        "pcd more points than data": ("short.pcd", pcd_text(12, 12, "binary", xyz.tobytes())),
        "pcd fewer points than data": ("long.pcd", pcd_text(8, 8, "binary", xyz.tobytes())),
        "pcd width disagrees with points": ("wh.pcd", pcd_text(10, 9, "binary", xyz.tobytes())),
        "pcd ascii more points than rows": ("rows.pcd", pcd_text(11, 11, "ascii", b"1 2 3\n" * 10)),
        "pcd ascii wrong column count": ("cols.pcd", pcd_text(2, 2, "ascii", b"1 2 3 4\n5 6 7 8\n")),
        "pcd binary_compressed without its sizes": ("lzf.pcd", pcd_text(10, 10, "binary_compressed", b"\0" * 7)),
        "pcd binary_compressed uncompressed size not points x point size":
            ("lzf.pcd", pcd_text(10, 10, "binary_compressed", lzf_body(b"\x1f" + bytes(32), 32))),
        "pcd binary_compressed compressed size beyond the file":
            ("lzf.pcd", pcd_text(10, 10, "binary_compressed", lzf_body(b"\x1f" + bytes(32), 120, 34))),
        "pcd binary_compressed block beyond LZF's expansion":
            ("lzf.pcd", pcd_text(300_000_000, 300_000_000, "binary_compressed", lzf_body(b"\0\0", 3_600_000_000))),
        "pcd binary_compressed back-reference before the start":
            ("lzf.pcd", pcd_text(10, 10, "binary_compressed", lzf_body(b"\x20\x00", 120))),
        "pcd binary_compressed stream shorter than its size":
            ("lzf.pcd", pcd_text(10, 10, "binary_compressed", lzf_body(b"\x1f" + bytes(32), 120))),
        "pcd without z": ("noz.pcd", b"FIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n"),
        "las garbage": ("garbage.las", b"LASF" + bytes(100)),
    }
    name, content = files[case]
    path = tmp_path / name
    if case == "inf in npy":
        np.save(path, np.array([[1.0, 2.0, np.inf]]))
    elif case == "npy with two columns":
        np.save(path, np.ones((5, 2)))
    elif case == "npy of objects":
        np.save(path, np.array([[1, "a", None]], dtype=object), allow_pickle=True)
    elif case == "npy of integers":
        np.save(path, np.array([[120, 45, 3], [121, 45, 3]], dtype=np.int32))
    elif case == "absurd coordinates in npy":
        np.save(path, np.array([[1.0, 2.0, 3.0], [2e7, 0.0, 0.0]]))
    else:
        path.write_bytes(content)
    return path


BAD_INPUTS = {
    "missing": PointCloudFormatError,
    "directory": PointCloudFormatError,
    "unknown extension": PointCloudFormatError,
    "bin size not a multiple of 16": PointCloudFormatError,
    "pcd.bin size not a multiple of 20": PointCloudFormatError,
    "empty bin": InvalidPointCloudError,
    "nan in bin": InvalidPointCloudError,
    "inf in npy": InvalidPointCloudError,
    "npy with two columns": PointCloudFormatError,
    "npy of objects": PointCloudFormatError,
    "npy of integers": PointCloudFormatError,
    "absurd coordinates in npy": InvalidPointCloudError,
    "ply garbage": PointCloudFormatError,
    "pcd garbage": PointCloudFormatError,
    "pcd more points than data": PointCloudFormatError,
    "pcd fewer points than data": PointCloudFormatError,
    "pcd width disagrees with points": PointCloudFormatError,
    "pcd ascii more points than rows": PointCloudFormatError,
    "pcd ascii wrong column count": PointCloudFormatError,
    "pcd binary_compressed without its sizes": PointCloudFormatError,
    "pcd binary_compressed uncompressed size not points x point size": PointCloudFormatError,
    "pcd binary_compressed compressed size beyond the file": PointCloudFormatError,
    "pcd binary_compressed block beyond LZF's expansion": PointCloudFormatError,
    "pcd binary_compressed back-reference before the start": PointCloudFormatError,
    "pcd binary_compressed stream shorter than its size": PointCloudFormatError,
    "pcd without z": PointCloudFormatError,
    "las garbage": PointCloudFormatError,
}


@pytest.mark.parametrize(("case", "error"), BAD_INPUTS.items(), ids=list(BAD_INPUTS))
def test_bad_input_raises_typed_error_naming_the_file(tmp_path, case, error):
    path = make_bad_file(tmp_path, case)
    with pytest.raises(error) as excinfo:
        read_points(path)
    assert_single_line_naming(excinfo, path)


def test_pcd_binary_compressed_errors_say_what_is_wrong(tmp_path):
    expected = {
        "pcd binary_compressed without its sizes": "PCD binary_compressed data ends before its sizes (truncated?)",
        "pcd binary_compressed uncompressed size not points x point size":
            "PCD header declares 10 points of 12 bytes (120 bytes), the binary_compressed data says 32 bytes "
            "uncompressed",
        "pcd binary_compressed compressed size beyond the file":
            "PCD binary_compressed data declares 34 compressed bytes, the file holds 33 after the header (truncated?)",
        "pcd binary_compressed block beyond LZF's expansion":
            "PCD binary_compressed data declares 3,600,000,000 bytes uncompressed from 2 compressed, more than LZF "
            "can expand to (88x)",
        "pcd binary_compressed back-reference before the start":
            "corrupt PCD binary_compressed data (LZF: a back-reference at byte 0 points 1 bytes back from output "
            "byte 0, before the start)",
        "pcd binary_compressed stream shorter than its size":
            "corrupt PCD binary_compressed data (LZF: the stream decompresses to 32 bytes, 120 expected)",
    }
    for case, message in expected.items():
        path = make_bad_file(tmp_path, case)
        with pytest.raises(PointCloudFormatError) as excinfo:
            read_points(path)
        assert str(excinfo.value) == f"{path}: {message}"


@pytest.mark.parametrize("compiled", [False, True], ids=["python", "compiled"])
def test_lzf_decompress_literals_references_and_overlapping_copies(lzf_compress, compiled):
    cases = [
        (b"\x02abc\x20\x02", b"abcabc"),  # a 3-byte reference 3 back
        (b"\x01ab\x60\x01", b"ab" + b"ababa"),  # 5 bytes from 2 back: overlapping, the pattern repeated
        (b"\x00a\xe0\x01\x00", b"a" * 11),  # length field 7 + extra byte 1 + 2 = 10, 1 back
        (b"\x00z\xe0\xff\x00", b"z" * 265),  # the longest reference, 264 bytes
        (b"\x1f" + bytes(range(32)) + b"\x20\x1f", bytes(range(32)) + bytes(range(3))),  # 32 back
        (b"", b""),
    ]
    for stream, expected in cases:
        assert bytes(lzf.decompress(stream, len(expected), compiled)) == expected
    far = bytes(range(256)) * 32  # 8,192 bytes, then 3 of them again from the farthest offset
    assert bytes(lzf.decompress(b"".join(b"\x1f" + far[i : i + 32] for i in range(0, 8192, 32)) + b"\x3f\xff",
                                8195, compiled)) == far + far[:3]
    rng = np.random.default_rng(5)
    for data in (bytes(1000), rng.integers(0, 4, 5000, dtype=np.uint8).tobytes(),
                 rng.normal(size=3000).astype("<f4").tobytes(), b"abc" * 700 + bytes(range(256))):
        assert bytes(lzf.decompress(lzf_compress(data), len(data), compiled)) == data
    assert len(lzf_compress(bytes(1000))) == 14  # 1 literal, 3 references of 264 + 1 of 207: references are made


@pytest.mark.parametrize(("stream", "size", "message"), [
    (b"\x20\x00", 3, "a back-reference at byte 0 points 1 bytes back from output byte 0, before the start"),
    (b"\x00a\x40\x01", 5, "a back-reference at byte 2 points 2 bytes back from output byte 1, before the start"),
    (b"\x05ab", 6, "a literal run of 6 bytes at byte 0 runs past the end of the 3-byte stream"),
    (b"\x00a\x20", 4, "a back-reference at byte 2 runs past the end of the 3-byte stream"),
    (b"\x00a\xe0\x01", 11, "a back-reference at byte 2 runs past the end of the 4-byte stream"),
    (b"\x02abc", 2, "the stream decompresses to more than the 2 bytes expected"),
    (b"\x00a\xe0\x01\x00", 10, "the stream decompresses to more than the 10 bytes expected"),
    (b"\x02abc", 4, "the stream decompresses to 3 bytes, 4 expected"),
])
@pytest.mark.parametrize("compiled", [False, True], ids=["python", "compiled"])
def test_lzf_decompress_refuses_corrupt_streams_without_overrunning(stream, size, message, compiled):
    with pytest.raises(lzf.LZFError) as excinfo:
        lzf.decompress(stream, size, compiled)
    assert str(excinfo.value) == message


def test_lzf_decompress_takes_the_compiled_kernel_for_large_blocks(lzf_compress, monkeypatch):
    """Blocks of COMPILED_BYTES or more go to the compiled kernel (the same bytes), smaller ones stay in Python."""
    import sys

    data = np.random.default_rng(6).integers(0, 3, 4000, dtype=np.uint8).tobytes()
    stream = lzf_compress(data)
    monkeypatch.delitem(sys.modules, "mapsqueeze.io.lzfcompiled", raising=False)
    monkeypatch.setattr(lzf, "COMPILED_BYTES", len(data) + 1)
    assert bytes(lzf.decompress(stream, len(data))) == data and "mapsqueeze.io.lzfcompiled" not in sys.modules
    monkeypatch.setattr(lzf, "COMPILED_BYTES", len(data))
    assert bytes(lzf.decompress(stream, len(data))) == data and "mapsqueeze.io.lzfcompiled" in sys.modules


def test_ply_without_xyz_or_vertex_element(tmp_path):
    write_ply_vertices(tmp_path / "noz.ply", np.zeros(4, dtype=[("x", "f4"), ("y", "f4"), ("w", "f4")]))
    with pytest.raises(PointCloudFormatError, match="no z property"):
        read_points(tmp_path / "noz.ply")
    write_ply_vertices(tmp_path / "faces.ply", np.zeros(4, dtype=[("x", "f4")]), element="face")
    with pytest.raises(PointCloudFormatError, match="no vertex element"):
        read_points(tmp_path / "faces.ply")


@pytest.mark.parametrize("fmt", ["ply", "las", "laz", "npy"])
def test_truncated_files_raise_format_error(tmp_path, fmt):
    path = tmp_path / f"cloud{EXTENSION[fmt]}"
    write_points(path, local_cloud(200))
    data = path.read_bytes()
    # LAS is cut at a record boundary (20 bytes per point): only the header's point count can reveal it
    path.write_bytes(data[: len(data) - (200 if fmt == "las" else len(data) // 3)])
    with pytest.raises(PointCloudFormatError) as excinfo:
        read_points(path)
    assert_single_line_naming(excinfo, path)


def test_unknown_format_name(tmp_path):
    with pytest.raises(PointCloudFormatError, match="unknown point-cloud format 'xyz'"):
        write_points(tmp_path / "cloud.ply", local_cloud(), format="xyz")


# ---- validation and writing ------------------------------------------------------------------------------------

def test_validate_points_returns_float64_and_rejects_bad_clouds():
    checked = validate_points(np.arange(12, dtype=np.int32).reshape(4, 3))
    assert checked.dtype == np.float64 and checked.flags.c_contiguous and checked[3, 2] == 11.0
    bad = {
        "shape": np.zeros((5, 4)),
        "empty": np.zeros((0, 3)),
        "NaN": np.array([[0.0, np.nan, 0.0]]),
        "infinite": np.array([[0.0, 0.0, -np.inf]]),
        "absurd": np.array([[0.0, 0.0, 1e7]]),
        "dtype": np.array([["a", "b", "c"]]),
    }
    for label, points in bad.items():
        with pytest.raises(InvalidPointCloudError, match=r"^my cloud: ") as excinfo:
            validate_points(points, name="my cloud")
        assert "\n" not in str(excinfo.value), label


@pytest.mark.parametrize(
    ("attributes", "message"),
    [
        ({"intensity": np.zeros(3)}, "shape"),
        ({"x": np.zeros(10)}, "bad attribute name"),
        ({"my name": np.zeros(10)}, "bad attribute name"),
        ({"label": np.array(["a"] * 10)}, "not numeric"),
    ],
)
def test_write_rejects_bad_attributes(tmp_path, attributes, message):
    with pytest.raises(InvalidPointCloudError, match=message):
        write_points(tmp_path / "cloud.ply", local_cloud(10), attributes=attributes)
    assert list(tmp_path.iterdir()) == []


def test_las_refuses_clashing_attributes(tmp_path):
    with pytest.raises(InvalidPointCloudError, match="'intensity_float64', the extra dimension that would hold it"):
        write_points(tmp_path / "cloud.las", local_cloud(10),
                     attributes={"intensity": np.full(10, 0.5), "intensity_float64": np.ones(10)})
    with pytest.raises(InvalidPointCloudError, match="clashes with a standard LAS field"):
        write_points(tmp_path / "cloud.las", local_cloud(10), attributes={"Classification": np.ones(10, np.uint8)})
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    path = tmp_path / "scan.bin"
    write_points(path, local_cloud(20))
    before = path.read_bytes()
    with pytest.raises(InvalidPointCloudError):
        write_points(path, local_cloud(20) + UTM_OFFSET_M)
    assert path.read_bytes() == before and list(tmp_path.iterdir()) == [path]


def test_write_into_missing_directory_or_onto_a_directory(tmp_path):
    with pytest.raises(PointCloudFormatError, match="cannot write") as excinfo:
        write_points(tmp_path / "absent" / "cloud.ply", local_cloud())
    assert_single_line_naming(excinfo, tmp_path / "absent" / "cloud.ply")
    (tmp_path / "folder.ply").mkdir()
    with pytest.raises(PointCloudFormatError, match="folder.ply: is a directory, not a point-cloud file"):
        write_points(tmp_path / "folder.ply", local_cloud())
    assert [entry.name for entry in tmp_path.iterdir()] == ["folder.ply"]


def test_atomic_helpers(tmp_path):
    target = tmp_path / "out.msq"
    atomic_write_bytes(target, b"first")
    umask = os.umask(0)
    os.umask(umask)
    assert target.read_bytes() == b"first" and target.stat().st_mode & 0o777 == 0o666 & ~umask
    with pytest.raises(RuntimeError):
        with atomic_output(target) as temp:
            assert temp.parent == tmp_path and temp != target
            temp.write_bytes(b"half")
            raise RuntimeError("writer failed")
    assert target.read_bytes() == b"first" and list(tmp_path.iterdir()) == [target]


def test_point_cloud_dataclass():
    cloud = PointCloud(np.zeros((4, 3)))
    assert len(cloud) == 4 and cloud.attributes == {}


# ---- CLI -------------------------------------------------------------------------------------------------------

MAPSQUEEZE = Path(sys.executable).parent / "mapsqueeze"


def run_cli(*args: str) -> subprocess.CompletedProcess:
    if not MAPSQUEEZE.exists():
        pytest.skip(f"{MAPSQUEEZE} not installed")
    return subprocess.run([str(MAPSQUEEZE), *args], capture_output=True, text=True, timeout=120)


@pytest.mark.slow
def test_cli_convert(tmp_path):
    source, target = tmp_path / "scan.bin", tmp_path / "scan.laz"
    write_points(source, local_cloud(321), attributes={"reflectance": np.full(321, 0.25, np.float32)})
    result = run_cli("convert", str(source), str(target))
    assert result.returncode == 0, result.stderr
    assert "321 points" in result.stdout
    assert np.abs(read_points(target) - read_points(source)).max() <= LAS_ERROR_M
    missing = run_cli("convert", str(tmp_path / "absent.ply"), str(tmp_path / "out.ply"))
    assert missing.returncode == 2
    assert missing.stderr.startswith("error: ") and missing.stderr.count("\n") == 1
    assert "absent.ply" in missing.stderr and not (tmp_path / "out.ply").exists()


# --- chunked reading ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["a.ply", "a.npy", "a.las", "a.laz", "a.bin", "a.pcd.bin", "a.pcd"])
def test_iter_points_chunks_concatenate_to_read_points(tmp_path, name):
    from mapsqueeze.io import iter_points

    rng = np.random.default_rng(11)
    points = rng.uniform(-50, 50, (5003, 3))
    write_points(tmp_path / name, points)
    chunks = list(iter_points(tmp_path / name, chunk_points=1000))
    bound = 5003 if name.endswith(".pcd") else 1000  # PCD is read whole (one chunk)
    assert all(len(chunk) <= bound and chunk.dtype == np.float64 for chunk in chunks)
    np.testing.assert_array_equal(np.concatenate(chunks), read_points(tmp_path / name))


def test_iter_points_reports_bad_files(tmp_path):
    from mapsqueeze.io import iter_points

    (tmp_path / "cut.bin").write_bytes(np.zeros(4 * 4 * 10 + 3, dtype=np.uint8).tobytes())
    with pytest.raises(PointCloudFormatError, match="not a multiple"):
        list(iter_points(tmp_path / "cut.bin"))
    (tmp_path / "empty.bin").write_bytes(b"")
    with pytest.raises(InvalidPointCloudError, match="empty"):
        list(iter_points(tmp_path / "empty.bin"))
    write_points(tmp_path / "a.las", np.random.default_rng(0).random((3000, 3)))
    data = (tmp_path / "a.las").read_bytes()
    (tmp_path / "cut.las").write_bytes(data[: len(data) - 2000])
    with pytest.raises(PointCloudFormatError):
        list(iter_points(tmp_path / "cut.las", chunk_points=500))
    with pytest.raises(PointCloudFormatError, match="no such file"):
        list(iter_points(tmp_path / "missing.ply"))


def write_raw(path: Path, points: np.ndarray) -> None:
    """Write points as they are (NaN included: write_points refuses them) as a binary PLY, .npy, .bin or .pcd.bin."""
    if path.suffix == ".ply":
        vertices = np.empty(len(points), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
        vertices["x"], vertices["y"], vertices["z"] = points.T
        plyfile.PlyData([plyfile.PlyElement.describe(vertices, "vertex")]).write(str(path))
    elif path.suffix == ".npy":
        np.save(path, points)
    else:
        columns = 5 if path.name.endswith(".pcd.bin") else 4
        np.column_stack([points, np.zeros((len(points), columns - 3))]).astype("<f4").tofile(path)


@pytest.mark.parametrize("name", ["a.ply", "a.npy", "a.bin", "a.pcd.bin"])
def test_non_finite_points_are_counted_and_numbered_in_the_file_not_the_chunk(tmp_path, name):
    from mapsqueeze.io import iter_points

    points = local_cloud(1000)
    points[[250, 262, 940], [0, 2, 1]] = [np.nan, np.inf, np.nan]
    write_raw(tmp_path / name, points)
    path = tmp_path / name
    with pytest.raises(InvalidPointCloudError) as whole:
        read_points(path)
    assert str(whole.value) == f"{path}: 3 of 1,000 points have NaN or infinite coordinates (the first: point 250, " \
                               "counting from 0)"
    with pytest.raises(InvalidPointCloudError) as chunked:
        list(iter_points(path, chunk_points=100))
    assert str(chunked.value) == (f"{path}: 2 of points 200 to 299 (of 1,000) have NaN or infinite coordinates (the "
                                  "first: point 250, counting from 0; points from 300 on are not checked)")
    points[[250, 262]] = 0.0
    write_raw(path, points)
    with pytest.raises(InvalidPointCloudError) as last:
        list(iter_points(path, chunk_points=300))
    assert str(last.value) == (f"{path}: 1 of points 900 to 999 (of 1,000) has NaN or infinite coordinates (the "
                               "first: point 940, counting from 0)")


def test_chunks_written_are_numbered_in_the_output(tmp_path):
    from mapsqueeze.io import write_point_chunks

    bad = local_cloud(50)
    bad[7, 1] = np.nan
    with pytest.raises(InvalidPointCloudError) as excinfo:
        write_point_chunks(tmp_path / "out.las", lambda: [local_cloud(100), bad])
    assert str(excinfo.value) == (f"points for {tmp_path / 'out.las'}: 1 of points 100 to 149 has NaN or infinite "
                                  "coordinates (the first: point 107, counting from 0; any later points are not "
                                  "checked)")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name, offset", [("a.ply", 0.0), ("a.ply", UTM_OFFSET_M), ("a.bin", 0.0), ("a.npy", 0.0)])
def test_iter_points_reports_a_file_cut_while_it_is_read(tmp_path, name, offset):
    from mapsqueeze.io import iter_points

    points = offset + np.random.default_rng(13).uniform(-50, 50, (5000, 3))  # UTM: a float64 PLY
    write_points(tmp_path / name, points)
    np.testing.assert_array_equal(np.concatenate(list(iter_points(tmp_path / name, chunk_points=1000))),
                                  read_points(tmp_path / name))
    size = (tmp_path / name).stat().st_size
    chunks = iter_points(tmp_path / name, chunk_points=1000)
    next(chunks)
    os.truncate(tmp_path / name, size // 2)
    with pytest.raises(PointCloudFormatError, match="cannot read"):
        list(chunks)


@pytest.mark.parametrize("name", ["a.ply", "a.npy", "a.las", "a.laz", "a.pcd", "a.ply-ascii"])
def test_write_point_chunks_matches_write_points(tmp_path, name):
    from mapsqueeze.io import write_point_chunks

    points = UTM_OFFSET_M + np.random.default_rng(12).uniform(0, 100, (4001, 3))
    format = "ply-ascii" if name.endswith("ply-ascii") else None
    path = tmp_path / name.replace(".ply-ascii", ".ply")
    n = write_point_chunks(path, lambda: (points[i:i + 700] for i in range(0, len(points), 700)), format=format)
    write_points(tmp_path / ("ref_" + path.name), points, format=format)
    assert n == len(points)
    np.testing.assert_array_equal(read_points(path), read_points(tmp_path / ("ref_" + path.name)))


def test_write_point_chunks_refuses_lossy_float32_and_leaves_no_file(tmp_path):
    from mapsqueeze.io import write_point_chunks

    points = UTM_OFFSET_M + np.zeros((10, 3))
    with pytest.raises(InvalidPointCloudError, match="float32"):
        write_point_chunks(tmp_path / "a.bin", lambda: iter([points]))
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InvalidPointCloudError, match="empty"):
        write_point_chunks(tmp_path / "a.ply", lambda: iter([]))


def _resident_bytes_of(path: Path) -> int:
    """Resident bytes of this process's mappings of `path` (/proc/self/smaps)."""
    resident, inside = 0, False
    with open("/proc/self/smaps") as smaps:
        for line in smaps:
            fields = line.split()
            if fields and "-" in fields[0] and len(fields) >= 5:  # a mapping's header line
                inside = len(fields) >= 6 and fields[-1] == str(path)
            elif inside and fields[0] == "Rss:":
                resident += int(fields[1]) * 1024
    return resident


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps"), reason="needs Linux's /proc/self/smaps")
@pytest.mark.parametrize("fmt", ["ply", "bin", "npy"])
def test_chunked_reading_keeps_one_chunk_of_a_file_resident(tmp_path, fmt):
    from mapsqueeze.io import iter_point_clouds

    path = (tmp_path / f"big{EXTENSION[fmt]}").resolve()
    points = local_cloud(400_000, seed=3)
    write_points(path, points, format=fmt)
    chunk_points = 10_000
    file_bytes = path.stat().st_size
    peak, total = 0, 0
    for chunk in iter_point_clouds(path, chunk_points=chunk_points):
        total += len(chunk)
        peak = max(peak, _resident_bytes_of(path))
    assert total == len(points)
    # one chunk's rows (at most 8 float64 columns) and two pages, against ~5-10 MB for the whole file
    assert peak <= chunk_points * 64 + 8192 < file_bytes / 4, (peak, file_bytes)
