"""Crafted .msq files with valid checksums: only validation can catch them (docs/format.md, "Integrity").

Each case rewrites header fields or tile-table entries and recomputes every CRC; every outcome must be a typed
MapsqueezeError or a correct decode. The fuzz test runs the decoder in a subprocess under a memory cap.
"""

import dataclasses
import os
import struct
import subprocess
import sys
import textwrap
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mapsqueeze
from mapsqueeze.codec.container import (
    DEFAULT_MAX_TILE_POINTS,
    TileCoding,
    TileRecord,
    open_container,
    serialise_container,
)
from mapsqueeze.codec.entropy import ByteReader
from mapsqueeze.codec.header import DefaultCount
from mapsqueeze.codec.postfilter import PATCH_CHOICES, PATCH_OPTIONS, encode_patch_choices
from mapsqueeze.codec.rawtile import encode_raw_tile
from mapsqueeze.errors import ContainerError, DecodeLimitError, MapsqueezeError, ModelError
from mapsqueeze.io import MAX_ABS_COORDINATE_M
from mapsqueeze.model import load_model

UTM = np.array([500_000.123, 4_000_000.456, 50.0])
TILE = np.array([8.0, 8.0, 4.0])


@pytest.fixture(scope="module")
def model_dir(tiny_model_dir):
    return tiny_model_dir


@pytest.fixture(scope="module")
def model(model_dir):
    return load_model(model_dir)


@pytest.fixture(scope="module")
def map_points():
    rng = np.random.default_rng(0)
    ground = np.column_stack([rng.uniform(0, 14, 3000), rng.uniform(0, 7, 3000), rng.normal(0.5, 0.03, 3000)])
    post = np.column_stack([rng.normal(13, 0.05, 4), rng.normal(1, 0.05, 4), rng.uniform(4.5, 7.5, 4)])
    return np.concatenate([ground, post]) + UTM


@pytest.fixture(scope="module")
def compressed(map_points, model):
    return mapsqueeze.compress(map_points, model=model, precision="f16", fallback=False)  # network tiles


def parts(data: bytes):
    """(header, table records) of a container, the records carrying their payloads."""
    reader, stream = open_container(data)
    with stream:
        records = [TileRecord(e.index, e.n_points, e.bounds_lo, e.bounds_hi, e.coding, reader.payload(p),
                              e.post_filter) for p, e in enumerate(reader.entries)]
        return reader.header, records


def craft(data: bytes, header_changes: dict | None = None, tile_changes: dict | None = None,
          position: int = 0, flags: int = 0) -> bytes:
    """The container with header fields / one tile's record replaced and every CRC recomputed."""
    header, records = parts(data)
    header = dataclasses.replace(header, **(header_changes or {}))
    records[position] = dataclasses.replace(records[position], **(tile_changes or {}))
    out = bytearray(serialise_container(header, records))
    if flags:  # version 7: the flags varint at byte 6 (one byte below 128)
        assert out[6] == 0 and flags < 128
        out[6] = flags
        return with_head_crc(out)
    return bytes(out)


def head_layout(data: bytes) -> tuple[int, int, int]:
    """(first header byte, header bytes, table bytes) of a version 7 file whose flags varint is one byte."""
    lengths = ByteReader(bytes(data[7:27]), "preamble")
    body, table = lengths.varint(), lengths.varint()
    return 7 + 20 - lengths.remaining, body, table


def with_head_crc(data: bytearray) -> bytes:
    """A version 7 file with the CRC of its header and table recomputed."""
    start, body, table = head_layout(data)
    struct.pack_into("<I", data, start + body + table, zlib.crc32(bytes(data[:start + body + table])))
    return bytes(data)


def test_crafting_without_changes_keeps_the_bytes(compressed):
    assert craft(compressed) == compressed


def test_raw_tile_with_no_points_is_refused(compressed, model):
    header, records = parts(compressed)
    position = next(p for p, r in enumerate(records) if r.coding is TileCoding.raw)
    empty = encode_raw_tile(np.zeros((0, 3)), TILE)
    data = craft(compressed, tile_changes={"payload": empty}, position=position)
    with pytest.raises(ContainerError, match="raw payload holds 0 points"):
        mapsqueeze.decompress(data, model=model)


