"""Classical baseline codecs (Draco, plain octree, octree-ac, G-PCC wrapper) and the rate-distortion helpers."""

import json
import math
import struct
import sys
import zlib
from itertools import pairwise

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from mapsqueeze.baselines import (
    BASELINES,
    DracoCodec,
    GpccCodec,
    OctreeAcCodec,
    OctreeCodec,
    distortion_at,
    get_baseline,
    gpcc,
    octree,
    pareto_front,
    setting_label,
)
from mapsqueeze.errors import BaselineError, ContainerError, InvalidPointCloudError, MapsqueezeError
from mapsqueeze.geometry.voxel import voxel_filter

HALF_DIAGONAL = math.sqrt(3) / 2


@pytest.fixture(scope="module")
def map_points() -> np.ndarray:
    """A small map-like cloud in a local frame: a 20 x 20 m ground plane and two walls, 2 cm noise."""
    rng = np.random.default_rng(7)
    ground = np.column_stack([rng.uniform(-10, 10, 2500), rng.uniform(-10, 10, 2500), np.zeros(2500)])
    wall_x = np.column_stack([np.full(1200, 8.0), rng.uniform(-10, 10, 1200), rng.uniform(0, 4, 1200)])
    wall_y = np.column_stack([rng.uniform(-10, 0, 800), np.full(800, -6.0), rng.uniform(0, 3, 800)])
    points = np.concatenate([ground, wall_x, wall_y]) + rng.normal(0, 0.02, (4500, 3))
    return points + np.array([3.0, -2.0, 1.5])


