"""Attribute coding in the .msq container: round trips of LAZ/PCD/PLY files with every field, quality, integrity."""

import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import laspy
import numpy as np
import pytest
from pykdtree.kdtree import KDTree

import mapsqueeze
from mapsqueeze.codec.attributes import parse_selection
from mapsqueeze.codec.compress import AttributeOptions
from mapsqueeze.codec.entropy import ByteReader
from mapsqueeze.errors import ContainerError, InvalidPointCloudError
from mapsqueeze.io import read_point_cloud, write_points

UTM = np.array([500000.0, 4000000.0, 40.0])


def street(n_ground: int = 24000, n_wall: int = 8000, seed: int = 0):
    """A ground plane and a wall (UTM); intensity brighter on one half of the road and on the wall, noisy;
    classification 2 (ground) / 6 (building); a laser number per point."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(0, 36, n_ground), rng.uniform(0, 36, n_ground),
                              rng.normal(0, 0.02, n_ground)])
    wall = np.column_stack([rng.uniform(0, 36, n_wall), 30 + rng.normal(0, 0.02, n_wall), rng.uniform(0, 8, n_wall)])
    points = np.concatenate([ground, wall]) + UTM
    intensity = np.concatenate([np.where(ground[:, 0] > 18, 150.0, 40.0), np.full(n_wall, 220.0)])
    intensity = np.clip(intensity + rng.normal(0, 8, len(points)), 0, 255).astype(np.uint16)
    classification = np.concatenate([np.full(n_ground, 2), np.full(n_wall, 6)]).astype(np.uint8)
    laser = (np.concatenate([ground[:, 0], wall[:, 2]]) // 3).astype(np.uint8)
    return points, intensity, classification, laser


def nearest_original(original: np.ndarray, decoded: np.ndarray) -> np.ndarray:
    return KDTree(original).query(decoded, k=1)[1].astype(np.int64)


def assert_quality(original_points, decoded_points, original, decoded, continuous=(), categorical=()):
    nearest = nearest_original(original_points, decoded_points)
    for name in continuous:
        truth = original[name][nearest].astype(np.float64)
        error = np.abs(decoded[name].astype(np.float64) - truth).mean()
        constant = np.abs(np.median(original[name]) - truth).mean()
        assert error <= 0.6 * constant, (name, error, constant)
    for name in categorical:
        accuracy = (decoded[name] == original[name][nearest]).mean()
        assert accuracy >= 0.95, (name, accuracy)


def strip_attribute_section(data: bytes, plain_length: int) -> bytes:
    """The file without its attribute section: flags cleared (and the header CRC, which covers them, redone;
    version 7: the one-byte flags varint at byte 6, the CRC after the header and the table)."""
    out = bytearray(data[:plain_length])
    out[6] = 0
    lengths = ByteReader(bytes(out[7:27]), "preamble")
    body, table = lengths.varint(), lengths.varint()
    end = 7 + 20 - lengths.remaining + body + table
    struct.pack_into("<I", out, end, zlib.crc32(bytes(out[:end])))
    return bytes(out)


def test_files_without_attributes_are_byte_identical_and_attributes_follow_the_geometry():
    points, intensity, classification, _ = street(6000, 2000)
    plain = mapsqueeze.compress(points)
    assert plain[4:7] == bytes([7, 0, 0])  # version 7, flags 0
    assert mapsqueeze.compress(points, attributes={"intensity": intensity},
                               attribute_options=AttributeOptions("none")) == plain
    with_attributes = mapsqueeze.compress(points, attributes={"intensity": intensity, "cls": classification})
    assert with_attributes[6] == 1
    assert strip_attribute_section(with_attributes, len(plain)) == plain
    np.testing.assert_array_equal(mapsqueeze.decompress(with_attributes), mapsqueeze.decompress(plain))
    assert mapsqueeze.info(plain).attribute_schema is None


def test_laz_with_intensity_and_crs_round_trips_with_every_field(tmp_path):
    from test_io_attributes import geokey_vlr

    points, intensity, classification, laser = street()
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = np.full(3, 0.001), UTM
    header.vlrs.append(geokey_vlr(25832))
    header.add_extra_dims([laspy.ExtraBytesParams("laser", np.uint8, "laser number")])
    las = laspy.LasData(header)
    las.x, las.y, las.z = points.T
    las.intensity, las.classification, las.laser = intensity, classification, laser
    las.gps_time = np.linspace(0, 100, len(points))
    las.write(str(tmp_path / "map.laz"))
    mapsqueeze.compress_file(tmp_path / "map.laz", tmp_path / "map.msq")
    mapsqueeze.decompress_file(tmp_path / "map.msq", tmp_path / "out.laz")
    original, decoded = read_point_cloud(tmp_path / "map.laz"), read_point_cloud(tmp_path / "out.laz")
    assert set(decoded.attributes) == set(original.attributes)
    for name, values in original.attributes.items():
        assert decoded.attributes[name].dtype == values.dtype, name
    assert decoded.metadata["crs"] == "EPSG:25832"
    out = laspy.read(tmp_path / "out.laz").header
    assert out.point_format.id == 6 and list(out.scales) == [0.001] * 3 and list(out.offsets) == list(UTM)
    assert any(vlr.record_id == 34735 for vlr in out.vlrs)
    assert_quality(original.points, decoded.points, original.attributes, decoded.attributes,
                   continuous=("intensity", "gps_time"), categorical=("classification", "laser"))


def test_binary_pcd_with_intensity_round_trips(tmp_path):
    points, intensity, _, _ = street()
    local = points - UTM
    write_points(tmp_path / "map.pcd", local, attributes={"intensity": intensity.astype(np.float32)})
    mapsqueeze.compress_file(tmp_path / "map.pcd", tmp_path / "map.msq")
    mapsqueeze.decompress_file(tmp_path / "map.msq", tmp_path / "out.pcd")
    assert b"DATA binary" in (tmp_path / "out.pcd").read_bytes()[:400]
    decoded = read_point_cloud(tmp_path / "out.pcd")
    assert decoded.attributes["intensity"].dtype == np.float32
    assert_quality(local, decoded.points, {"intensity": intensity.astype(np.float32)}, decoded.attributes,
                   continuous=("intensity",))


def test_ply_with_extra_fields_round_trips_and_chunked_compression_matches(tmp_path):
    points, intensity, classification, laser = street()
    attributes = {"intensity": intensity.astype(np.float32), "label": classification.astype(np.int32),
                  "laser_number": laser, "red": (intensity // 2).astype(np.uint8)}
    write_points(tmp_path / "map.ply", points, attributes=attributes)
    mapsqueeze.compress_file(tmp_path / "map.ply", tmp_path / "map.msq")
    data = (tmp_path / "map.msq").read_bytes()
    cloud = read_point_cloud(tmp_path / "map.ply")
    assert data == mapsqueeze.compress(cloud.points, attributes=cloud.attributes)
    mapsqueeze.decompress_file(tmp_path / "map.msq", tmp_path / "out.ply")
    decoded = read_point_cloud(tmp_path / "out.ply")
    assert {name: values.dtype for name, values in decoded.attributes.items()} == \
        {name: values.dtype for name, values in attributes.items()}
    assert_quality(points, decoded.points, attributes, decoded.attributes, continuous=("intensity", "red"),
                   categorical=("label", "laser_number"))


def test_selection_bbox_density_and_info():
    points, intensity, classification, _ = street(8000, 3000)
    attributes = {"intensity": intensity, "classification": classification}
    data = mapsqueeze.compress(points, attributes=attributes, metadata={"crs": "EPSG:32632"},
                               attribute_options=AttributeOptions("classification", voxel_m=1.0))
    summary = mapsqueeze.info(data)
    assert summary.attributes == ("classification",) and summary.metadata == {"crs": "EPSG:32632"}
    assert "voxel 1 m" in summary.attribute_summary() and summary.attribute_bytes > 0
    box = (*(UTM + [0, 0, -1]), *(UTM + [18, 36, 10]))
    cropped = mapsqueeze.decompress_cloud(data, bbox=box)
    assert len(cropped.points) == len(cropped.attributes["classification"]) > 0
    assert (cropped.points[:, 0] <= UTM[0] + 18).all()
    dense = mapsqueeze.decompress_cloud(data, n_points=20000)
    assert len(dense.attributes["classification"]) == len(dense.points) == 20000
    metadata_only = mapsqueeze.compress(points, attributes=attributes, metadata={"crs": "EPSG:32632"},
                                        attribute_options=AttributeOptions("none"))
    assert mapsqueeze.info(metadata_only).attributes == () and mapsqueeze.decompress_cloud(metadata_only).metadata
    with pytest.raises(InvalidPointCloudError, match="no attribute nope"):
        parse_selection("intensity,nope", ["intensity"])
    for selection in (",", "intensity,", ["intensity", ""]):
        with pytest.raises(InvalidPointCloudError, match="has an empty name"):
            parse_selection(selection, ["intensity"])
    with pytest.raises(InvalidPointCloudError, match="attribute voxel"):
        mapsqueeze.compress(points, attributes=attributes, attribute_options=AttributeOptions(voxel_m=0.0))


def test_corrupt_or_truncated_attribute_sections_are_detected():
    points, intensity, classification, _ = street(3000, 1000)
    plain_length = len(mapsqueeze.compress(points))
    data = mapsqueeze.compress(points, attributes={"intensity": intensity, "classification": classification})
    for position in list(range(plain_length, len(data), max(1, (len(data) - plain_length) // 60))) + [len(data) - 1]:
        corrupt = bytearray(data)
        corrupt[position] ^= 0x40
        with pytest.raises(ContainerError):
            mapsqueeze.decompress_cloud(bytes(corrupt))
    for length in range(plain_length, len(data), max(1, (len(data) - plain_length) // 40)):
        with pytest.raises(ContainerError):
            mapsqueeze.decompress_cloud(data[:length])
    flagged = bytearray(data)
    flagged[6] = 2
    with pytest.raises(ContainerError, match="reserved flags 0x0002"):
        mapsqueeze.info(bytes(flagged))


def test_cli_compress_options_and_info(tmp_path):
    cli = Path(sys.executable).parent / "mapsqueeze"
    if not cli.exists():
        pytest.skip("CLI not installed")
    points, intensity, classification, _ = street(6000, 2000)
    write_points(tmp_path / "map.ply", points - UTM, attributes={"intensity": intensity, "ring": classification})
    env = {**os.environ, "COLUMNS": "250"}
    run = lambda *args: subprocess.run([str(cli), *args], capture_output=True, text=True, timeout=300,  # noqa: E731
                                       env=env)
    result = run("compress", str(tmp_path / "map.ply"), "-o", str(tmp_path / "map.msq"), "--attributes", "ring",
                 "--attribute-voxel", "0.5")
    assert result.returncode == 0, result.stderr
    shown = run("info", str(tmp_path / "map.msq")).stdout
    assert "ring (uint8, majority); voxel 0.5 m" in shown and "intensity" not in shown
    result = run("decompress", str(tmp_path / "map.msq"), "-o", str(tmp_path / "out.bin"))
    assert result.returncode == 0 and "cannot hold attribute(s) ring" in result.stderr
    bad = run("compress", str(tmp_path / "map.ply"), "-o", str(tmp_path / "x.msq"), "--attributes", "colour")
    assert bad.returncode == 2 and bad.stderr.startswith("error: no attribute colour")


def test_cli_decompress_without_attributes_writes_the_same_geometry_only(tmp_path, run_cli):
    points, intensity, _, _ = street(6000, 2000)
    write_points(tmp_path / "map.ply", points - UTM, attributes={"intensity": intensity})
    mapsqueeze.compress_file(tmp_path / "map.ply", tmp_path / "map.msq")
    code, _, err = run_cli("decompress", str(tmp_path / "map.msq"), "-o", str(tmp_path / "full.ply"))
    assert code == 0, err
    code, _, err = run_cli("decompress", str(tmp_path / "map.msq"), "-o", str(tmp_path / "bare.ply"),
                           "--no-attributes")
    assert code == 0, err
    full, bare = read_point_cloud(tmp_path / "full.ply"), read_point_cloud(tmp_path / "bare.ply")
    assert "intensity" in full.attributes and "intensity" not in bare.attributes
    assert np.array_equal(full.points, bare.points)


@pytest.mark.parametrize("voxel_m, relative_step, message", [(-1.0, 1 / 32, "attribute voxel"),
                                                             (float("nan"), 1 / 32, "attribute voxel"),
                                                             (1.0, 0.0, "attribute step"),
                                                             (1.0, 2.0, "attribute step")])
def test_attribute_options_out_of_range_are_refused_without_attributes_too(tmp_path, run_cli, voxel_m,
                                                                           relative_step, message):
    """A bad voxel edge or step is an error whether or not the map has attributes (not silently ignored)."""
    with pytest.raises(InvalidPointCloudError, match=message):
        AttributeOptions(voxel_m=voxel_m, relative_step=relative_step)
    write_points(tmp_path / "map.ply", np.random.default_rng(0).uniform(0, 5, (300, 3)))
    code, out, err = run_cli("compress", str(tmp_path / "map.ply"), "-o", str(tmp_path / "map.msq"),
                             "--attribute-voxel", str(voxel_m), "--attribute-step", str(relative_step))
    assert (code, out) == (2, "") and err.startswith(f"error: {message}") and err.count("\n") == 1
    assert not (tmp_path / "map.msq").exists()


@pytest.mark.parametrize("name, dtype", [("reflectivity", np.uint16), ("t", np.uint32), ("signal", np.uint16),
                                         ("near_ir", np.uint16), ("ambient", np.uint16), ("offset_time", np.uint32),
                                         ("Intensity", np.uint16)])
def test_integer_lidar_measurements_of_driver_pcds_are_continuous(name, dtype):
    """Integer fields that Ouster and Livox drivers write (reflectivity, signal, near_ir, ambient; per-point time
    t, offset_time), and intensity in any case, are measurements: coded as a quantised median, not as categories
    (one palette entry per distinct value: 55x the bytes on an Ouster submap)."""
    points, intensity, _, _ = street(3000, 1000)
    values = (intensity * 1000).astype(dtype)
    summary = mapsqueeze.info(mapsqueeze.compress(points, attributes={name: values}))
    assert summary.attribute_summary().startswith(f"{name} ({np.dtype(dtype).name}, median"), \
        summary.attribute_summary()
    labels = mapsqueeze.info(mapsqueeze.compress(points, attributes={"label": values % 20}))
    assert "majority" in labels.attribute_summary()


def test_categorical_attribute_with_more_values_than_voxels_decodes():
    """An integer id per point (more distinct values in a tile than the tile has attribute voxels) is coded with a
    palette of the values the voxels take, so the file decodes; before, the encoder wrote every input value into the
    palette and the decoder, which bounds a palette by the voxel count, refused the file it had been given."""
    points, _, classification, _ = street(6000, 2000)
    point_id = np.arange(len(points), dtype=np.uint32)
    data = mapsqueeze.compress(points, attributes={"point_id": point_id, "cls": classification})
    cloud = mapsqueeze.decompress_cloud(data, n_points=len(points))
    assert cloud.attributes["point_id"].dtype == np.uint32
    nearest = nearest_original(points, cloud.points)
    decoded_ids = np.unique(cloud.attributes["point_id"])
    assert len(decoded_ids) > 100 and np.isin(decoded_ids, point_id).all()
    # an id names one input point: the one it names lies within a voxel (1 m) and a half of the decoded point
    gap = np.linalg.norm(points[cloud.attributes["point_id"].astype(np.int64)] - points[nearest], axis=1)
    assert np.median(gap) < 1.5, np.median(gap)
    assert_quality(points, cloud.points, {"cls": classification}, cloud.attributes, categorical=("cls",))