def test_header_feature_channels_must_match_the_model(compressed, model):
    data = craft(compressed, header_changes={"n_features": 4})
    with pytest.raises(ContainerError, match="4 embedding channels.*3"):
        mapsqueeze.decompress(data, model=model)


def test_decompression_bomb_is_refused_with_the_option_that_allows_it(map_points, model):
    raw_only = mapsqueeze.compress(map_points[-4:], model=model, precision="f16")  # one sparse raw tile
    header, records = parts(raw_only)
    claim = DEFAULT_MAX_TILE_POINTS + 1
    bomb = craft(raw_only, header_changes={"n_points": claim}, tile_changes={"n_points": claim})
    with pytest.raises(DecodeLimitError, match="max-tile-points"):
        mapsqueeze.decompress(bomb, model=model)
    with pytest.raises(DecodeLimitError, match="max-tile-points"):
        mapsqueeze.decompress(raw_only, model=model, n_points=claim)
    # The limit is an option: a small claim passes when allowed, and the raw payload's count must match.
    assert len(mapsqueeze.decompress(raw_only, model=model, max_tile_points=4)) == 4
    with pytest.raises(DecodeLimitError, match="max-tile-points"):
        mapsqueeze.decompress(raw_only, model=model, max_tile_points=3)
    liar = craft(raw_only, header_changes={"n_points": 1000}, tile_changes={"n_points": 1000})
    with pytest.raises(ContainerError, match="holds 4 points.*1000"):
        mapsqueeze.decompress(liar, model=model)


@pytest.mark.parametrize("changes", [
    {"header_changes": {"origin": (1e300, 0.0, 0.0)}},
    {"header_changes": {"origin": (-MAX_ABS_COORDINATE_M, 0.0, 0.0)}},
    {"tile_changes": {"index": (2**31 - 1, 0, 0)}, "position": -1},
    {"header_changes": {"tile_size": (1e9, 8.0, 4.0)}},
])
def test_absurd_coordinates_are_refused_by_the_api(compressed, model, changes):
    data = craft(compressed, **changes)
    with pytest.raises(ContainerError, match="absurd|tile size"):
        mapsqueeze.decompress(data, model=model)
    with pytest.raises(ContainerError):
        mapsqueeze.info(data)


def test_reserved_flags_are_refused(compressed, model):
    with pytest.raises(ContainerError, match="reserved flags 0x0004"):
        mapsqueeze.decompress(craft(compressed, flags=4), model=model)


def test_model_id_resolves_only_to_shipped_models(compressed, model_dir, tmp_path, monkeypatch):
    # A file naming a model folder (absolute, or relative to the working directory) does not load it.
    for name in (str(model_dir), "tiny"):
        data = craft(compressed, header_changes={"model_id": name})
        monkeypatch.chdir(model_dir.parent)
        with pytest.raises(ModelError, match="not a shipped model.*--model"):
            mapsqueeze.decompress(data)
        assert len(mapsqueeze.decompress(data, model=str(model_dir))) > 0  # the user's --model works


@pytest.fixture(scope="module")
def shipped_file(map_points):
    return mapsqueeze.compress(map_points, model="e0", precision="q", workers=1)


def test_a_shipped_model_is_named_by_a_digest_prefix_and_its_config(shipped_file, map_points, model_dir):
    from mapsqueeze.model.shipped import shipped_weights_sha256

    reader, stream = open_container(shipped_file)
    stream.close()
    header = reader.header
    assert reader.version == 7 and header.model_id == "e0" and header.weights_sha256 == shipped_weights_sha256("e0")
    assert (header.subsampling_dist_m, header.tile_size, header.n_features) == (3.0, (40.0, 40.0, 15.0), 3)
    start, body, _ = head_layout(shipped_file)
    assert shipped_file[start + 2:start + 4] == b"e0"
    assert shipped_file[start + 4:start + 12] == bytes.fromhex(header.weights_sha256)[:8]
    assert len(mapsqueeze.decompress(shipped_file, n_points=len(map_points))) == len(map_points)
    # A custom model stores its whole digest and its grid: 24 + 33 more header bytes.
    custom = craft(shipped_file, header_changes={"model_id": "e0x"})
    assert head_layout(custom)[1] == body + 1 + 24 + 33
    with pytest.raises(ModelError, match="not a shipped model"):
        mapsqueeze.decompress(custom)


