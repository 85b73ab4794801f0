"""io.ply.write_ply_stream: the bytes of the binary PLY writer, whatever the estimate of the count and the
coordinates' float32 rounding (the decoder writes its tiles with it, `api.decompress_file`)."""

import numpy as np
import pytest

from mapsqueeze.codec.decompress import DecodedTile
from mapsqueeze.errors import InvalidPointCloudError
from mapsqueeze.io import ply, write_points
from mapsqueeze.io.pointcloud import FLOAT32_SAFE_ABS_M


def clouds(offset: float, sizes=(7, 1, 30, 4)) -> list[np.ndarray]:
    rng = np.random.default_rng(len(sizes))
    return [rng.uniform(-50, 50, (size, 3)) + offset for size in sizes]


@pytest.mark.parametrize("offset", [0.0, 600_000.0, 2.0**20])  # float32; float64; float64 values float32 holds
@pytest.mark.parametrize("estimate", [1, 10, 42, 1_000])  # fewer, as many and more digits than 42 points
def test_streamed_ply_has_the_writers_bytes(tmp_path, monkeypatch, offset, estimate):
    parts = clouds(offset)
    if offset == 2.0**20:
        parts = [np.round(part) for part in parts]  # whole metres: float32 errs by 0 m
    write_points(tmp_path / "expected.ply", np.concatenate(parts))
    monkeypatch.setattr(ply, "MOVE_CHUNK_POINTS", 5)  # moved in several chunks
    certain = offset + 51 < FLOAT32_SAFE_ABS_M
    count = ply.write_ply_stream(tmp_path / "streamed.ply", iter(parts), certain, lambda first: estimate)
    assert count == 42
    expected = (tmp_path / "expected.ply").read_bytes()
    assert (tmp_path / "streamed.ply").read_bytes() == expected
    assert (b"property float x" in expected) == (offset != 600_000.0)


def test_an_empty_or_invalid_stream_leaves_no_file(tmp_path):
    target = tmp_path / "out.ply"
    with pytest.raises(InvalidPointCloudError, match="empty"):
        ply.write_ply_stream(target, iter([]), True, lambda first: first)
    with pytest.raises(InvalidPointCloudError, match="NaN"):
        ply.write_ply_stream(target, iter([np.zeros((3, 3)), np.full((2, 3), np.nan)]), True, lambda first: first)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("move_chunk", [1, 5, 1 << 16])
def test_narrowed_body_moves_behind_a_longer_header(tmp_path, monkeypatch, move_chunk):
    # float64 written, float32 kept ("float" is 1 byte shorter than "double" in each of 3 property lines), and a
    # count 4 digits longer than the estimate: the header ends 1 byte later than the body started
    parts = [np.round(part) for part in clouds(2.0**20, sizes=(1, 20_000))]  # whole metres: float32 exact
    write_points(tmp_path / "expected.ply", np.concatenate(parts))
    monkeypatch.setattr(ply, "MOVE_CHUNK_POINTS", move_chunk)
    count = ply.write_ply_stream(tmp_path / "streamed.ply", iter(parts), False, lambda first: first)
    assert count == 20_001
    expected = (tmp_path / "expected.ply").read_bytes()
    assert b"property float x" in expected and b"element vertex 20001" in expected
    assert (tmp_path / "streamed.ply").read_bytes() == expected


@pytest.mark.parametrize("frame", [(0.0, 0.0, 0.0), (612_345.678, 4_567_890.123, -31.4)])
def test_a_tile_is_placed_as_frame_plus_points(frame):
    """`DecodedTile.place` adds column by column: the float64 sums of the broadcast frame + points, bit for bit."""
    points = np.random.default_rng(3).uniform(0, 40, (10_001, 3)).astype(np.float32)
    tile = DecodedTile(np.array(frame), points, {}, {})
    placed = tile.place(tile.take()[1:])  # a slice, as the writer places a tile part by part
    assert placed.dtype == np.float64
    np.testing.assert_array_equal(placed.view(np.int64), (np.array(frame) + points[1:]).view(np.int64))
