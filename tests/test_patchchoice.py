"""Patch choices (codec.postfilter.PATCH_CHOICES): the encoder's per-patch search raises IoU, the choice stream
round-trips and corrupt streams are refused, files without choices keep their version and bytes."""

import numpy as np
import pytest

import mapsqueeze
from mapsqueeze.codec.entropy import ByteReader
from mapsqueeze.codec.container import TileRecord, open_container, serialise_container
from mapsqueeze.codec.postfilter import (
    CHOICE_SEARCH_START,
    CLEAR_PAY_FRACTION,
    IOU_PER_LOG_RATE,
    OFF,
    PATCH_CHOICE_RATE_SWEEPS,
    PATCH,
    PATCH_CANDIDATES,
    PATCH_CHOICES,
    PATCH_OPTIONS,
    PatchChoiceSearch,
    PostFilter,
    apply_patch_choices,
    apply_patch_filter,
    check_setting,
    choices_pay_clearly,
    choose_patch_filter,
    decode_patch_choices,
    encode_patch_choices,
    patch_choice_prefix,
    search_patch_choices,
    split_patch_choices,
)
from mapsqueeze.codec.tilepoints import keep_inside
from mapsqueeze.errors import ContainerError
from mapsqueeze.geometry import occupancy, patches
from mapsqueeze.geometry.occupancy import patch_option_ious
from mapsqueeze.geometry.patches import patch_option_cells, patch_options, patch_planes
from mapsqueeze.metrics import IOU_VOXEL_M, iou
from mapsqueeze.model import load_model

FRAME = np.array([500_000.0, 4_000_000.0, 50.0])
EXTENT = np.array([12.0, 12.0, 4.0])
FACTORS = (4, 4, 4, 4)  # patches of the last 4 levels: 256 points