def test_a_shipped_model_of_other_weights_needs_a_model_of_its_prefix_and_an_unknown_one_is_refused(shipped_file):
    """A file written by a build whose e0 has other weights still reads (info) and decodes with a model whose
    digest, or one of the digests of its earlier versions with the same decoder, starts with the file's prefix;
    this build's e0 is refused with the ModelError naming --model."""
    import types

    from mapsqueeze.codec.decompress import check_model
    from mapsqueeze.model.config import SAME_DECODER_KEY
    from mapsqueeze.model.shipped import shipped_weights_sha256

    start, _, _ = head_layout(shipped_file)
    other = bytearray(shipped_file)
    other[start + 11] ^= 1  # the digest prefix's last byte
    other = with_head_crc(other)
    prefix = bytes(other[start + 4:start + 12]).hex()
    summary = mapsqueeze.info(other)
    assert summary.model_id == "e0" and summary.weights_sha256 == prefix
    with pytest.raises(ModelError, match="pass the model used for compression"):
        mapsqueeze.decompress(other)
    reader, stream = open_container(other)
    stream.close()
    body = reader.header.serialise()  # the prefix is written back in a shipped model's layout
    assert body[2:4] == b"e0" and body[4:12] == bytes.fromhex(prefix)
    def model(sha: str, *same_decoder: str):
        return types.SimpleNamespace(weights_sha256=sha, model_id="e0",
                                     config=types.SimpleNamespace(extra={SAME_DECODER_KEY: list(same_decoder)}))

    check_model(model(prefix + "0" * 48), reader.header, "f")
    # a model whose encoder was retrained from weights of that prefix (the same decoder), and one of other lineage
    check_model(model(shipped_weights_sha256("e0"), "1" * 64, prefix + "0" * 48), reader.header, "f")
    with pytest.raises(ModelError):
        check_model(model(shipped_weights_sha256("e0"), "1" * 64), reader.header, "f")
    unknown = bytearray(shipped_file)
    unknown[start + 3:start + 4] = b"9"  # e9: no such shipped model
    with pytest.raises(ContainerError, match="names shipped model 'e9', which this mapsqueeze does not ship"):
        mapsqueeze.info(with_head_crc(unknown))
    reserved = bytearray(shipped_file)
    reserved[start] |= 0x80
    with pytest.raises(ContainerError, match="reserved header flags 0x80"):
        mapsqueeze.info(with_head_crc(reserved))


def test_a_file_of_an_earlier_shipped_model_with_the_same_decoder_decodes_and_info_says_so(map_points, run_cli,
                                                                                            tmp_path):
    """A file the earlier e1 wrote (its digest prefix; the shipped e1 lists that digest, its encoder alone
    retrained) decodes without --model to the points the shipped e1's own file of the same payloads gives, and
    `info` names the shipped model instead of asking for --model PATH."""
    from mapsqueeze.model import load_model
    from mapsqueeze.model.config import SAME_DECODER_KEY

    (earlier,) = load_model("e1").config.extra[SAME_DECODER_KEY]
    data = mapsqueeze.compress(map_points, model="e1", precision="q", workers=1)
    start, _, _ = head_layout(data)
    old = bytearray(data)
    old[start + 4:start + 12] = bytes.fromhex(earlier)[:8]
    old = with_head_crc(old)
    assert mapsqueeze.info(old).weights_sha256 == earlier[:16]
    assert np.array_equal(mapsqueeze.decompress(old, workers=1), mapsqueeze.decompress(data, workers=1))
    (tmp_path / "old.msq").write_bytes(old)
    code, out, _ = run_cli("info", str(tmp_path / "old.msq"))
    assert code == 0 and "an earlier version of the shipped model" in out and "--model PATH" not in out


