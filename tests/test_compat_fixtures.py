"""Backward compatibility: .msq files written by older commits decode, with this reader, to exactly the points and
attributes that an older decoder gave them (sha256 of the default decode's float64 points and of each attribute's
values; `decompress_cloud(data, workers=1)`).

Each fixture `tests/data/compat_vN.msq` holds the map of `tests/data/make_compat_fixture.py` (4,729 points: three
crops of the real KITTI submap in three tiles, with an intensity and a classification), written by the last commit
whose default `compress` wrote version N (version 4: the last one whose newest version was 4, with
`post_filter=True`; version 3 with `model="e1", bpp=1.5`, which gives an octree tile), with

    git worktree add /tmp/fx_vN COMMIT
    PYTHONPATH=/tmp/fx_vN/src OMP_NUM_THREADS=1 python tests/data/make_compat_fixture.py N tests/data/compat_vN.msq

which prints the digests of that commit's own decode:

| version | written by | tiles (coding, post-filter byte) | digests taken with |
|---|---|---|---|
| 1 | b9b5e2a (last before version 2, 6ba14fe) | network, network, raw | 3c189ac (see below) |
| 3 | 3c189ac (last before version 5, 07be7e4) | network, octree, raw | 3c189ac |
| 4 | 3c189ac | network 0x1f, network 0x07, raw | 3c189ac |
| 5 | c4fe0ae (last before version 6, 4007bf6) | network 0x20, network 0x20, raw | c4fe0ae |
| 6 | d88b8a7 | network 0x80 (patch choices), network 0x20, raw | d88b8a7 |
| 7 | 1b67df4 (the last before version 8, written only with constant attributes: later commits write these bytes) | network 0x80, network 0x20, raw | 1b67df4 |

Version 2 has its own fixture (`tests/data/attributes_v2.msq`, `test_attribute_field.py`).

Versions 3 and 4 have two attribute stream layouts (docs/format.md, "Attributes"): dbe03a0 added the support's CRC
without a version change. `tests/data/compat_v3_nocrc.msq` and `compat_v4_nocrc.msq` hold the layout without it,
written with the same command by 82847f7 (the source of 417ee14, the first commit to write version 3; 3278f80, the
last before dbe03a0, writes the same bytes) and 0dc44a0 (the first to write version 4): network, network, raw
tiles, post-filter bytes 0, 0, 0 and 0x07, 0x07, 0. Their attribute digests are those of the writers' own decode,
which 3278f80 (dbe03a0^) gives too; their point digests are those of every decoder since bb02e9e (bb02e9e, 3c189ac,
c4fe0ae, d88b8a7 with `attributes=False`: the decoders from dbe03a0 until the reader of both layouts refused their
attributes). bb02e9e's forward moves the network's output by at most 2.9e-6 m (8,872 of 49,573 points of the
version 3 file differ from 3278f80's decode), which the neighbour-plane post-filter of the version 4 file carries to
up to 4.8 cm (20,011 of 99,018 points); the voxel supports, and so the attribute values, stay the same.

Version 1: the writer b9b5e2a decoded its file with the torch forward, to other digests (points 03c9cec2...,
classification c3917f30..., intensity cabfa34e...). The network's output differs from it by at most 2.9e-6 m
(the numpy forward of f9a1e70, then its row groups of bb02e9e: 20,990 of the 23,750 points of the first tile), and
a version 1 file decodes each tile to its input count by thinning that output along a Morton order
(`resample_to_count`), which turns these last-bit differences into other kept points (3,422 of 3,882 points of the
first tile, up to 2.2 m apart). The digests are those of every decoder since bb02e9e (bb02e9e, 3c189ac, c4fe0ae,
d88b8a7 give the same).
"""

import importlib.util
from pathlib import Path

import pytest

import mapsqueeze
from mapsqueeze.codec.container import AttributeSection, TileCoding, open_container
from mapsqueeze.codec.entropy import ByteReader
from mapsqueeze.errors import ContainerError

DATA = Path(__file__).parent / "data"
NETWORK, RAW, OCTREE = TileCoding.network, TileCoding.raw, TileCoding.octree

