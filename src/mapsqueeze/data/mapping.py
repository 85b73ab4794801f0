"""The paper's map building (Sec. IV-A): aggregate range-filtered scans with their poses, voxel-filter at 10 cm,
cut 40 x 40 x 15 m submaps around key poses, and store them as a dataset (PLY files + manifest.json).

The functions are general so that real sequences and the LiDAR simulator share them:
`preprocess_scan` -> `transform` -> `aggregate_map` -> `submap_centers` -> `build_submaps` -> `write_dataset`.

Dataset layout: `manifest.json` plus one binary PLY per submap holding float32 x, y, z in metres *relative to the
submap's origin* (its box's lower corner, float64 in the manifest), so world coordinates of any size (UTM) keep
sub-millimetre precision: world = origin + local. Simulated submaps add per-point `intensity` (float32),
`label` and `instance` (uint16) properties; training reads x, y, z only.
"""

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapsqueeze.errors import DataError
from mapsqueeze.geometry.tiling import TILE_SIZE_M, to_local
from mapsqueeze.geometry.voxel import VoxelAccumulator, as_lengths
from mapsqueeze.io import atomic_write_bytes, read_points, validate_points, write_points

MIN_RANGE_M = 2.0
MAX_RANGE_M = 20.0
VOXEL_SIZE_M = 0.1
SUBMAP_SPACING_M = 15.0
SUBMAP_DZ_M = 4.0
"""Submap boxes are centred `dz` metres above the key pose (the reference's `grid.dz`): with the 15 m box height
they span z in [pose_z - 3.5, pose_z + 11.5], i.e. the ground ~1.7 m below a car-mounted LiDAR and the buildings
and trees above it."""

MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "mapsqueeze-submaps"
MANIFEST_VERSION = 1
SPLITS = ("train", "val", "test")
VALIDATION_EVERY = 10
"""Every 10th submap of a training source (index % 10 == 9) goes to the validation split."""
TEST_SOURCES = frozenset({"kitti-08"})
"""Sources whose submaps form the test split: KITTI sequence 08, the paper's test sequence."""


def range_mask(
    points_sensor: np.ndarray, min_range: float = MIN_RANGE_M, max_range: float = MAX_RANGE_M
) -> np.ndarray:
    """(N,) bool: which points of a scan (sensor frame, metres) lie at a distance in (min_range, max_range)."""
    distances = np.linalg.norm(points_sensor, axis=1)
    return (distances > min_range) & (distances < max_range)


def preprocess_scan(
    points_sensor: np.ndarray, min_range: float = MIN_RANGE_M, max_range: float = MAX_RANGE_M
) -> np.ndarray:
    """Points of a scan (sensor frame, metres) whose distance to the sensor is in (min_range, max_range)."""
    return points_sensor[range_mask(points_sensor, min_range, max_range)]


