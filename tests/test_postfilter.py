"""The encoder-signalled decode post-filter (codec.postfilter): it raises IoU on a tile with a known surface, its
per-tile setting round-trips through the container, the paper's mode is unchanged, and it is deterministic."""

import os
import subprocess
import sys

import numpy as np
import pytest

import mapsqueeze
from mapsqueeze.codec.container import TileRecord, open_container, serialise_container
from mapsqueeze.codec.postfilter import (
    CANDIDATES,
    MAX_D_E_INCREASE,
    OFF,
    PostFilter,
    apply_post_filter,
    choose_post_filter,
    setting_byte,
)
from mapsqueeze.codec.tilepoints import keep_inside
from mapsqueeze.errors import ContainerError
from mapsqueeze.metrics import d_euclidean, iou
from mapsqueeze.model import load_model

EXTENT = np.array([12.0, 12.0, 3.0])


def known_surface(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(original, decoded) of a tilted plane z = 1 + 0.05 x over 12 x 12 m: the original an even 10 cm sampling,
    the decoded one clumps of 60 points (8 cm across the plane, 4 cm off it) every 50 cm with holes between them,
    plus 3 % stray points up to 30 cm off the plane; tile-local metres."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(np.arange(0.05, 12, 0.1), np.arange(0.05, 12, 0.1)), -1).reshape(-1, 2)
    original = np.column_stack([grid, 1 + 0.05 * grid[:, 0]])
    centres = np.stack(np.meshgrid(np.arange(0.25, 12, 0.5), np.arange(0.25, 12, 0.5)), -1).reshape(-1, 2)
    xy = np.repeat(centres, 60, axis=0) + rng.normal(0, 0.08, (len(centres) * 60, 2))
    z = 1 + 0.05 * xy[:, 0] + rng.normal(0, 0.04, len(xy))
    clumps = np.column_stack([xy, z])
    stray = clumps[rng.choice(len(clumps), len(clumps) * 3 // 100)] + rng.uniform(-0.3, 0.3, (len(clumps) * 3 // 100, 3))
    decoded = np.concatenate([clumps, stray])
    return original, keep_inside(decoded.astype(np.float32), EXTENT)


def test_the_post_filter_raises_iou_on_a_known_surface():
    original, decoded = known_surface()
    frame = np.array([500_000.0, 4_000_000.0, 50.0])
    before = iou(original + frame, decoded.astype(np.float64) + frame)
    setting, d_e = choose_post_filter(original, decoded, frame, lambda cloud: keep_inside(cloud, EXTENT))
    filtered = keep_inside(apply_post_filter(decoded, setting), EXTENT).astype(np.float64)
    assert setting != OFF
    assert iou(original + frame, filtered + frame) > before + 0.05
    assert d_e == pytest.approx(d_euclidean(original, filtered))
    assert d_e <= d_euclidean(original, decoded.astype(np.float64)) * (1 + MAX_D_E_INCREASE)
    # snapping alone brings the points to the plane: the offsets across it shrink
    snapped = apply_post_filter(decoded, setting_byte(snap=3)).astype(np.float64)
    assert np.abs(snapped[:, 2] - 1 - 0.05 * snapped[:, 0]).mean() < \
        0.5 * np.abs(decoded[:, 2] - 1 - 0.05 * decoded[:, 0]).mean()


def test_each_setting_does_what_its_byte_says():
    _, decoded = known_surface()
    assert apply_post_filter(decoded, OFF) is decoded
    spread = apply_post_filter(decoded, setting_byte(snap=3, spread=3))
    assert len(spread) == 3 * len(decoded)
    isolated = apply_post_filter(decoded, setting_byte(isolated=True))
    assert len(decoded) * 0.9 < len(isolated) < len(decoded)
    assert PostFilter.parse(setting_byte(snap=1, spread=2, isolated=True)) == PostFilter(16, 1, 0.10, True)
    for byte in (0x20, 0x80, 256):
        with pytest.raises(ContainerError, match="post-filter"):
            PostFilter.parse(byte)


@pytest.fixture(scope="module")
def e0_tile():
    """A 40 m tile of ground and a wall, at UTM coordinates, and the shipped e0 model."""
    rng = np.random.default_rng(0)
    n = 30_000
    ground = np.column_stack([rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.normal(0.5, 0.05, n)])
    wall = np.column_stack([rng.uniform(0, 40, n // 3), rng.normal(20, 0.05, n // 3), rng.uniform(0.5, 8, n // 3)])
    return np.concatenate([ground, wall]) + [500_000.0, 4_000_000.0, 50.0], load_model("e0")


@pytest.fixture(scope="module")
def filtered_and_paper(e0_tile):
    points, model = e0_tile
    return (mapsqueeze.compress(points, model=model, post_filter=True, workers=1),
            mapsqueeze.compress(points, model=model, workers=1))


def test_a_post_filtered_file_signals_a_filter_that_the_decoder_applies(e0_tile, filtered_and_paper):
    points, model = e0_tile
    filtered, paper = filtered_and_paper
    reader, stream = open_container(filtered)
    with stream:
        settings = [entry.post_filter for entry in reader.entries]
    assert reader.version == 4 and any(s in CANDIDATES and s != OFF for s in settings)
    assert len(filtered) == len(paper) + len(settings)  # one byte per tile, the payloads unchanged
    with_filter, without = (mapsqueeze.decompress(data, model=model, workers=1) for data in (filtered, paper))
    assert iou(points, with_filter) > iou(points, without)


def test_paper_mode_is_unchanged(e0_tile, filtered_and_paper):
    """The default (--post-filter off) writes the version 3 bytes of the paper's decode, with or without
    --no-fallback."""
    points, model = e0_tile
    _, paper = filtered_and_paper
    assert open_container(paper)[0].version == 3
    assert mapsqueeze.compress(points, model=model, fallback=False, workers=1) == \
        mapsqueeze.compress(points, model=model, fallback=False, post_filter=False, workers=1)
    assert mapsqueeze.compress(points, model=model, post_filter=False, workers=1) == paper
    reader, stream = open_container(paper)
    with stream:
        assert all(entry.post_filter == OFF for entry in reader.entries)


def _rewritten(data: bytes, settings: list[int]) -> bytes:
    """The container `data` with its tiles' post-filter settings replaced."""
    reader, stream = open_container(data)
    with stream:
        records = [TileRecord(e.index, e.n_points, e.bounds_lo, e.bounds_hi, e.coding, reader.payload(p), s)
                   for p, (e, s) in enumerate(zip(reader.entries, settings))]
        header = reader.header
    return serialise_container(header, records)


def test_the_per_tile_setting_round_trips_and_bad_ones_are_refused(e0_tile, filtered_and_paper):
    points, model = e0_tile
    filtered, paper = filtered_and_paper
    n_tiles = len(open_container(paper)[0].entries)
    settings = [CANDIDATES[(i + 1) % len(CANDIDATES)] for i in range(n_tiles)]
    rewritten = _rewritten(paper, settings)
    assert [entry.post_filter for entry in open_container(rewritten)[0].entries] == settings
    assert _rewritten(filtered, [OFF] * n_tiles) == paper  # all settings off: version 3, the paper's bytes
    with pytest.raises(ContainerError, match="post-filter"):
        open_container(_rewritten(paper, [0x40] * n_tiles))


def test_the_filter_does_not_depend_on_the_thread_count(tmp_path):
    """pykdtree's neighbour searches run on OpenMP threads: the filtered points are the same on 1 and 2."""
    _, decoded = known_surface()
    np.save(tmp_path / "decoded.npy", decoded)
    script = ("import sys, numpy as np; from mapsqueeze.codec.postfilter import apply_post_filter; "
              "sys.stdout.buffer.write(apply_post_filter(np.load(sys.argv[1]), int(sys.argv[2])).tobytes())")
    outputs = set()
    for threads in ("1", "2"):
        env = dict(os.environ, OMP_NUM_THREADS=threads)
        outputs.add(subprocess.run([sys.executable, "-c", script, str(tmp_path / "decoded.npy"),
                                    str(setting_byte(snap=3, spread=1, isolated=True))],
                                   env=env, check=True, capture_output=True).stdout)
    assert len(outputs) == 1 and len(outputs.pop()) > 0


def test_decoding_a_filtered_file_does_not_depend_on_the_workers(e0_tile, filtered_and_paper):
    _, model = e0_tile
    filtered, _ = filtered_and_paper
    assert mapsqueeze.decompress(filtered, model=model, workers=1).tobytes() == \
        mapsqueeze.decompress(filtered, model=model, workers=2).tobytes()