def test_good_file_still_decodes(compressed, model, map_points):
    assert len(mapsqueeze.decompress(compressed, model=model, n_points=len(map_points))) == len(map_points)


# --- property-based mutation of header fields and tile-table entries (checksums recomputed) ---------------------

_DECODE_UNDER_CAP = textwrap.dedent("""
    import resource, sys
    resource.setrlimit(resource.RLIMIT_AS, ({cap}, {cap}))
    import mapsqueeze
    from mapsqueeze.errors import MapsqueezeError
    from mapsqueeze.model import load_model
    model = load_model(sys.argv[2])
    for path in sys.argv[3:]:
        try:
            points = mapsqueeze.decompress(open(path, "rb").read(), model=model)
            print("decoded", len(points), flush=True)
        except MapsqueezeError as exc:
            print("error", type(exc).__name__, flush=True)
""")

_HEADER_FIELDS = st.one_of(
    st.builds(lambda v: {"n_points": v}, st.integers(0, 2**64 - 1)),
    st.builds(lambda v: {"n_tiles": v}, st.integers(0, 2**32 - 1)),
    st.builds(lambda v: {"n_features": v}, st.integers(0, 255)),
    st.builds(lambda v: {"subsampling_dist_m": v}, st.floats(allow_nan=True, allow_infinity=True)),
    st.builds(lambda v: {"raw_step_m": v}, st.floats(allow_nan=True, allow_infinity=True)),
    st.builds(lambda v: {"tile_size": v}, st.tuples(*[st.floats(-1e12, 1e12)] * 3)),
    st.builds(lambda v: {"origin": v}, st.tuples(*[st.floats(allow_nan=True, allow_infinity=True)] * 3)),
    st.builds(lambda v: {"model_id": v}, st.text(max_size=40)),
)
_TILE_FIELDS = st.one_of(
    st.builds(lambda v: {"index": v}, st.tuples(*[st.integers(-2**31 + 1, 2**31 - 1)] * 3)),
    st.builds(lambda v: {"n_points": v}, st.integers(0, 2**32 - 1)),
    st.builds(lambda v: {"bounds_lo": v}, st.tuples(*[st.integers(0, 65535)] * 3)),
    st.builds(lambda v: {"bounds_hi": v}, st.tuples(*[st.integers(0, 65535)] * 3)),
    st.builds(lambda v: {"coding": v}, st.sampled_from(list(TileCoding))),
    st.builds(lambda v: {"payload": v}, st.binary(max_size=64)),
)
FUZZ_EXAMPLES = int(os.environ.get("MAPSQUEEZE_FUZZ_EXAMPLES", "25"))
MEMORY_CAP_BYTES = 3 << 30


@pytest.mark.parametrize("layout", ["custom", "shipped"])
def test_fuzzed_headers_and_tables_give_typed_errors_or_decodes(layout, compressed, shipped_file, model_dir,
                                                               tmp_path):
    """Both version 7 header layouts: a custom model's (whole digest, grid stored) and a shipped model's."""
    from mapsqueeze.model.shipped import SHIPPED_DIR

    if layout == "shipped":
        compressed, model_dir = shipped_file, SHIPPED_DIR / "e0"
    crafted: list[bytes] = []

    @settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(st.lists(_HEADER_FIELDS, max_size=2), _TILE_FIELDS, st.integers(0, 100), st.booleans())
    def mutate(header_fields, tile_fields, position, sum_points):
        header_changes = {"default_count": DefaultCount.input}  # decodes to the stored counts, checked below
        header_changes.update({k: v for fields in header_fields for k, v in fields.items()})
        header, records = parts(compressed)
        if "n_points" in tile_fields and sum_points and "n_points" not in header_changes:
            moved = records[position % len(records)].n_points
            header_changes["n_points"] = header.n_points - moved + tile_fields["n_points"]  # keep the sum valid
        try:
            crafted.append(craft(compressed, header_changes, tile_fields, position % len(records)))
        except (ValueError, OverflowError, struct.error, UnicodeEncodeError):
            pass  # a field the writer cannot even store

    mutate()
    outcomes = decode_under_cap(model_dir, tmp_path, crafted)
    for data, (kind, value) in zip(crafted, outcomes):
        if kind == "decoded":  # a field the decoder does not depend on (e.g. a bounds box the points still fit)
            assert int(value) == parts(data)[0].n_points
    assert len(outcomes) >= FUZZ_EXAMPLES // 2


