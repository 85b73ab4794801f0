"""Write a backward-compatibility fixture `tests/data/compat_vN.msq` with the mapsqueeze on PYTHONPATH and print
the digests of its default decode, as `tests/test_compat_fixtures.py` checks them.

Run it with the source tree of the commit that wrote version N (the commits and commands are listed in
`tests/test_compat_fixtures.py`):

    git worktree add /tmp/fx_vN COMMIT
    PYTHONPATH=/tmp/fx_vN/src OMP_NUM_THREADS=1 python tests/data/make_compat_fixture.py N tests/data/compat_vN.msq

The map: three crops of the real KITTI submap (shared/data/real/submaps/kitti_hdl64_6scans.ply) moved into three
tiles of a 2 x 2 grid in UTM-sized coordinates: a dense 12 x 12 m crop (network), a sparse 3 x 3 m crop (raw) and
a thinned 12 x 12 m crop (raw, octree or network, as the writer's mode decision picks), each well inside its tile
(no decoded point near a face shared with another tile), with an intensity (u16) and a classification (u8).
"""

import hashlib
import sys
from pathlib import Path

import numpy as np

KITTI = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real" / "submaps" / "kitti_hdl64_6scans.ply"
UTM = np.array([500000.0, 4000000.0, 100.0])
OPTIONS = {3: {"model": "e1", "bpp": 1.5},  # a rate target that gives the thinned crop an octree
           4: {"post_filter": True}}  # version 4's writer chose neighbour-plane post-filters on request only
"""compress options per version besides the attributes (the defaults otherwise)."""


def read_kitti(path: Path = KITTI) -> np.ndarray:
    """The submap's float32 x, y, z (binary little-endian PLY, no other property) as float64."""
    data = path.read_bytes()
    body = data.index(b"end_header\n") + len(b"end_header\n")
    return np.frombuffer(data[body:], dtype="<f4").reshape(-1, 3).astype(np.float64)


def crop(points: np.ndarray, x0: float, y0: float, side: float, every: int) -> np.ndarray:
    inside = ((points[:, 0] >= x0) & (points[:, 0] < x0 + side) &
              (points[:, 1] >= y0) & (points[:, 1] < y0 + side))
    return points[inside][::every]


def fixture_cloud() -> tuple[np.ndarray, dict[str, np.ndarray]]:
    kitti = read_kitti()
    dense = crop(kitti, -6.0, -6.0, 12.0, 4)
    sparse = crop(kitti, 10.0, 10.0, 3.0, 60) + [50.0, 0.0, 0.0]
    thinned = crop(kitti, -20.0, 0.0, 12.0, 12) + [14.0, 50.0, 0.0]
    local = np.concatenate([dense, sparse, thinned])
    intensity = np.clip(np.round((local[:, 2] + 6.0) * 30.0 + 20.0 * np.sin(local[:, 0])), 0, 255).astype(np.uint16)
    classification = np.where(local[:, 2] < -1.5, 2, 6).astype(np.uint8)
    return local + UTM, {"intensity": intensity, "classification": classification}


def digests(cloud) -> dict[str, object]:
    """Point count and sha256 of the decoded points (float64, C order) and of each attribute's values."""
    points = np.ascontiguousarray(cloud.points, dtype=np.float64)
    return {"count": len(points), "points": hashlib.sha256(points.tobytes()).hexdigest(),
            **{name: hashlib.sha256(np.ascontiguousarray(values).tobytes()).hexdigest()
               for name, values in sorted(cloud.attributes.items())}}


def main(version: int, out: Path) -> None:
    import mapsqueeze
    from mapsqueeze.io.atomic import atomic_write_bytes

    points, attributes = fixture_cloud()
    options = OPTIONS.get(version, {})
    data = mapsqueeze.compress(points, attributes=attributes, workers=1, **options)
    written = int.from_bytes(data[4:6], "little")
    if written != version:
        raise SystemExit(f"this mapsqueeze wrote version {written}, not {version}")
    atomic_write_bytes(out, data)
    print(f"{out}: {len(points)} input points, {len(data)} bytes, version {written}")
    print(digests(mapsqueeze.decompress_cloud(out.read_bytes(), workers=1)))


if __name__ == "__main__":
    main(int(sys.argv[1]), Path(sys.argv[2]))