def mixed_patches(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(original in world metres, decoder-ordered float32 tile-local output) of 40 cm squares of a ground at
    z = 1.05 m, one patch of 256 points each: the odd patches are the flat ground spread 4 cm across it (a pull
    onto the patch plane helps), the even ones 40 cm tall blocks of vegetation, decoded exactly (a pull empties
    voxels)."""
    rng = np.random.default_rng(seed)
    centres = np.stack(np.meshgrid(np.arange(0.2, 12, 0.4), np.arange(0.2, 12, 0.4)), -1).reshape(-1, 2)
    xy = np.repeat(centres, 256, axis=0) + rng.uniform(-0.2, 0.2, (len(centres) * 256, 2))
    thick = (np.arange(len(xy)) // 256) % 2 == 1
    z = np.where(thick, 1.05, 1.05 + rng.uniform(0, 0.4, len(xy)))
    original = np.column_stack([xy, z])
    z = z + np.where(thick, rng.normal(0, 0.04, len(xy)), 0)
    return original + FRAME, np.column_stack([xy, z]).astype(np.float32)


def test_per_patch_choices_beat_every_single_setting_and_the_search_reports_the_metric():
    original, decoded = mixed_patches()
    search = search_patch_choices(original, decoded, FACTORS, FRAME, EXTENT, OFF)
    choices = search.choices
    assert patch_choice_prefix(search, 10_000) == encode_patch_choices(choices)
    assert len(choices) == len(decoded) // 256
    cloud = apply_patch_choices(decoded, choices, FACTORS, EXTENT)
    chosen = iou(original, cloud.astype(np.float64) + FRAME)
    singles = [iou(original, apply_patch_filter(decoded, byte, FACTORS, EXTENT).astype(np.float64) + FRAME)
               for byte in PATCH_CANDIDATES] + [iou(original, keep_inside(decoded, EXTENT).astype(np.float64) + FRAME)]
    assert chosen > max(singles) + 0.02
    assert set(choices[0::2]) != set(choices[1::2])  # the exact and the thick patches get different options
    before, after = search.before, search.after
    assert before == pytest.approx(iou(original, keep_inside(decoded, EXTENT).astype(np.float64) + FRAME), abs=1e-12)
    assert after == pytest.approx(chosen, abs=1e-12)


def test_patch_options_give_the_bytes_of_each_patch_reworked_alone():
    """One call for every option and patch: the points of `patch_planes` on each patch alone (disk samples numbered
    from the patch's first point, not the cloud's), cropped or not, a flat and a single-point patch included."""
    _, decoded = mixed_patches()
    decoded = decoded[:256 * 12].copy()
    decoded[256 * 3:256 * 4] = decoded[256 * 3]  # every point of patch 3 the same: no plane
    decoded[256 * 5:256 * 6, 2] = 1.0  # patch 5 flat
    decoded[256 * 7:256 * 8, 0] -= 0.3  # patch 7 partly outside the box
    n = len(decoded) // 256
    for upper in (EXTENT, None):
        points, ends = patch_options(decoded, 256, PATCH_OPTIONS, upper)
        assert len(ends) == len(PATCH_OPTIONS) * n
        expected = [patch_planes(decoded[i * 256:(i + 1) * 256], 256, *option, upper)
                    for option in PATCH_OPTIONS for i in range(n)]
        assert np.array_equal(ends, np.cumsum([len(cloud) for cloud in expected]))
        assert np.array_equal(points[:ends[-1]], np.concatenate(expected))
    cropped = patch_options(decoded, 256, PATCH_OPTIONS, EXTENT)[1]
    assert cropped[-1] < ends[-1]  # the box cropped patch 7
    whole = patch_planes(decoded, 256, *PATCH_OPTIONS[4])  # one call over the cloud numbers its samples across it
    assert not np.array_equal(whole[512 * 1:512 * 2], expected[4 * n + 1])


@pytest.mark.parametrize("reserved_part", [4, 1, 10**9])
def test_patch_option_cells_are_the_distinct_voxels_of_the_reworked_points(monkeypatch, reserved_part):
    """The cells the search reads are those of `patch_options`'s points (float32, voxel floor((p + frame) / voxel)),
    each patch's under each option once, whether the first reservation of cells holds them (single-point patches:
    about one cell per point, more than the default reservation) or not (a reservation of one patch's points)."""
    monkeypatch.setattr(patches, "CELLS_RESERVED_PART", reserved_part)
    _, decoded = mixed_patches()
    decoded = decoded[:256 * 20]
    voxel = np.asarray(IOU_VOXEL_M)
    low = np.floor(FRAME / voxel).astype(np.int64) - 2
    shape = np.floor((EXTENT + FRAME) / voxel).astype(np.int64) - low + 3
    for patch in (256, 1):  # single-point patches: more lists than points
        points, ends = patch_options(decoded, patch, PATCH_OPTIONS, EXTENT)
        cells, offsets = patch_option_cells(decoded, patch, PATCH_OPTIONS, EXTENT, FRAME, voxel, low, shape)
        voxels = np.floor((points.astype(np.float64) + FRAME) / voxel).astype(np.int64) - low
        linear = (voxels[:, 0] * shape[1] + voxels[:, 1]) * shape[2] + voxels[:, 2]
        assert len(offsets) == len(ends) + 1 and offsets[-1] == len(cells) > (len(decoded) if patch == 1 else 0)
        for entry, (begin, end) in enumerate(zip(np.concatenate([[0], ends[:-1]]), ends)):
            listed = cells[offsets[entry]:offsets[entry + 1]]
            assert len(set(listed.tolist())) == len(listed) and set(listed.tolist()) == set(linear[begin:end].tolist())



def test_patch_option_cells_fit_when_nearly_every_reworked_point_has_a_voxel_of_its_own():
    """One patch of points far apart on a plane, 5 mm voxels: every extra point but the first (disk sample 0 is
    the point itself) lands in a voxel of its own; the last list (copied cells, then extra points) still fits."""
    rng = np.random.default_rng(0)
    decoded = np.c_[rng.uniform(0.2, 1.8, (8, 2)), np.full(8, 0.5)].astype(np.float32)
    voxel, low, shape = np.full(3, 0.005), np.zeros(3, dtype=np.int64), np.array([402, 402, 202])
    points, ends = patch_options(decoded, 8, PATCH_OPTIONS, np.array([2.0, 2.0, 1.0]))
    cells, offsets = patch_option_cells(decoded, 8, PATCH_OPTIONS, np.array([2.0, 2.0, 1.0]), np.zeros(3), voxel,
                                        low, shape)
    voxels = np.floor(points.astype(np.float64) / voxel).astype(np.int64)
    linear = (voxels[:, 0] * shape[1] + voxels[:, 1]) * shape[2] + voxels[:, 2]
    for entry, (begin, end) in enumerate(zip(np.concatenate([[0], ends[:-1]]), ends)):
        assert sorted(cells[offsets[entry]:offsets[entry + 1]].tolist()) == sorted(set(linear[begin:end].tolist()))
    assert len(cells) > 0.9 * len(points)

def test_the_search_renumbers_the_listed_cells_in_grid_order():
    """The search's arrays span the cells the lists name, numbered in grid order (across blocks of cells and a last
    partial block), each with the original's bit."""
    rng = np.random.default_rng(5)
    grid = (rng.random(8 * 40 + 3) < 0.3).astype(np.uint8)
    cells = rng.integers(0, len(grid), 500).astype(np.int32)
    cells[:2] = len(grid) - 1, 0
    distinct = np.unique(cells)
    renumbered = cells.copy()
    listed = occupancy._compact_cells(grid.copy(), renumbered)
    assert np.array_equal(renumbered, np.searchsorted(distinct, cells))
    assert np.array_equal(listed, grid[distinct])


def test_the_search_grid_spans_the_tile_box_unless_too_large(monkeypatch):
    """The voxel grid of the tile box [0, extent] gives the choices of the points' own box; when the tile box
    holds more voxels than the grid's limit, the points' own box decides whether the search runs."""
    original, decoded = mixed_patches()
    start = np.zeros(len(decoded) // 256, dtype=np.int64)

    def search(upper):
        return patch_option_ious(original, decoded, 256, PATCH_OPTIONS, upper, start, FRAME, IOU_VOXEL_M, 3)

    found = search(EXTENT)
    monkeypatch.setattr(occupancy, "_MAX_OCCUPANCY_VOXELS", 100_000)  # tile box 61 x 61 x 41, points' 60 x 60 x 8
    assert all(np.array_equal(a, b) for a, b in zip(search(EXTENT), found))
    monkeypatch.setattr(occupancy, "_MAX_OCCUPANCY_VOXELS", 20_000)
    assert search(EXTENT) is None


def test_the_copy_weight_puts_extra_points_on_the_original_and_the_bits_weight_shortens_the_stream():
    """The copy weight trades IoU for extra points where the original is (the spread ground patches, odd), more than
    on the exactly decoded vegetation; charging the bits gives a shorter choice stream; both off, or sweeps with
    the bits at no weight, leave the IoU search as it is."""
    original, decoded = mixed_patches()
    start = np.zeros(len(decoded) // 256, dtype=np.int64)
    copies = np.array([option[1] for option in PATCH_OPTIONS])

    def search(*weights):
        return patch_option_ious(original, decoded, 256, PATCH_OPTIONS, EXTENT, start, FRAME, IOU_VOXEL_M, 3,
                                 *weights)

    plain = search()
    assert not copies[plain[0]].any() and plain[2] == pytest.approx(1.0)
    for same in (search(0.0, 0.0, 2), search(0.0, 0.0, 0)):
        assert np.array_equal(same[0], plain[0]) and same[1:] == plain[1:]
    weighted = search(2.0)
    assert copies[weighted[0][1::2]].mean() == 2 and copies[weighted[0][0::2]].mean() < 1
    assert plain[2] - 0.05 < weighted[2] < plain[2] and weighted[1] == plain[1]
    rated = search(0.0, 1e-4, 2)
    assert len(encode_patch_choices(rated[0])) < len(encode_patch_choices(plain[0])) - 10
    assert plain[2] - 0.01 < rated[2] <= plain[2]


def test_the_search_weighs_d_e_and_bits_for_models_with_a_copy_weight_only():
    from mapsqueeze.model import ModelConfig, load_model

    weights = {rate: ModelConfig.for_rate(rate).patch_choice_copy_weight for rate in ("e0", "e1", "e2", "e3")}
    assert weights == {"e0": 0.0, "e1": 0.0, "e2": 0.0, "e3": 2.0}
    assert {name: load_model(name).config.patch_choice_copy_weight for name in weights} == weights  # the shipped
    original, decoded = mixed_patches()
    start = np.zeros(len(decoded) // 256, dtype=np.int64)
    plain = search_patch_choices(original, decoded, FACTORS, FRAME, EXTENT, OFF).choices
    assert np.array_equal(search_patch_choices(original, decoded, FACTORS, FRAME, EXTENT, OFF, 0.0, 3000).choices,
                          plain)
    traded = search_patch_choices(original, decoded, FACTORS, FRAME, EXTENT, OFF, weights["e3"], 3000).choices
    expected = patch_option_ious(original, decoded, 256, PATCH_OPTIONS, EXTENT, start, FRAME, IOU_VOXEL_M, 3,
                                 weights["e3"], IOU_PER_LOG_RATE / (8 * 3000), PATCH_CHOICE_RATE_SWEEPS)[0]
    assert np.array_equal(traded, expected) and not np.array_equal(traded, plain)
    unrated = search_patch_choices(original, decoded, FACTORS, FRAME, EXTENT, OFF, weights["e3"]).choices  # no size
    assert np.array_equal(unrated, patch_option_ious(original, decoded, 256, PATCH_OPTIONS, EXTENT, start, FRAME,
                                                     IOU_VOXEL_M, 3, weights["e3"])[0])
    assert not np.array_equal(unrated, traded)


def test_choices_are_left_off_where_they_do_not_pay():
    """A decode equal to the original gains nothing; a tiny payload makes the stream cost more than it gains."""
    original, decoded = mixed_patches()
    exact = (original - FRAME).astype(np.float32)
    assert patch_choice_prefix(search_patch_choices(original, exact, FACTORS, FRAME, EXTENT, OFF), 10_000) is None
    assert patch_choice_prefix(search_patch_choices(original, decoded, FACTORS, FRAME, EXTENT, OFF), 1) is None
    assert IOU_PER_LOG_RATE == 0.12


def test_the_choice_stream_round_trips_and_corrupt_ones_are_refused():
    weights = 0.7 ** np.arange(len(PATCH_OPTIONS))
    choices = np.random.default_rng(0).choice(len(PATCH_OPTIONS), 500, p=weights / weights.sum())
    prefix = encode_patch_choices(choices)
    payload = prefix + b"latent bytes"
    stream, rest = split_patch_choices(payload, "tile")
    assert rest == b"latent bytes" and np.array_equal(decode_patch_choices(stream, 500, "tile"), choices)
    counts = np.bincount(choices)
    entropy_bits = -(counts[counts > 0] * np.log2(counts[counts > 0] / 500)).sum()
    assert len(prefix) * 8 < entropy_bits + 8 * 20 < 500 * np.log2(len(PATCH_OPTIONS))  # entropy coded
    single = encode_patch_choices(np.full(7, 3))
    assert np.array_equal(decode_patch_choices(split_patch_choices(single, "t")[0], 7, "t"), np.full(7, 3))
    for bad, count in ((stream[:-4], 500), (stream + b"\0\0\0\0", 500), (stream[:3], 500), (stream, 900), (stream, 400)):
        with pytest.raises(ContainerError, match="patch choices"):
            decode_patch_choices(bad, count, "tile")
    with pytest.raises(ContainerError, match="patch choices"):
        split_patch_choices(b"\x7f" + prefix[1:10], "tile")  # a stream longer than the payload
    outside = encode_patch_choices(np.full(5, len(PATCH_OPTIONS)))  # option 11 of 0..10
    with pytest.raises(ContainerError, match="options"):
        decode_patch_choices(split_patch_choices(outside, "t")[0], 5, "t")


def test_the_setting_byte_and_version_of_patch_choices():
    setting = PostFilter.parse(PATCH_CHOICES)
    assert setting.per_patch and setting.patch_levels == 4 and setting.spread_copies == 2
    assert setting.describe() == "patch planes chosen per patch"
    assert check_setting(PATCH_CHOICES, "tile", 6) == PATCH_CHOICES
    with pytest.raises(ContainerError, match="version 5"):
        check_setting(PATCH_CHOICES, "tile", 5)


@pytest.fixture(scope="module")
def cluttered():
    """A 40 m tile of ground, a wall, poles and bushes at UTM coordinates (the learned decode spreads poles and
    bushes over many empty voxels), and the shipped e0 model."""
    rng = np.random.default_rng(0)
    n = 30_000
    ground = np.column_stack([rng.uniform(0, 40, n), rng.uniform(0, 40, n), rng.normal(0.5, 0.02, n)])
    wall = np.column_stack([rng.uniform(0, 40, n // 3), rng.normal(20, 0.02, n // 3), rng.uniform(0.5, 8, n // 3)])
    poles = [np.column_stack([rng.normal(x, 0.05, 400), rng.normal(y, 0.05, 400), rng.uniform(0.5, 5, 400)])
             for x, y in rng.uniform(2, 38, (15, 2))]
    bushes = [rng.normal(centre, 0.6, (800, 3)) for centre in np.column_stack([rng.uniform(2, 38, (10, 2)),
                                                                                 np.full(10, 1.5)])]
    return np.concatenate([ground, wall, *poles, *bushes]) + FRAME, load_model("e0")


def test_the_default_writes_patch_choices_that_raise_iou_and_decode_the_same_on_any_workers(cluttered):
    points, model = cluttered
    default = mapsqueeze.compress(points, model=model, workers=1)
    two_tiles = np.concatenate([points, points + [40.0, 0.0, 0.0]])  # the choices searched by 2 worker processes
    assert mapsqueeze.compress(two_tiles, model=model, workers=2) == mapsqueeze.compress(two_tiles, model=model,
                                                                                         workers=1)
    reader, stream = open_container(default)
    with stream:
        entries = reader.entries
        payloads = [reader.payload(position) for position in range(len(entries))]
    assert reader.version == 7 and PATCH_CHOICES in {entry.post_filter for entry in entries}
    decoded = mapsqueeze.decompress(default, model=model, workers=1)
    assert mapsqueeze.decompress(default, model=model, workers=2).tobytes() == decoded.tobytes()
    # the same embeddings with the choice streams taken out and per-tile patch planes: lower IoU
    records = []
    for entry, payload in zip(entries, payloads):
        if entry.post_filter == PATCH_CHOICES:
            payload = split_patch_choices(payload, "tile")[1]
        setting = PATCH if entry.post_filter == PATCH_CHOICES else entry.post_filter
        records.append(TileRecord(entry.index, entry.n_points, entry.bounds_lo, entry.bounds_hi, entry.coding,
                                  payload, setting))
    per_tile = serialise_container(reader.header, records)
    assert iou(points, decoded) > iou(points, mapsqueeze.decompress(per_tile, model=model, workers=1)) + 0.01
    assert mapsqueeze.info(default).tile_modes.get("network (patch planes chosen per patch)", 0) >= 1


def test_the_paper_mode_and_rate_targets_write_no_choices(cluttered):
    points, model = cluttered
    f16 = mapsqueeze.compress(points, model=model, precision="f16", workers=1)  # choices on f16 embeddings too
    assert PATCH_CHOICES in {entry.post_filter for entry in open_container(f16)[0].entries}
    assert len(mapsqueeze.decompress(f16, model=model, workers=1))
    paper = open_container(mapsqueeze.compress(points, model=model, post_filter="off", workers=1))[0]
    assert {entry.post_filter for entry in paper.entries} == {0}
    reader = open_container(mapsqueeze.compress(points, model=model, bpp=0.5, workers=1))[0]
    assert all(entry.post_filter != PATCH_CHOICES for entry in reader.entries)


def test_a_corrupt_choice_stream_in_a_file_is_a_container_error(cluttered):
    """Choices naming an option beyond PATCH_OPTIONS, the tile's CRC recomputed: refused by the stream's parsing."""
    points, model = cluttered
    reader, stream = open_container(mapsqueeze.compress(points, model=model, workers=1))
    with stream:
        entries = reader.entries
        payloads = [reader.payload(position) for position in range(len(entries))]
    records = []
    for entry, payload in zip(entries, payloads):
        if entry.post_filter == PATCH_CHOICES:
            choices, latent = split_patch_choices(payload, "t")
            count = ByteReader(choices, "t").varint()  # the stream starts with its count of choices
            payload = encode_patch_choices(np.full(count, len(PATCH_OPTIONS))) + latent
        records.append(TileRecord(entry.index, entry.n_points, entry.bounds_lo, entry.bounds_hi, entry.coding,
                                  payload, entry.post_filter))
    with pytest.raises(ContainerError, match="patch choices: choice alphabet 11"):
        mapsqueeze.decompress(serialise_container(reader.header, records), model=model, workers=1)


def test_a_copy_of_e3_under_another_name_searches_with_e3s_copy_weight(cluttered, tmp_path):
    """The copy weight is the model config's (`patch_choice_copy_weight`), not looked up by name: e3 copied under
    another name writes e3's tile payloads; with the weight set to 0 the search, and so the payload, differs."""
    import json
    import shutil

    from mapsqueeze.model.shipped import CONFIG_FILE, SHIPPED_DIR

    points, _ = cluttered
    copies = {}
    for name, weight in (("my-e3", 2.0), ("e3-unweighted", 0.0)):
        copies[name] = tmp_path / name
        shutil.copytree(SHIPPED_DIR / "e3", copies[name])
        config = json.loads((copies[name] / CONFIG_FILE).read_text())
        (copies[name] / CONFIG_FILE).write_text(json.dumps({**config, "name": name,
                                                            "patch_choice_copy_weight": weight}))

    def tiles(model) -> list[tuple[int, bytes]]:
        reader, stream = open_container(mapsqueeze.compress(points, model=model, workers=1))
        with stream:
            return [(entry.post_filter, reader.payload(position)) for position, entry in enumerate(reader.entries)]

    shipped = tiles("e3")
    assert PATCH_CHOICES in {setting for setting, _ in shipped}
    assert tiles(str(copies["my-e3"])) == shipped
    assert tiles(str(copies["e3-unweighted"])) != shipped


def test_choices_pay_clearly_only_where_they_would_pay_for_a_fraction_of_the_payload():
    choices = np.zeros(100, dtype=np.int64)
    growth = len(encode_patch_choices(choices))
    at_full = IOU_PER_LOG_RATE * np.log((2000 + growth) / 2000)
    at_fraction = IOU_PER_LOG_RATE * np.log((2000 * CLEAR_PAY_FRACTION + growth) / (2000 * CLEAR_PAY_FRACTION))
    between = PatchChoiceSearch(choices, 0.3, 0.3 + (at_full + at_fraction) / 2)
    assert patch_choice_prefix(between, 2000) is not None and not choices_pay_clearly(between, 2000)
    assert choices_pay_clearly(PatchChoiceSearch(choices, 0.3, 0.3 + 1.01 * at_fraction), 2000)
    assert not choices_pay_clearly(None, 2000)


def test_the_encoder_chooses_the_tile_setting_only_where_the_choices_do_not_pay_clearly(monkeypatch):
    """`tilejobs._patch_choices`: choices searched from CHOICE_SEARCH_START's option; where they pay clearly the
    tile's own setting is never chosen; where they do not (a decode equal to the original, a one-byte payload), it
    is, and the search runs again from its option, as a search from that setting gives."""
    from types import SimpleNamespace

    from mapsqueeze.codec import tilejobs

    chosen = []
    monkeypatch.setattr(tilejobs, "choose_patch_filter", lambda *args: chosen.append(choose_patch_filter(*args))
                        or chosen[-1])
    model = SimpleNamespace(config=SimpleNamespace(upsampling_factors=FACTORS, patch_choice_copy_weight=0.0))
    original, decoded = mixed_patches()
    local = (original - FRAME).astype(np.float32)
    setting, search = tilejobs._patch_choices(original, local, FRAME, EXTENT, decoded, model, 10_000, True)
    assert setting == CHOICE_SEARCH_START and not chosen
    start = search_patch_choices(original, decoded, FACTORS, FRAME, EXTENT, CHOICE_SEARCH_START, 0.0, 10_000)
    assert np.array_equal(search.choices, start.choices) and choices_pay_clearly(search, 10_000)
    setting, search = tilejobs._patch_choices(original, local, FRAME, EXTENT, local, model, 1, True)  # 1 byte
    assert chosen == [setting] == [OFF]  # the exact decode's setting
    again = search_patch_choices(original, local, FACTORS, FRAME, EXTENT, OFF, 0.0, 1)
    assert np.array_equal(search.choices, again.choices) and search.before == again.before
    assert patch_choice_prefix(search, 1) is None