# --- property-based mutation of version 6 choice streams (payload CRCs recomputed) ------------------------------

@pytest.fixture(scope="module")
def with_choices(compressed):
    """`compressed` decoding to the input counts: every network tile with patch choices (a
    stream of one option per embedding point, all options used) before its latent payload."""
    header, records = parts(compressed)
    changed = []
    for record in records:
        if record.coding is TileCoding.network:
            embedding, _ = header.latent.decode(record.payload, record.n_points, "tile")
            choices = np.arange(len(embedding)) % len(PATCH_OPTIONS)
            record = dataclasses.replace(record, payload=encode_patch_choices(choices) + record.payload,
                                         post_filter=PATCH_CHOICES)
        changed.append(record)
    return serialise_container(dataclasses.replace(header, default_count=DefaultCount.input), changed)


def decode_under_cap(model_dir, tmp_path, crafted: list[bytes]) -> list[tuple[str, str]]:
    """(outcome, value) of decoding each file in a subprocess under MEMORY_CAP_BYTES: ("decoded", count) or
    ("error", MapsqueezeError subclass); fails on any other exception, a crash or a hang."""
    paths = []
    for number, data in enumerate(crafted):
        paths.append(tmp_path / f"crafted{number}.msq")
        paths[-1].write_bytes(data)
    script = _DECODE_UNDER_CAP.format(cap=MEMORY_CAP_BYTES)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    result = subprocess.run([sys.executable, "-c", script, "x", str(model_dir), *map(str, paths)],
                            capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    outcomes = [tuple(line.split(" ", 1)) for line in result.stdout.split("\n")[:-1]]
    assert len(outcomes) == len(paths)
    return outcomes


_STREAM_EDITS = st.lists(st.tuples(st.sampled_from(["set", "insert", "delete", "cut"]), st.integers(0, 63),
                                   st.integers(0, 255)), min_size=1, max_size=3)


def test_fuzzed_choice_streams_give_typed_errors_or_decodes(with_choices, model_dir, model, tmp_path):
    header, records = parts(with_choices)
    assert open_container(with_choices)[0].version == 7
    assert len(mapsqueeze.decompress(with_choices, model=model)) == header.n_points  # the unmutated file decodes
    network = [p for p, record in enumerate(records) if record.post_filter == PATCH_CHOICES]
    crafted: list[bytes] = []

    @settings(max_examples=FUZZ_EXAMPLES, deadline=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(_STREAM_EDITS, st.integers(0, 100))
    def mutate(edits, position):
        position = network[position % len(network)]
        payload = bytearray(records[position].payload)
        for kind, offset, value in edits:  # offsets within the stream's first 64 bytes: its length, count, histogram
            offset = min(offset, len(payload))
            if kind == "set" and offset < len(payload):
                payload[offset] = value
            elif kind == "insert":
                payload.insert(offset, value)
            elif kind == "delete" and offset < len(payload):
                del payload[offset]
            elif kind == "cut":
                del payload[offset:]
        crafted.append(craft(with_choices, tile_changes={"payload": bytes(payload)}, position=position))

    mutate()
    for data, (kind, value) in zip(crafted, decode_under_cap(model_dir, tmp_path, crafted)):
        if kind == "decoded":  # edits that leave a decodable stream (or shift the latent payload): input counts
            assert int(value) == header.n_points
        else:
            assert kind == "error"
    assert len(crafted) >= FUZZ_EXAMPLES // 2
