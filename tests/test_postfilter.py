"""The encoder-signalled decode post-filter (codec.postfilter): both kinds raise IoU on a tile with a known surface,
the per-tile setting round-trips through the container, the paper's mode is unchanged, and it is deterministic."""

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
    PATCH,
    PATCH_CANDIDATES,
    PATCH_EXTRA_COPY_MIN_IOU_GAIN,
    PATCH_STRENGTH,
    PostFilter,
    apply_patch_filter,
    apply_post_filter,
    choose_patch_filter,
    check_setting,
    choose_post_filter,
    patch_planes_byte,
    setting_byte,
)
from mapsqueeze.codec.tilepoints import keep_inside
from mapsqueeze.errors import ContainerError, MapsqueezeError
from mapsqueeze.geometry.occupancy import occupancy_ious, patch_setting_ious
from mapsqueeze.geometry.patches import patch_planes
from mapsqueeze.metrics import IOU_VOXEL_M, d_euclidean, iou
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
    assert PostFilter.parse(patch_planes_byte(2)) == PostFilter(0, 2, 0.05, False, 4)
    assert PostFilter.parse(PATCH) == PostFilter(0, 1, 0.05, False, 4)
    assert PATCH_CANDIDATES == (PATCH, PATCH | 0x40)
    for byte in (PATCH | 1, PATCH | 0x10, PATCH | 0x80, 0x40, 0x81, 0xC0, 0xC3, 256):
        with pytest.raises(ContainerError, match="post-filter"):
            PostFilter.parse(byte)
    with pytest.raises(ValueError, match="uncropped"):
        apply_post_filter(decoded, PATCH)
    patch = patches()[0] + np.float32(10)  # inside the box [0, 100 m]
    one, two = (apply_patch_filter(patch, byte, (4, 4, 4, 1), np.full(3, 100.0)) for byte in PATCH_CANDIDATES)
    assert np.array_equal(one, patch_planes(patch, 64, PATCH_STRENGTH, 1, 0.05)) and len(one) == 2 * len(patch)
    assert np.array_equal(two, patch_planes(patch, 64, PATCH_STRENGTH, 2, 0.05)) and len(two) == 3 * len(patch)


