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

Version 2 has its own fixture (`tests/data/attributes_v2.msq`, `test_attribute_field.py`).

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
from mapsqueeze.codec.container import TileCoding, open_container

DATA = Path(__file__).parent / "data"
NETWORK, RAW, OCTREE = TileCoding.network, TileCoding.raw, TileCoding.octree

FIXTURES = {
    1: {"tiles": [(NETWORK, 0), (NETWORK, 0), (RAW, 0)],
        "digests": {"count": 4729,
                    "points": "19adf2309b842eca9754e84381d3b52e96868b9008232028202fad5f61377591",
                    "classification": "79d6daa0f8d02e01d98c506359bde825fecc2ba95b37646134fa95bd9ff864e7",
                    "intensity": "454cb72b4d5718bb1354715e8a7e61e7602d79e95fa2e5704aa91f0e5d238590"}},
    3: {"tiles": [(NETWORK, 0), (OCTREE, 0), (RAW, 0)],
        "digests": {"count": 23313,
                    "points": "30db319dda89f21fdfd21d7dcc255a0c93871e8576d30c33e2e585b2b6268a79",
                    "classification": "39e65f00ec311f3c3377c3976059125a3f4cf906c2aa8d7a8817e0fc60f76d9a",
                    "intensity": "5a26c1a485d87b23664f91de5c7382e2e1336f4a371ecb6725399929c11c7538"}},
    4: {"tiles": [(NETWORK, 0x1F), (NETWORK, 0x07), (RAW, 0)],
        "digests": {"count": 121349,
                    "points": "204f810773944c13a49f7258e05ebab72d398402ab1c1476e6e8ebb2088fd8f0",
                    "classification": "66a940062e2301edf728a7818d2a11a4c92c370171fa7374a052313c820231be",
                    "intensity": "d7c26e580e728ba502199f0bdc3c5587645569f017a0fc073a1f83c89f310ed1"}},
    5: {"tiles": [(NETWORK, 0x20), (NETWORK, 0x20), (RAW, 0)],
        "digests": {"count": 99078,
                    "points": "b86c7139928d7e4ebf33ff0ce3be435ae1763adca578265b0d4038453ea60376",
                    "classification": "2a6d500101015bf6b383e6bfd8e9da28ee6bc7747c19a0d98e97aae9e0ef84fa",
                    "intensity": "ab15894403250ad37c0c7f0d90895f584eddf84ea4b3070b12a741fe1e4408d7"}},
    6: {"tiles": [(NETWORK, 0x80), (NETWORK, 0x20), (RAW, 0)],
        "digests": {"count": 101115,
                    "points": "673d1d82d3955cdcf7b3768337697a2fa21e93a6309bbabefa97040a290eba34",
                    "classification": "b0b5271913e51c3e9857b9fd668c9563ec3a1492d9e14335bfc90697390d52a9",
                    "intensity": "fa7bb915444d798733435cfbe874a5b22aedec6eaca6ab939911efc4b73d3937"}},
}


def fixture_tool():
    """tests/data/make_compat_fixture.py as a module (its digests are the ones recorded above)."""
    spec = importlib.util.spec_from_file_location("make_compat_fixture", DATA / "make_compat_fixture.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("version", sorted(FIXTURES))
def test_files_of_older_commits_decode_to_the_recorded_digests(version):
    data = (DATA / f"compat_v{version}.msq").read_bytes()
    reader, stream = open_container(data)
    with stream:
        assert reader.version == version
        assert reader.header.n_points == 4729
        assert [(entry.coding, entry.post_filter) for entry in reader.entries] == FIXTURES[version]["tiles"]
        assert bool(reader.attribute_entries)
    cloud = mapsqueeze.decompress_cloud(data, workers=1)
    assert fixture_tool().digests(cloud) == FIXTURES[version]["digests"]


def test_every_older_readable_version_has_a_fixture():
    """Each version the reader takes, except the newest (which this code writes), has a fixture."""
    from mapsqueeze.codec.container import READABLE_VERSIONS

    assert (DATA / "attributes_v2.msq").is_file()
    assert set(READABLE_VERSIONS) - {max(READABLE_VERSIONS)} <= set(FIXTURES) | {2}