def transform(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Apply a 4 x 4 rigid transform to (N, 3) points: R @ p + t, float64."""
    pose = np.asarray(pose, dtype=np.float64)
    # einsum, not `@`: a multi-threaded BLAS call on an (N, 3) x (3, 3) product is ~10x slower on busy machines
    return np.einsum("ij,nj->ni", pose[:3, :3], np.asarray(points, dtype=np.float64)) + pose[:3, 3]


def aggregate_map(
    scans: Iterable[tuple[np.ndarray, np.ndarray]],
    min_range: float = MIN_RANGE_M,
    max_range: float = MAX_RANGE_M,
    voxel_size: float = VOXEL_SIZE_M,
) -> np.ndarray:
    """World map from (points in sensor frame (N, 3), sensor-to-world pose (4, 4)) pairs, (M, 3) float64 metres.

    Each scan is range-filtered, transformed and folded into a voxel accumulator at once, so memory grows with
    the map's occupied voxels, not with the raw points. The result is exactly the centroid voxel filter
    (`geometry.voxel.voxel_filter`, world-aligned grid) of all transformed points, sorted by voxel index.
    """
    accumulator = VoxelAccumulator(voxel_size)
    for points, pose in scans:
        accumulator.add(transform(preprocess_scan(points, min_range, max_range), pose))
    return accumulator.centroids()


def submap_centers(poses: np.ndarray, spacing: float = SUBMAP_SPACING_M, rule: str = "travelled") -> np.ndarray:
    """Indices of the key poses that submaps are centred on, ascending.

    rule "travelled": the first pose, then each first pose at least `spacing` metres of travelled path (3-D)
    beyond the previous key pose. Revisited places get submaps again on every pass.
    rule "coverage": the reference implementation's rule: the first pose not yet covered becomes a key pose and
    covers every pose within `spacing` metres of it (horizontal distance), so revisits add no submaps.
    """
    if not spacing > 0:
        raise DataError(f"submap spacing must be positive, got {spacing} m")
    positions = np.asarray(poses, dtype=np.float64)[:, :3, 3]
    if len(positions) == 0:
        return np.empty(0, dtype=np.int64)
    if rule == "travelled":
        travelled = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(positions, axis=0), axis=1))]
        keys = [0]
        while True:
            following = keys[-1] + int(np.searchsorted(travelled[keys[-1] :], travelled[keys[-1]] + spacing))
            if following >= len(positions):
                return np.array(keys, dtype=np.int64)
            keys.append(following)
    if rule == "coverage":
        from scipy.spatial import cKDTree  # imported here: `mapsqueeze --help` stays fast

        tree = cKDTree(positions[:, :2])
        covered = np.zeros(len(positions), dtype=bool)
        keys = []
        for index in range(len(positions)):
            if not covered[index]:
                keys.append(index)
                covered[tree.query_ball_point(positions[index, :2], spacing)] = True
        return np.array(keys, dtype=np.int64)
    raise DataError(f"unknown submap-centre rule {rule!r} (travelled or coverage)")


def submap_bounds(
    center_xyz: np.ndarray, size: float | Iterable[float] = TILE_SIZE_M, dz: float = SUBMAP_DZ_M
) -> np.ndarray:
    """(2, 3) float64 lower and upper corner of the box of `size` metres centred `dz` metres above `center_xyz`."""
    middle = np.asarray(center_xyz, dtype=np.float64).reshape(3) + np.array([0.0, 0.0, dz])
    half = as_lengths(size, "submap size") / 2
    return np.stack([middle - half, middle + half])


def crop_submap(
    map_points: np.ndarray,
    center_xyz: np.ndarray,
    size: float | Iterable[float] = TILE_SIZE_M,
    dz: float = SUBMAP_DZ_M,
) -> np.ndarray:
    """Map points in the half-open box `submap_bounds(center_xyz, size, dz)` ([lower, upper) per axis)."""
    return map_points[crop_mask(map_points, center_xyz, size, dz)]


def crop_mask(
    map_points: np.ndarray,
    center_xyz: np.ndarray,
    size: float | Iterable[float] = TILE_SIZE_M,
    dz: float = SUBMAP_DZ_M,
) -> np.ndarray:
    """(M,) bool: which map points `crop_submap` keeps."""
    lower, upper = submap_bounds(center_xyz, size, dz)
    return np.all((map_points >= lower) & (map_points < upper), axis=1)


@dataclass
class Submap:
    """A box of a map: world points (float64 metres) plus where it came from. `pose` is None for grid tiles;
    `attributes`: per-point fields (name -> (N,) array, e.g. simulated intensity, label, instance)."""

    points: np.ndarray
    center: np.ndarray  # key-pose position, or the box centre of a grid tile (metres)
    bounds: np.ndarray  # (2, 3) lower and upper box corner (metres)
    source: str  # sequence or map name
    index: int  # position among the source's submaps
    pose: np.ndarray | None = None  # (4, 4) key pose
    split: str = ""  # train / val / test; filled by `assign_split` when empty
    attributes: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.split = self.split or assign_split(self.source, self.index)

    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def origin(self) -> np.ndarray:
        """float64 origin of the stored local coordinates: the box's lower corner."""
        return self.bounds[0]


def assign_split(source: str, index: int) -> str:
    """Deterministic split: TEST_SOURCES -> test; else every VALIDATION_EVERY-th submap -> val; else train."""
    if source in TEST_SOURCES:
        return "test"
    return "val" if index % VALIDATION_EVERY == VALIDATION_EVERY - 1 else "train"


def build_submaps(
    map_points: np.ndarray,
    poses: np.ndarray,
    source: str,
    spacing: float = SUBMAP_SPACING_M,
    size: float | Iterable[float] = TILE_SIZE_M,
    dz: float = SUBMAP_DZ_M,
    rule: str = "travelled",
    split: str = "",
) -> list[Submap]:
    """Submaps of `map_points` (M, 3) around the key poses `submap_centers(poses, spacing, rule)`.

    Empty boxes are skipped (indices stay those of the key poses' order). `split` forces one split for all;
    empty means `assign_split`. Submap points keep the map's order. Candidates come from a map index sorted by
    (x, y) cell, so a whole sequence's map is not rescanned for every submap.
    """
    size = as_lengths(size, "submap size")
    map_points = np.asarray(map_points, dtype=np.float64)
    cell = float(size[:2].max())
    cells = np.floor(map_points[:, :2] / cell).astype(np.int64)
    order = np.lexsort((cells[:, 1], cells[:, 0]))  # x cell, then y cell
    cells = cells[order]
    submaps = []
    for number, pose_index in enumerate(submap_centers(poses, spacing, rule)):
        pose = np.asarray(poses[pose_index], dtype=np.float64)
        bounds = submap_bounds(pose[:3, 3], size, dz)
        low_cell, high_cell = np.floor(bounds[:, :2] / cell).astype(np.int64)
        candidates = []
        for cell_x in range(low_cell[0], high_cell[0] + 1):
            start, stop = np.searchsorted(cells[:, 0], [cell_x, cell_x + 1])
            start, stop = start + np.searchsorted(cells[start:stop, 1], [low_cell[1], high_cell[1] + 1])
            candidates.append(order[start:stop])
        points = crop_submap(map_points[np.sort(np.concatenate(candidates))], pose[:3, 3], size, dz)
        if len(points):
            submaps.append(Submap(points, pose[:3, 3].copy(), bounds, source, number, pose, split))
    return submaps


def _file_name(source: str, index: int) -> str:
    safe = "".join(char if char.isalnum() or char in "-_." else "_" for char in source)
    return f"{safe}-{index:05d}.ply"


def _read_manifest(path: Path) -> dict:
    try:
        manifest = json.loads(path.read_text())
    except OSError as exc:
        raise DataError(f"{path}: cannot read manifest ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise DataError(f"{path}: corrupt manifest ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        raise DataError(f"{path}: not a mapsqueeze submap manifest")
    if manifest.get("version") != MANIFEST_VERSION:
        raise DataError(
            f"{path}: manifest version {manifest.get('version')!r} unsupported (expected {MANIFEST_VERSION})"
        )
    return manifest


_PARTIAL, _BACKUP = ".partial-", ".replaced-"
"""Prefixes of a submap file written but not yet in place, and of the file it replaces until the manifest is
written (hidden names: `io.point_cloud_files` lists no hidden file)."""


def _commit(out_dir: Path, manifest_path: Path, manifest: dict, records: list[dict], meta: dict) -> None:
    """Put the written submaps (`_PARTIAL` names) in place and write the manifest that names them. The files they
    replace are kept under `_BACKUP` names until the manifest is written, and put back should anything fail."""
    written = {record["source"] for record in records}
    replaced = {record["file"] for record in manifest["submaps"] if record["source"] in written}
    manifest["sources"].update({source: meta for source in sorted(written)})
    kept = [record for record in manifest["submaps"] if record["source"] not in written]
    manifest["submaps"] = sorted(kept + records, key=lambda record: (record["source"], record["index"]))
    header = json.dumps({key: manifest[key] for key in ("format", "version", "sources")}, indent=1)[: -len("\n}")]
    entries = ",\n  ".join(json.dumps(record) for record in manifest["submaps"])  # one line per submap
    backups, placed = [], []
    try:
        for record in records:
            final = out_dir / record["file"]
            if final.exists():
                os.replace(final, out_dir / f"{_BACKUP}{record['file']}")
                backups.append(record["file"])
            os.replace(out_dir / f"{_PARTIAL}{record['file']}", final)
            placed.append(final)
        atomic_write_bytes(manifest_path, f'{header},\n "submaps": [\n  {entries}\n ]\n}}\n'.encode())
    except BaseException as exc:
        for final in placed:
            final.unlink(missing_ok=True)
        for name in backups:
            os.replace(out_dir / f"{_BACKUP}{name}", out_dir / name)
        if isinstance(exc, OSError):
            raise DataError(f"{manifest_path}: cannot write ({exc.strerror or exc})") from None
        raise
    for name in backups:
        (out_dir / f"{_BACKUP}{name}").unlink(missing_ok=True)
    for stale in replaced - {record["file"] for record in records}:  # a rebuilt source with fewer submaps
        (out_dir / stale).unlink(missing_ok=True)


def _record(submap: Submap, name: str) -> dict:
    """The manifest entry of a submap written as `name`."""
    return {
        "file": name,
        "source": submap.source,
        "index": submap.index,
        "split": submap.split,
        "n_points": submap.n_points,
        "origin": submap.origin.tolist(),
        "center": np.asarray(submap.center, dtype=np.float64).tolist(),
        "bounds": submap.bounds.tolist(),
        "pose": None if submap.pose is None else np.asarray(submap.pose, dtype=np.float64).tolist(),
    }


def write_dataset(out_dir: str | os.PathLike, submaps: Iterable[Submap], meta: dict) -> Path:
    """Write each submap as `<source>-<index>.ply` (float32 x, y, z relative to its origin, then its attributes)
    and update `manifest.json`; returns the manifest path. All writes are atomic.

    The manifest keeps the entries of sources not written now, so sequences can be added one call at a time;
    a source written again replaces its previous entries. `meta` (JSON-serialisable, e.g. the build
    parameters) is stored per source written. Submaps are written under temporary names and take their own, with
    the manifest, once all are written, so a write that fails or is interrupted leaves the dataset as it was (and
    removes the directory when it made it and left it empty). Two submaps of one file name are a DataError.
    """
    out_dir = Path(out_dir)
    created = not out_dir.exists()
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"{out_dir}: cannot create the dataset directory ({exc.strerror or exc})") from None
    manifest_path = out_dir / MANIFEST_NAME
    manifest = (
        _read_manifest(manifest_path)
        if manifest_path.exists()
        else {"format": MANIFEST_FORMAT, "version": MANIFEST_VERSION, "sources": {}, "submaps": []}
    )
    records = []
    try:
        for submap in submaps:
            if submap.split not in SPLITS:
                raise DataError(f"submap {submap.source}/{submap.index}: unknown split {submap.split!r}")
            name = _file_name(submap.source, submap.index)
            if name in {record["file"] for record in records} or name.startswith(_PARTIAL):
                raise DataError(f"submap {submap.source}/{submap.index}: its file name {name} is taken (another "
                                f"submap's, or a temporary file's); rename the source")
            size = submap.bounds[1] - submap.bounds[0]
            records.append(_record(submap, name))  # first: its partial file is removed should the write fail
            write_points(out_dir / f"{_PARTIAL}{name}", to_local(submap.points, submap.origin, size),
                         attributes=submap.attributes)
        written = {record["source"] for record in records}
        kept = [record for record in manifest["submaps"] if record["source"] not in written]
        clash = {record["file"] for record in kept} & {record["file"] for record in records}
        if clash:
            raise DataError(f"{out_dir}: {', '.join(sorted(clash))} belong(s) to another source's submaps; rename "
                            "the source")
        _commit(out_dir, manifest_path, manifest, records, meta)
    except BaseException:  # an error, Ctrl-C or SIGTERM: the dataset as it was, without a folder made now
        for record in records:
            (out_dir / f"{_PARTIAL}{record['file']}").unlink(missing_ok=True)
        if created and not any(out_dir.iterdir()):
            out_dir.rmdir()
        raise
    return manifest_path


@dataclass(frozen=True)
class SubmapRecord:
    """A manifest entry; `local_points()` / `load()` read its PLY file."""

    path: Path
    source: str
    index: int
    split: str
    n_points: int
    origin: np.ndarray
    center: np.ndarray
    bounds: np.ndarray
    pose: np.ndarray | None

    def local_points(self) -> np.ndarray:
        """(n_points, 3) float32 metres relative to `origin`, as stored."""
        points = read_points(self.path)
        if len(points) != self.n_points:
            raise DataError(f"{self.path}: {len(points):,} points, manifest says {self.n_points:,}")
        return points.astype(np.float32)

    def load(self) -> Submap:
        """The submap with world coordinates (origin + local, float64)."""
        world = validate_points(self.origin + self.local_points().astype(np.float64), name=str(self.path))
        return Submap(world, self.center, self.bounds, self.source, self.index, self.pose, self.split)


@dataclass(frozen=True)
class SubmapDataset:
    """A dataset directory: per-source build metadata and the submap records, ordered by (source, index)."""

    directory: Path
    sources: dict[str, dict]
    records: list[SubmapRecord]

    def split(self, name: str) -> list[SubmapRecord]:
        """The records of one split (train, val or test), or every record for "all" (e.g. a held-out dataset)."""
        if name == "all":
            return list(self.records)
        if name not in SPLITS:
            raise DataError(f"unknown split {name!r} (one of {', '.join(SPLITS)}, all)")
        return [record for record in self.records if record.split == name]


def read_dataset(directory: str | os.PathLike) -> SubmapDataset:
    """Load a dataset's manifest (written by `write_dataset`); submap points are read on demand."""
    directory = Path(directory)
    manifest_path = directory / MANIFEST_NAME
    if not manifest_path.is_file():
        raise DataError(f"{directory}: no {MANIFEST_NAME} (not a dataset directory)")
    manifest = _read_manifest(manifest_path)
    try:
        records = [
            SubmapRecord(
                path=directory / entry["file"],
                source=str(entry["source"]),
                index=int(entry["index"]),
                split=str(entry["split"]),
                n_points=int(entry["n_points"]),
                origin=np.array(entry["origin"], dtype=np.float64).reshape(3),
                center=np.array(entry["center"], dtype=np.float64).reshape(3),
                bounds=np.array(entry["bounds"], dtype=np.float64).reshape(2, 3),
                pose=None if entry["pose"] is None else np.array(entry["pose"], dtype=np.float64).reshape(4, 4),
            )
            for entry in manifest["submaps"]
        ]
    except (KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{manifest_path}: malformed submap entry ({exc!r})") from None
    return SubmapDataset(directory, dict(manifest.get("sources", {})), records)