def patches(seed: int = 0, n_patches: int = 400, patch: int = 64) -> np.ndarray:
    """Decoder-ordered (n_patches x patch, 3) points: each patch a 20 cm disk of a randomly tilted plane at a
    random place, 2 cm thick (float32 metres)."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-5, 5, (n_patches, 3))
    normals = rng.normal(size=(n_patches, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = rng.normal(0, 0.1, (n_patches, patch, 3))
    offsets -= np.einsum("npi,ni->np", offsets, normals)[..., None] * normals[:, None, :]
    offsets += rng.normal(0, 0.02, (n_patches, patch, 1)) * normals[:, None, :]
    return (centres[:, None, :] + offsets).reshape(-1, 3).astype(np.float32), normals


def test_patch_planes_match_an_eigendecomposition():
    points, _ = patches()
    moved = patch_planes(points, 64, 1.0, 2, 0.05).astype(np.float64).reshape(-1, 64, 3, 3)  # point, its 2 copies
    grouped = points.astype(np.float64).reshape(-1, 64, 3)
    offsets = grouped - grouped.mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.einsum("npi,npj->nij", offsets, offsets))[1][:, :, 0]
    across = np.einsum("npi,ni->np", offsets, normals)
    expected = grouped - across[..., None] * normals[:, None, :]
    assert np.abs(moved[:, :, 0] - expected).max() < 1e-5  # float32 output
    copies = moved[:, :, 1:] - moved[:, :, :1]  # in the point's patch plane, within 5 cm of it
    assert np.abs(np.einsum("npci,ni->npc", copies, normals)).max() < 1e-5
    assert np.linalg.norm(copies, axis=-1).max() <= 0.05 + 1e-5
    partly = patch_planes(points, 64, PATCH_STRENGTH, 0, 0.05).astype(np.float64).reshape(-1, 64, 3)
    assert np.allclose(np.einsum("npi,ni->np", partly - grouped.mean(axis=1, keepdims=True), normals),
                       (1 - PATCH_STRENGTH) * across, atol=1e-5)
    box = np.array([5.0, 10.0, 10.0])
    cropped = patch_planes(points, 64, PATCH_STRENGTH, 1, 0.05, box)
    assert np.array_equal(cropped, keep_inside(patch_planes(points, 64, PATCH_STRENGTH, 1, 0.05), box))
    assert 0 < len(cropped) < 2 * len(points)
    with pytest.raises(ValueError, match="patches"):
        patch_planes(points[:-1], 64, 1.0, 0, 0.05)


def test_patch_planes_raise_iou_where_the_decode_is_thick_and_are_left_off_where_not():
    """Patches of 256 points on 40 cm squares of a ground plane, spread 4 cm across it: the filter narrows them onto
    the plane's 10 cm IoU cells; a decode equal to the original points gains nothing, so the encoder keeps the
    paper's decode."""
    rng = np.random.default_rng(1)
    frame = np.array([500_000.0, 4_000_000.0, 50.0])
    centres = np.stack(np.meshgrid(np.arange(0.2, 12, 0.4), np.arange(0.2, 12, 0.4)), -1).reshape(-1, 2)
    xy = np.repeat(centres, 256, axis=0) + rng.uniform(-0.2, 0.2, (len(centres) * 256, 2))
    original = np.column_stack([xy, np.full(len(xy), 1.05)])
    decoded = np.column_stack([xy, 1.05 + rng.normal(0, 0.04, len(xy))]).astype(np.float32)
    plain = keep_inside(decoded, EXTENT)
    factors = (2, 4, 4, 4)  # patches of the last 4 levels: 256 points
    setting = choose_patch_filter(original + frame, decoded, plain, factors, frame, EXTENT)
    assert setting in PATCH_CANDIDATES
    ious = {byte: iou(original + frame, apply_patch_filter(decoded, byte, factors, EXTENT).astype(np.float64) + frame)
            for byte in PATCH_CANDIDATES}
    plain_iou = iou(original + frame, plain.astype(np.float64) + frame)
    one, two = PATCH_CANDIDATES
    assert ious[one] > plain_iou + 0.3
    assert setting == (two if ious[two] >= ious[one] + PATCH_EXTRA_COPY_MIN_IOU_GAIN else one)
    exact = original.astype(np.float32)
    assert choose_patch_filter(original + frame, exact, keep_inside(exact, EXTENT), factors, frame, EXTENT) == OFF
    outside = decoded + np.float32(20)  # nothing inside the box: every point clamped into it, as keep_inside does
    assert np.array_equal(apply_patch_filter(outside, PATCH, factors, EXTENT),
                          keep_inside(patch_planes(outside, 256, PATCH_STRENGTH, 1, 0.05), EXTENT))


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
    return (mapsqueeze.compress(points, model=model, post_filter="auto", workers=1),
            mapsqueeze.compress(points, model=model, post_filter="off", workers=1))


def test_a_post_filtered_file_signals_a_filter_that_the_decoder_applies(e0_tile, filtered_and_paper):
    points, model = e0_tile
    filtered, paper = filtered_and_paper
    reader, stream = open_container(filtered)
    with stream:
        settings = [entry.post_filter for entry in reader.entries]
    assert reader.version == 7 and any(s in CANDIDATES and s != OFF for s in settings)
    assert len(filtered) == len(paper)  # only the network tiles' post-filter bytes differ, the payloads unchanged
    with_filter, without = (mapsqueeze.decompress(data, model=model, workers=1) for data in (filtered, paper))
    assert iou(points, with_filter) > iou(points, without)


def test_paper_mode_is_unchanged(e0_tile, filtered_and_paper):
    """--post-filter off writes every post-filter byte off (the paper's decode)."""
    _, paper = filtered_and_paper
    assert open_container(paper)[0].version == 7
    reader, stream = open_container(paper)
    with stream:
        assert all(entry.post_filter == OFF for entry in reader.entries)