def nearest_distances(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances from each point of a to its nearest in b, and from each point of b to its nearest in a."""
    return cKDTree(b).query(a)[0], cKDTree(a).query(b)[0]


# --- registry ----------------------------------------------------------------------------------------------------


def test_registry_names_match_classes():
    assert set(BASELINES) == {"draco", "octree", "octree-ac", "gpcc"}
    for name, codec_class in BASELINES.items():
        codec = get_baseline(name)
        assert isinstance(codec, codec_class) and codec.name == name
        assert codec.settings() and all(setting_label(s) for s in codec.settings())


def test_unknown_baseline_is_a_mapsqueeze_error():
    with pytest.raises(MapsqueezeError, match=r"unknown baseline codec 'zip'.*draco"):
        get_baseline("zip")


@pytest.mark.parametrize("codec_class", [DracoCodec, OctreeCodec, OctreeAcCodec, GpccCodec])
def test_invalid_points_are_rejected(codec_class):
    codec = codec_class()
    with pytest.raises(InvalidPointCloudError):
        codec.encode(np.array([[0.0, np.nan, 1.0]]), codec.settings()[0])
    with pytest.raises(InvalidPointCloudError):
        codec.encode(np.zeros((0, 3)), codec.settings()[0])


@pytest.mark.parametrize(
    ("codec", "setting", "message"),
    [
        (OctreeCodec(), {"leaf_m": -0.1}, "leaf_m"),
        (OctreeCodec(), {"leaf_m": float("nan")}, "leaf_m"),
        (OctreeCodec(), {"leaf": 0.1}, "lacks 'leaf_m'"),
        (OctreeCodec(), {"leaf_m": 5e-6}, "too small"),
        (DracoCodec(), {"voxel_m": 0.2, "bits": 31}, "bits"),
        (DracoCodec(), {"voxel_m": 0.2, "bits": 8.5}, "integer"),
        (DracoCodec(), {"voxel_m": "big", "bits": 8}, "number"),
        (GpccCodec(), {"mode": "mesh", "cell_m": 0.1}, "mode"),
        (GpccCodec(), {"mode": "trisoup", "cell_m": 0.1, "node_log2": 1}, "node_log2"),
    ],
)
def test_bad_settings_raise_baseline_error(map_points, codec, setting, message):
    with pytest.raises(BaselineError, match=message):
        if isinstance(codec, GpccCodec):
            codec.encoder_arguments(setting, "in.ply", "out.bin")
        else:
            codec.encode(map_points, setting)


# --- octree ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("codec_class", [OctreeCodec, OctreeAcCodec])
def test_octree_round_trip_every_setting(map_points, codec_class):
    codec = codec_class()
    sizes = []
    for setting in codec.settings():
        leaf = setting["leaf_m"]
        data = codec.encode(map_points, setting)
        decoded = codec.decode(data)
        sizes.append(len(data))
        origin = map_points.min(axis=0)
        occupied = np.unique(np.floor((map_points - origin) / leaf).astype(np.int64), axis=0)
        assert len(decoded) == len(occupied)
        offsets = (decoded - origin) / leaf - 0.5  # cell centres sit on the grid anchored at the minimum corner
        np.testing.assert_allclose(offsets, np.round(offsets), atol=1e-6)
        to_decoded, to_input = nearest_distances(map_points, decoded)
        assert to_decoded.max() <= HALF_DIAGONAL * leaf + 1e-9
        assert to_input.max() <= HALF_DIAGONAL * leaf + 1e-9
    assert sizes == sorted(sizes, reverse=True) and len(set(sizes)) == len(sizes)


def test_octree_is_deterministic_and_order_independent(map_points):
    setting = {"leaf_m": 0.2}
    for codec in (OctreeCodec(), OctreeAcCodec()):
        data = codec.encode(map_points, setting)
        assert codec.encode(map_points, setting) == data
        shuffled = np.random.default_rng(1).permutation(map_points)
        assert codec.encode(shuffled, setting) == data


def test_octree_ac_decodes_the_same_leaves_in_fewer_bytes(map_points):
    setting = {"leaf_m": 0.1}
    raw, coded = OctreeCodec().encode(map_points, setting), OctreeAcCodec().encode(map_points, setting)
    assert len(coded) < 0.95 * len(raw)
    np.testing.assert_array_equal(OctreeCodec().decode(raw), OctreeCodec().decode(coded))


def test_octree_single_point():
    point = np.array([[1.25, -3.5, 0.75]])
    decoded = OctreeCodec().decode(OctreeCodec().encode(point, {"leaf_m": 0.4}))
    assert decoded.shape == (1, 3) and np.linalg.norm(decoded - point) <= HALF_DIAGONAL * 0.4 + 1e-9


def _with_payload(data: bytes, payload: bytes, **fields) -> bytes:
    """Re-pack an octree stream with a new payload (and any header fields changed), fixing the CRC."""
    names = ["magic", "version", "coding", "depth", "leaf_count", "crc", "x", "y", "z", "root_size"]
    values = dict(zip(names, octree._HEADER.unpack_from(data), strict=True))
    values.update(fields, crc=zlib.crc32(payload))
    return octree._HEADER.pack(*values.values()) + payload


@pytest.fixture(scope="module")
def octree_stream(map_points) -> bytes:
    return OctreeCodec().encode(map_points, {"leaf_m": 0.8})


def test_corrupt_octree_raises_container_error(octree_stream):
    size = octree._HEADER.size
    payload = octree_stream[size:]
    flipped = bytearray(octree_stream)
    flipped[size + 3] ^= 0x10
    corrupt = {
        "empty": b"",
        "truncated header": octree_stream[: size - 1],
        "truncated payload": octree_stream[:-5],
        "flipped payload bit": bytes(flipped),
        "bad magic": b"XXXX" + octree_stream[4:],
        "bad version": _with_payload(octree_stream, payload, version=9),
        "unknown coding": _with_payload(octree_stream, payload, coding=7),
        "depth 0": _with_payload(octree_stream, payload, depth=0),
        "depth 40": _with_payload(octree_stream, payload, depth=40),
        "NaN origin": _with_payload(octree_stream, payload, x=float("nan")),
        "negative root": _with_payload(octree_stream, payload, root_size=-1.0),
        "wrong leaf count": _with_payload(octree_stream, payload, leaf_count=3),
        "zero occupancy": _with_payload(octree_stream, b"\x00" + payload[1:]),
        "missing level": _with_payload(octree_stream, payload[:-4]),
        "stray bytes": _with_payload(octree_stream, payload + b"\x01"),
        "raw read as arithmetic": _with_payload(octree_stream, payload, coding=1),
    }
    for label, data in corrupt.items():
        with pytest.raises(ContainerError):
            OctreeCodec().decode(data)
            pytest.fail(f"no error for {label}")


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_mutated_octree_never_crashes(octree_stream, map_points, data):
    """Random byte edits (CRC fixed up so the structure parser sees them) decode or raise ContainerError."""
    source = data.draw(st.sampled_from([octree_stream, OctreeAcCodec().encode(map_points, {"leaf_m": 0.8})]))
    payload = bytearray(source[octree._HEADER.size :])
    for _ in range(data.draw(st.integers(1, 4))):
        payload[data.draw(st.integers(0, len(payload) - 1))] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, 3))
    mutated = _with_payload(source, bytes(payload[: len(payload) - cut]))
    try:
        decoded = OctreeCodec().decode(mutated)
    except ContainerError:
        return
    assert decoded.ndim == 2 and decoded.shape[1] == 3 and np.isfinite(decoded).all()


# --- Draco -------------------------------------------------------------------------------------------------------


def test_draco_round_trip_every_setting(map_points):
    codec = DracoCodec()
    sizes = {}
    for setting in codec.settings():
        voxel, bits = setting["voxel_m"], setting["bits"]
        expected = voxel_filter(map_points, voxel) if voxel > 0 else map_points
        data = codec.encode(map_points, setting)
        decoded = codec.decode(data)
        sizes[voxel, bits] = len(data)
        assert decoded.shape == expected.shape and decoded.dtype == np.float64
        step = np.ptp(expected, axis=0).max() / (2**bits - 1)
        to_decoded, to_expected = nearest_distances(expected, decoded)
        assert max(to_decoded.max(), to_expected.max()) <= HALF_DIAGONAL * step + 1e-5  # + float32 rounding
    voxels, all_bits = sorted({v for v, _ in sizes}), sorted({b for _, b in sizes})
    for bits in all_bits:  # coarser voxels, fewer bytes
        assert all(sizes[a, bits] > sizes[b, bits] for a, b in pairwise(voxels))
    for voxel in voxels:  # fewer bits, fewer bytes
        assert all(sizes[voxel, a] < sizes[voxel, b] for a, b in pairwise(all_bits))


def test_draco_is_deterministic(map_points):
    setting = {"voxel_m": 0.4, "bits": 10}
    assert DracoCodec().encode(map_points, setting) == DracoCodec().encode(map_points, setting)


def test_corrupt_draco_raises_container_error(map_points):
    valid = DracoCodec().encode(map_points, {"voxel_m": 0.4, "bits": 10})
    for data in (b"", b"not draco at all", valid[:20], valid[: len(valid) // 2]):
        with pytest.raises(ContainerError, match="draco"):
            DracoCodec().decode(data)


# --- G-PCC (tmc3) ------------------------------------------------------------------------------------------------

# PLUMBING ONLY: this fake `tmc3` does no compression. Its "bitstream" is a PLY of the input in metres (input units
# times --srcUnitLength), which its decoder copies out. It checks that the wrapper hands it integer coordinates
# and logs every command line, so the tests below verify command construction, file handling, error reporting
# and the decoded-bounds check, not G-PCC itself (see test_real_tmc3_round_trip for that).
FAKE_TMC3 = r"""#!{python}
import array, json, os, shutil, sys

args = dict(arg[2:].split("=", 1) for arg in sys.argv[1:])
with open(os.environ["FAKE_TMC3_LOG"], "a") as log:
    log.write(json.dumps(sys.argv[1:]) + "\n")
print("MPEG PCC tmc3 version fake")
if os.environ.get("FAKE_TMC3_SAY"):
    print(os.environ["FAKE_TMC3_SAY"], file=sys.stderr)
if os.environ.get("FAKE_TMC3_FAIL"):
    print("Error: can't compress point cloud!")
    sys.exit(255)
if args["mode"] == "0":
    with open(args["uncompressedDataPath"], "rb") as source:
        header, body = source.read().split(b"end_header\n", 1)
    if b"property float64 x" not in header:
        sys.exit("fake tmc3: x is not a float64 property")
    grid = array.array("d", body)
    if any(value != int(value) or value < 0 for value in grid):
        sys.exit("fake tmc3: input coordinates are not non-negative integers")
    scale = float(args["srcUnitLength"]) * float(os.environ.get("FAKE_TMC3_SCALE", "1"))
    metres = array.array("d", (value * scale for value in grid))
    with open(args["compressedStreamPath"], "wb") as stream:  # laid out like tmc3's binary PLY output
        stream.write(header + b"element face 0\n"
                     b"property list uint8 int32 vertex_index\nend_header\n" + metres.tobytes())
else:
    shutil.copyfile(args["compressedStreamPath"], args["reconstructedDataPath"])
"""


@pytest.fixture
def fake_tmc3(tmp_path, monkeypatch):
    """Put the plumbing-only fake `tmc3` first on PATH; returns the path of its command-line log."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    script = bin_dir / "tmc3"
    script.write_text(FAKE_TMC3.replace("{python}", sys.executable))
    script.chmod(0o755)
    log = tmp_path / "tmc3.log"
    monkeypatch.setenv("PATH", str(bin_dir))
    monkeypatch.delenv("MAPSQUEEZE_TMC3", raising=False)
    monkeypatch.setenv("FAKE_TMC3_LOG", str(log))
    return log


def test_gpcc_unavailable_without_tmc3(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setenv("MAPSQUEEZE_SHARED", str(tmp_path))  # no shared copy either
    monkeypatch.delenv("MAPSQUEEZE_TMC3", raising=False)
    codec = GpccCodec()
    assert not codec.available() and "tmc3" in codec.requirement
    with pytest.raises(BaselineError, match="not found"):
        codec.encode(np.zeros((4, 3)), codec.settings()[0])


def test_gpcc_plumbing_with_fake_tmc3(fake_tmc3, map_points):
    codec = GpccCodec()
    assert codec.available()
    for setting in codec.settings():
        decoded = codec.decode(codec.encode(map_points, setting))
        # the fake is lossless, so only the wrapper's own 1 mm grid rounding remains
        assert np.abs(decoded - map_points).max() <= gpcc.GRID_STEP_M / 2 + 1e-9
    calls = [json.loads(line) for line in fake_tmc3.read_text().splitlines()]
    assert len(calls) == 2 * len(codec.settings())
    for setting, encoder, decoder in zip(codec.settings(), calls[::2], calls[1::2], strict=True):
        assert encoder[0] == "--mode=0" and decoder[0] == "--mode=1"
        options = dict(arg[2:].split("=", 1) for arg in encoder)
        assert options["inputScale"] == "1" and options["srcUnit"] == "1"
        assert float(options["srcUnitLength"]) == gpcc.GRID_STEP_M
        assert float(options["codingScale"]) == pytest.approx(gpcc.GRID_STEP_M / setting["cell_m"])
        trisoup = str(setting["node_log2"]) if setting["mode"] == "trisoup" else None
        assert options.get("trisoupNodeSizeLog2") == trisoup
        assert options["partitionMethod"] == "2"  # tmc3's default slicing corrupts clouds of >= 1.1M points
        assert "--outputUnitLength=1" in decoder and "--outputBinaryPly=1" in decoder


def test_gpcc_rejects_mis_scaled_output(fake_tmc3, monkeypatch, map_points):
    codec = GpccCodec()
    data = codec.encode(map_points, {"mode": "octree", "cell_m": 0.1})
    monkeypatch.setenv("FAKE_TMC3_SCALE", "1000")  # a tmc3 that ignores --srcUnitLength: output in millimetres
    scaled = codec.encode(map_points, {"mode": "octree", "cell_m": 0.1})
    with pytest.raises(BaselineError, match="scaled the output differently"):
        codec.decode(scaled)
    monkeypatch.setenv("FAKE_TMC3_SCALE", "0.25")
    with pytest.raises(BaselineError, match="scaled the output differently"):
        codec.decode(codec.encode(map_points, {"mode": "octree", "cell_m": 0.1}))
    assert len(codec.decode(data)) == len(map_points)


def test_gpcc_reports_tool_failures(fake_tmc3, monkeypatch, map_points):
    codec = GpccCodec()
    setting = codec.settings()[0]
    monkeypatch.setenv("FAKE_TMC3_FAIL", "1")
    with pytest.raises(BaselineError, match=r"encoder failed with exit code 255.*can't compress"):
        codec.encode(map_points, setting)
    monkeypatch.delenv("FAKE_TMC3_FAIL")
    monkeypatch.setenv("FAKE_TMC3_SAY", "Warning: Unhandled argument ignored: --codingScale=0.01")
    with pytest.raises(BaselineError, match=r"lacks options.*codingScale"):
        codec.encode(map_points, setting)


def test_gpcc_bad_header_raises_container_error(fake_tmc3, map_points):
    data = GpccCodec().encode(map_points, {"mode": "octree", "cell_m": 0.2})
    for corrupt in (b"", data[: gpcc._HEADER.size], b"ABCD" + data[4:], data[:4] + b"\x07" + data[5:]):
        with pytest.raises(ContainerError):
            GpccCodec().decode(corrupt)
    nan_origin = data[:5] + struct.pack("<d", float("nan")) + data[13:]
    with pytest.raises(ContainerError, match="absurd"):
        GpccCodec().decode(nan_origin)


def test_gpcc_sweep_covers_octree_and_trisoup_settings(tmp_path, monkeypatch):
    monkeypatch.setenv("MAPSQUEEZE_TMC3", str(tmp_path / "my-tmc3"))
    codec = GpccCodec()
    assert codec.executable == str(tmp_path / "my-tmc3")  # found through the shared resolver
    octree = sorted(s["cell_m"] for s in codec.settings() if s["mode"] == "octree")
    trisoup = {(s["cell_m"], s["node_log2"]) for s in codec.settings() if s["mode"] == "trisoup"}
    assert octree == [0.1, 0.2, 0.4, 0.8]
    assert trisoup == {(cell, node) for cell in (0.05, 0.1, 0.2) for node in (2, 3, 4, 5)}


@pytest.mark.slow
def test_real_tmc3_codes_a_cloud_of_more_than_a_million_points(tmc3):
    """tmc3's default slicing hangs or corrupts the stream at this size; the wrapper's --partitionMethod=2 does not."""
    rng = np.random.default_rng(3)
    n = 1_400_000
    ground = np.c_[rng.random((n, 2)) * 200.0, rng.normal(0.0, 0.05, n)] + [4.5e5, 5.4e6, 30.0]
    codec = GpccCodec(executable=tmc3, timeout_s=180)
    decoded = codec.decode(codec.encode(ground, {"mode": "octree", "cell_m": 0.1}))
    assert len(decoded) > 1_100_000  # occupied 10 cm cells: the size at which the default slicing fails
    to_decoded, to_input = nearest_distances(ground, decoded)
    bound = HALF_DIAGONAL * (0.1 + gpcc.GRID_STEP_M) + 1e-6
    assert to_decoded.max() <= bound and to_input.max() <= bound


def test_real_tmc3_round_trip(tmc3, map_points):
    codec = GpccCodec(executable=tmc3)
    sizes = []
    for cell in (0.1, 0.4):
        setting = {"mode": "octree", "cell_m": cell}
        data = codec.encode(map_points, setting)
        assert codec.encode(map_points, setting) == data
        sizes.append(len(data))
        to_decoded, to_input = nearest_distances(map_points, codec.decode(data))
        bound = HALF_DIAGONAL * (cell + gpcc.GRID_STEP_M) + 1e-6
        assert to_decoded.max() <= bound and to_input.max() <= bound
    assert sizes[0] > sizes[1]
    trisoup = codec.decode(codec.encode(map_points, {"mode": "trisoup", "cell_m": 0.1, "node_log2": 3}))
    assert cKDTree(map_points).query(trisoup)[0].mean() < 0.4


# --- rate-distortion helpers -------------------------------------------------------------------------------------

RATES = [1.0, 2.0, 4.0, 0.5, 2.0, 8.0, 1.0]
ERRORS = [0.5, 0.3, 0.2, 0.9, 0.4, 0.25, 0.5]


def test_pareto_front_keeps_non_dominated_points_by_rate():
    front = pareto_front(RATES, ERRORS)
    assert front.tolist() == [3, 0, 1, 2]  # (0.5, 0.9) (1, 0.5) (2, 0.3) (4, 0.2); duplicates and dominated dropped


def test_distortion_at_interpolates_in_log_bpp():
    assert distortion_at(RATES, ERRORS, math.sqrt(2)) == pytest.approx(0.4)  # halfway between 1 and 2 in log
    assert distortion_at(RATES, ERRORS, 2 * 2**0.25) == pytest.approx(0.3 - 0.1 / 4)
    np.testing.assert_allclose(distortion_at(RATES, ERRORS, [0.5, 4.0]), [0.9, 0.2])
    assert distortion_at(RATES, ERRORS, 8.0) == pytest.approx(0.2)  # 8 bpp measured (0.25, dominated): front holds 0.2
    assert np.isnan(distortion_at(RATES, ERRORS, [0.25, 8.5, 0.0])).all()  # outside the measured rates: no extrapolation


@pytest.mark.parametrize(
    ("rates", "errors"), [([1.0, -2.0], [0.1, 0.2]), ([1.0], [0.1, 0.2]), ([], []), ([1.0, np.nan], [0.1, 0.2])]
)
def test_rd_rejects_bad_input(rates, errors):
    with pytest.raises(BaselineError):
        pareto_front(rates, errors)


@pytest.mark.parametrize("codec, digest", [
    (OctreeCodec, "7113c6ceb43f176441a0bb1c89cb56effa61ca08c40ecccfb85ab9c9033288eb"),
    (OctreeAcCodec, "339defea60e8fa5b21dcc331f0f8e1e00f698717df6103453639b135b73b403b"),
])
def test_octree_bitstreams_are_pinned(codec, digest):
    """Encoder output and decoded points of a fixed cloud must not drift: pinned digests, changed only with a format."""
    import hashlib

    rng = np.random.default_rng(5)
    rng.random((3000, 3))  # the same draws as the raw-tile pin in test_codec.py
    world = rng.random((3000, 3)) * [40, 40, 15] + [500000, 5000000, 100]
    data = codec().encode(world, {"leaf_m": 0.2})
    assert hashlib.sha256(data).hexdigest() == digest
    decoded = np.ascontiguousarray(codec().decode(data))
    assert hashlib.sha256(decoded.tobytes()).hexdigest() == \
        "f96d88394817453f3d4da280b351c72ffe73e8da48c8eba8a61200c16c340941"