FIXTURES = {
    "compat_v1": {"version": 1, "tiles": [(NETWORK, 0), (NETWORK, 0), (RAW, 0)],
        "digests": {"count": 4729,
                    "points": "19adf2309b842eca9754e84381d3b52e96868b9008232028202fad5f61377591",
                    "classification": "79d6daa0f8d02e01d98c506359bde825fecc2ba95b37646134fa95bd9ff864e7",
                    "intensity": "454cb72b4d5718bb1354715e8a7e61e7602d79e95fa2e5704aa91f0e5d238590"}},
    "compat_v3": {"version": 3, "tiles": [(NETWORK, 0), (OCTREE, 0), (RAW, 0)],
        "digests": {"count": 23313,
                    "points": "30db319dda89f21fdfd21d7dcc255a0c93871e8576d30c33e2e585b2b6268a79",
                    "classification": "39e65f00ec311f3c3377c3976059125a3f4cf906c2aa8d7a8817e0fc60f76d9a",
                    "intensity": "5a26c1a485d87b23664f91de5c7382e2e1336f4a371ecb6725399929c11c7538"}},
    "compat_v4": {"version": 4, "tiles": [(NETWORK, 0x1F), (NETWORK, 0x07), (RAW, 0)],
        "digests": {"count": 121349,
                    "points": "204f810773944c13a49f7258e05ebab72d398402ab1c1476e6e8ebb2088fd8f0",
                    "classification": "66a940062e2301edf728a7818d2a11a4c92c370171fa7374a052313c820231be",
                    "intensity": "d7c26e580e728ba502199f0bdc3c5587645569f017a0fc073a1f83c89f310ed1"}},
    "compat_v5": {"version": 5, "tiles": [(NETWORK, 0x20), (NETWORK, 0x20), (RAW, 0)],
        "digests": {"count": 99078,
                    "points": "b86c7139928d7e4ebf33ff0ce3be435ae1763adca578265b0d4038453ea60376",
                    "classification": "2a6d500101015bf6b383e6bfd8e9da28ee6bc7747c19a0d98e97aae9e0ef84fa",
                    "intensity": "ab15894403250ad37c0c7f0d90895f584eddf84ea4b3070b12a741fe1e4408d7"}},
    "compat_v6": {"version": 6, "tiles": [(NETWORK, 0x80), (NETWORK, 0x20), (RAW, 0)],
        "digests": {"count": 101115,
                    "points": "673d1d82d3955cdcf7b3768337697a2fa21e93a6309bbabefa97040a290eba34",
                    "classification": "b0b5271913e51c3e9857b9fd668c9563ec3a1492d9e14335bfc90697390d52a9",
                    "intensity": "fa7bb915444d798733435cfbe874a5b22aedec6eaca6ab939911efc4b73d3937"}},
    "compat_v7": {"version": 7, "tiles": [(NETWORK, 0x80), (NETWORK, 0x20), (RAW, 0)],
        "digests": {"count": 104751,
                    "points": "bb1590af768b47c097647815f5bb46b195cc91f42d116c88148a8d156c8f71c3",
                    "classification": "b848ccf21df31b868c515950717ad252b4ab6b5e83cb0d1a9a1b807b3338d2f4",
                    "intensity": "2af675b6fd1f512c332eb7042ee9d33f0c1ea9d610eaa71bc27c0b868a96f629"}},
    "compat_v3_nocrc": {"version": 3, "tiles": [(NETWORK, 0), (NETWORK, 0), (RAW, 0)],
                        "digests": {"count": 49573,
                                    "points": "2d9e99226b0b8b520be21e25f678b2d7f5049a3a62a1cd2fe4fd12a3a31e2ac6",
                                    "classification":
                                        "6607dd8280facde85e4e820294a369e0872a5540bf049adff50f937a82dc4b69",
                                    "intensity": "0be6662c7fe5de468fe6e82734205556ee9d512766ad97396a52069a2b607de7"}},
    "compat_v4_nocrc": {"version": 4, "tiles": [(NETWORK, 0x07), (NETWORK, 0x07), (RAW, 0)],
                        "digests": {"count": 99018,
                                    "points": "5a126ac0b2e7113663f6d71fb256fd60499296f122afe1c2c24d074e4cf3041b",
                                    "classification":
                                        "2a70deb6a8678ade4d66b37040efbc3bd66e5364f53315d531136a1dfe9a8504",
                                    "intensity": "808e9a246b4ee19474f73f00619eb9357bcd76cab8ed26000f984e27949f6d5b"}},
}


def fixture_tool():
    """tests/data/make_compat_fixture.py as a module (its digests are the ones recorded above)."""
    spec = importlib.util.spec_from_file_location("make_compat_fixture", DATA / "make_compat_fixture.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("name", sorted(FIXTURES))
def test_files_of_older_commits_decode_to_the_recorded_digests(name):
    data = (DATA / f"{name}.msq").read_bytes()
    reader, stream = open_container(data)
    with stream:
        assert reader.version == FIXTURES[name]["version"]
        assert reader.header.n_points == 4729
        assert [(entry.coding, entry.post_filter) for entry in reader.entries] == FIXTURES[name]["tiles"]
        assert bool(reader.attribute_entries)
    cloud = mapsqueeze.decompress_cloud(data, workers=1)
    assert fixture_tool().digests(cloud) == FIXTURES[name]["digests"]


def without_support_crcs(data: bytes) -> bytes:
    """The file with every attribute stream in the layout without the support's CRC (the 4 bytes after its voxel
    count removed), all else the same."""
    reader, stream = open_container(data)
    with stream:
        streams = []
        for position in range(len(reader.entries)):
            coded = reader.attribute_stream(position)
            count = ByteReader(coded, "stream")
            count.varint()
            count_end = len(coded) - count.remaining
            streams.append(coded[:count_end] + coded[count_end + 4:])
        payload_end = reader.entries[-1].offset + reader.entries[-1].length
        rewritten = data[:payload_end] + AttributeSection(reader.attribute_schema, streams).serialise()
    assert open_container(rewritten)[0].version == reader.version
    return rewritten


def test_only_versions_3_and_4_read_attribute_streams_without_the_support_crc():
    """The same streams without the CRC decode to the same values in a version 4 file, and are refused in a version
    5 file (no writer of version 5 or later left the CRC out)."""
    legacy = without_support_crcs((DATA / "compat_v4.msq").read_bytes())
    assert fixture_tool().digests(mapsqueeze.decompress_cloud(legacy, workers=1)) == FIXTURES["compat_v4"]["digests"]
    with pytest.raises(ContainerError, match="does not match"):
        mapsqueeze.decompress_cloud(without_support_crcs((DATA / "compat_v5.msq").read_bytes()), workers=1)


def test_every_older_readable_version_has_a_fixture():
    """Each version the reader takes, except the newest (which this code writes), has a fixture."""
    from mapsqueeze.codec.container import READABLE_VERSIONS

    assert (DATA / "attributes_v2.msq").is_file()
    assert set(READABLE_VERSIONS) - {max(READABLE_VERSIONS)} <= {f["version"] for f in FIXTURES.values()} | {2}