def test_the_default_signals_patch_planes_that_the_decoder_applies(e0_tile, filtered_and_paper):
    """The default (patch) differs from the paper's file only in the tile table's post-filter bytes and its decode
    has a higher IoU; a version 4 file may not carry PATCH."""
    points, model = e0_tile
    _, paper = filtered_and_paper
    default = mapsqueeze.compress(points, model=model, workers=1)
    assert default == mapsqueeze.compress(points, model=model, post_filter="patch", workers=1)
    reader, stream = open_container(default)
    with stream:
        settings = [entry.post_filter for entry in reader.entries]
    assert reader.version == 7 and set(settings) <= {OFF, *PATCH_CANDIDATES} and set(settings) & set(PATCH_CANDIDATES)
    assert len(default) == len(paper)
    assert _rewritten(default, [OFF] * len(settings)) == paper
    with_filter, without = (mapsqueeze.decompress(data, model=model, workers=1) for data in (default, paper))
    assert iou(points, with_filter) > iou(points, without)
    assert mapsqueeze.decompress(default, model=model, workers=2).tobytes() == with_filter.tobytes()
    assert check_setting(PATCH, "tile", 5) == PATCH
    with pytest.raises(ContainerError, match="version 4"):
        check_setting(PATCH, "tile", 4)
    with pytest.raises(MapsqueezeError, match="post-filter"):
        mapsqueeze.compress(points, model=model, post_filter="on", workers=1)


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
    assert _rewritten(filtered, [OFF] * n_tiles) == paper  # all settings off: the paper's bytes
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


@pytest.mark.parametrize("factors", [(2, 4, 4, 4), (5, 5, 5, 5)])
def test_patch_setting_ious_are_those_of_the_settings_clouds(monkeypatch, factors):
    """One grid marked as the settings' points are made gives occupancy_ious of keep_inside's crop and of each
    patch-plane setting's cloud (points partly outside the box); None where a cloud has no point inside the box or
    the grid would be too large, and then choose_patch_filter picks from the clouds made whole."""
    rng = np.random.default_rng(11)
    frame = np.array([500_000.0, 4_000_000.0, 50.0])
    patch = int(np.prod(factors))
    centres = rng.uniform(-1, 13, (40, 3)) * [1, 1, 0.3]
    decoded = (np.repeat(centres, patch, axis=0) + rng.normal(0, [0.3, 0.3, 0.05], (40 * patch, 3))).astype(np.float32)
    original = rng.uniform(0, 12, (5000, 3)) * [1, 1, 0.3] + frame
    for cloud in (decoded[:10 * patch], decoded):
        clouds = [keep_inside(cloud, EXTENT)] + [patch_planes(cloud, patch, PATCH_STRENGTH, copies, 0.05, EXTENT)
                                                 for copies in (1, 2)]
        assert 0 < len(clouds[0]) < len(cloud)
        expected = occupancy_ious(original, clouds, frame, IOU_VOXEL_M)
        assert patch_setting_ious(original, cloud, patch, PATCH_STRENGTH, (1, 2), 0.05, EXTENT, frame,
                                  IOU_VOXEL_M) == expected
    outside = decoded + np.float32(50)
    assert patch_setting_ious(original, outside, patch, PATCH_STRENGTH, (1, 2), 0.05, EXTENT, frame,
                              IOU_VOXEL_M) is None
    far = original + [5000, 5000, 0]
    assert patch_setting_ious(far, decoded, patch, PATCH_STRENGTH, (1, 2), 0.05, EXTENT, frame, IOU_VOXEL_M) is None
    import mapsqueeze.geometry.occupancy as occupancy

    setting = choose_patch_filter(original, decoded, keep_inside(decoded, EXTENT), factors, frame, EXTENT)
    monkeypatch.setattr(occupancy, "patch_setting_ious", lambda *arguments: None)
    assert choose_patch_filter(original, decoded, keep_inside(decoded, EXTENT), factors, frame, EXTENT) == setting


def test_occupancy_ious_are_the_metric_and_refuse_a_box_too_large():
    rng = np.random.default_rng(3)
    frame = np.array([500_000.0, 4_000_000.0, 50.0])
    original = rng.uniform(0, 12, (5000, 3)) + frame
    clouds = [rng.uniform(0, 12, (n, 3)).astype(np.float32) for n in (3000, 8000)]
    expected = [iou(original, cloud.astype(np.float64) + frame) for cloud in clouds]
    assert occupancy_ious(original, clouds, frame, IOU_VOXEL_M) == pytest.approx(expected, abs=0)
    far = [np.array([[0, 0, 0], [5000, 5000, 500]], dtype=np.float32)]
    assert occupancy_ious(original, far, frame, IOU_VOXEL_M) is None


def test_info_names_each_network_tiles_post_filter(e0_tile, filtered_and_paper):
    points, model = e0_tile
    filtered, paper = filtered_and_paper
    n_tiles = len(open_container(paper)[0].entries)
    assert mapsqueeze.info(paper).tile_modes == {"network": n_tiles}
    one, two = PATCH_CANDIDATES
    mixed = _rewritten(paper, [two] + [one] * (n_tiles - 1))
    modes = mapsqueeze.info(mixed).tile_modes
    assert modes["network (patch planes, +2 points per point)"] == 1
    assert modes.get("network (patch planes, +1 point per point)", 0) == n_tiles - 1
    snapped = setting_byte(snap=3, spread=2, isolated=True)
    assert mapsqueeze.info(_rewritten(paper, [snapped] * n_tiles)).tile_modes == {
        "network (48-point planes, +1 on 10 cm disks, isolated points removed)": n_tiles}


@pytest.mark.parametrize("ious, chosen", [((0.30, 0.35, 0.355), 1), ((0.30, 0.35, 0.37), 2), ((0.30, 0.305, 0.31), 1),
                                          ((0.30, 0.30, 0.305), 0), ((0.30, 0.29, 0.31), 2), ((0.30, 0.29, 0.28), 0)])
def test_the_second_extra_copy_must_gain_its_iou_margin(monkeypatch, ious, chosen):
    """Of the paper's decode and one or two extra points per point, the highest IoU wins, ties to the fewer points;
    two extra points must also gain PATCH_EXTRA_COPY_MIN_IOU_GAIN (0.01) over one."""
    import mapsqueeze.geometry.occupancy as occupancy

    assert PATCH_EXTRA_COPY_MIN_IOU_GAIN == 0.01
    monkeypatch.setattr(occupancy, "patch_setting_ious", lambda *arguments: list(ious))
    decoded = np.random.default_rng(0).uniform(0, 10, (1024, 3)).astype(np.float32)
    setting = choose_patch_filter(decoded.astype(np.float64), decoded, keep_inside(decoded, EXTENT), (2, 4, 4, 4),
                                  np.zeros(3), EXTENT)
    assert setting == (OFF, *PATCH_CANDIDATES)[chosen]


def test_decoding_a_patch_plane_file_loads_no_numba(tmp_path, e0_tile):
    """The decoder runs the patch planes in numpy (`geometry.patchesnumpy`): neither a decompress nor its modules
    import numba (~120 MB a process)."""
    points, model = e0_tile
    path = tmp_path / "patched.msq"
    path.write_bytes(mapsqueeze.compress(points, model=model, workers=1))
    reader, stream = open_container(path.read_bytes())
    with stream:
        assert any(PostFilter.parse(entry.post_filter).patch_levels for entry in reader.entries)
    script = ("import sys, mapsqueeze\n"
              "import mapsqueeze.codec.decompress, mapsqueeze.model.compression\n"
              "assert 'numba' not in sys.modules\n"
              f"cloud = mapsqueeze.decompress(open({str(path)!r}, 'rb').read(), model='e0', workers=1)\n"
              "print(len(cloud), 'numba' in sys.modules)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert result.stdout.split() == [str(len(mapsqueeze.decompress(path.read_bytes(), model=model, workers=1))),
                                     "False"]
