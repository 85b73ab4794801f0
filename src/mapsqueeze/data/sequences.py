"""Readers of LiDAR scan sequences (scans + poses + optional labels) in a few on-disk layouts.

Layouts, tried in this order by `open_sequences`:
- `kitti-dataset`: a KITTI odometry / SemanticKITTI root holding `sequences/XX/` folders (each read as below).
- `kitti-sequence`: `velodyne/*.bin`, `calib.txt` (line `Tr: ...`, 12 numbers) and camera-frame poses in
  `poses.txt` (SemanticKITTI) or `../../poses/XX.txt` (KITTI odometry), 12 numbers (3 x 4 [R|t]) per line.
  The LiDAR-frame pose is inv(Tr) @ P_cam @ Tr. Optional `labels/*.label` (SemanticKITTI, uint32 per point,
  semantic class = label & 0xFFFF) remove dynamic and unreliable points (see DROPPED_CLASSES).
- `scan-folder`: any scan files `mapsqueeze.io` reads (.bin, .pcd.bin, .ply, .pcd, .las, .laz, .npy), in
  natural file-name order, with LiDAR-frame poses: 12 numbers (3 x 4 [R|t]) or 16 numbers (4 x 4) per line,
  one line per scan, found under a common name (POSES_FILE_NAMES, else a single `*poses*.txt`).

An explicit `poses_file` is always read as LiDAR-frame poses (e.g. KISS-ICP output) and overrides the above.
Without poses, `estimate_poses` runs KISS-ICP (optional extra `mapsqueeze[poses]`).
"""

import dataclasses
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapsqueeze.errors import DataError, MapsqueezeError
from mapsqueeze.io import SUPPORTED_FORMATS, read_points

DROPPED_CLASSES: frozenset[int] = frozenset({0, 1, *range(252, 260)})
"""SemanticKITTI classes removed from maps: 0 unlabeled, 1 outlier, 252-259 moving objects (moving car,
bicyclist, person, motorcyclist, on-rails, bus, truck, other vehicle). Parked vehicles (10 car etc.) and all
other static classes stay, as in the paper's maps; the reference implementation kept exactly 1 < label < 200."""

POSES_FILE_NAMES = ("poses.txt", "poses_lidar.txt", "poses_kitti.txt")
"""Pose-file names looked for in a scan folder before falling back to a single `*poses*.txt`."""

_SCAN_SUFFIXES = tuple(f".{name}" for name in SUPPORTED_FORMATS if "-" not in name)


@dataclass(frozen=True)
class ScanSequence:
    """One sequence of scans with their sensor-to-world poses (LiDAR frame) and optional per-point labels."""

    name: str
    layout: str
    scan_paths: tuple[Path, ...]
    poses: np.ndarray | None  # (N, 4, 4) float64, sensor frame -> world; None until estimated
    label_paths: tuple[Path, ...] | None = None

    def __len__(self) -> int:
        return len(self.scan_paths)

    def read_scan(self, index: int) -> np.ndarray:
        """Scan `index` in its sensor frame, (N, 3) float64 metres, without DROPPED_CLASSES when labelled."""
        points = read_points(self.scan_paths[index])
        if self.label_paths is None:
            return points
        classes = read_semantic_labels(self.label_paths[index])
        if len(classes) != len(points):
            raise DataError(
                f"{self.label_paths[index]}: {len(classes):,} labels for {len(points):,} points in "
                f"{self.scan_paths[index].name}"
            )
        return points[~np.isin(classes, list(DROPPED_CLASSES))]

    def scans(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(points in sensor frame, 4 x 4 pose) for each scan in order; the poses must be known."""
        if self.poses is None:
            raise DataError(f"{self.name}: no poses (give a poses file or estimate them)")
        for index, pose in enumerate(self.poses):
            yield self.read_scan(index), pose

    def with_poses(self, poses: np.ndarray) -> "ScanSequence":
        """A copy with the given (N, 4, 4) poses, checked against the number of scans."""
        return dataclasses.replace(self, poses=_check_pose_count(np.asarray(poses, dtype=np.float64), self))


def read_semantic_labels(path: Path) -> np.ndarray:
    """SemanticKITTI `.label` file -> (N,) semantic class per point (lower 16 bits of each uint32)."""
    if not path.is_file():
        raise DataError(f"{path}: label file missing")
    raw = path.read_bytes()
    if len(raw) % 4:
        raise DataError(f"{path}: size {len(raw)} bytes is not a whole number of uint32 labels")
    return np.frombuffer(raw, dtype="<u4") & 0xFFFF


def read_poses(path: Path) -> np.ndarray:
    """Pose file, one pose per line as 12 (3 x 4 [R|t], row-major) or 16 (4 x 4) numbers -> (N, 4, 4)."""
    try:
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
        values = np.array(rows, dtype=np.float64)
    except OSError as exc:
        raise DataError(f"{path}: cannot read poses ({exc.strerror or exc})") from None
    except ValueError:
        raise DataError(f"{path}: poses must be lines of 12 or 16 numbers") from None
    if values.ndim != 2 or values.shape[1] not in (12, 16) or not np.isfinite(values).all():
        raise DataError(f"{path}: poses must be lines of 12 or 16 finite numbers")
    poses = np.tile(np.eye(4), (len(values), 1, 1))
    poses[:, :3, :] = values.reshape(len(values), -1, 4)[:, :3, :]
    return poses


def read_kitti_calibration(path: Path) -> np.ndarray:
    """The 4 x 4 LiDAR-to-camera transform `Tr` from a KITTI `calib.txt`."""
    if not path.is_file():
        raise DataError(f"{path}: calibration missing (KITTI camera-frame poses need its Tr line)")
    for line in path.read_text().splitlines():
        key, _, numbers = line.partition(":")
        if key.strip() == "Tr":
            try:
                values = np.array(numbers.split(), dtype=np.float64)
            except ValueError:
                break
            if values.shape == (12,):
                return np.vstack([values.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
            break
    raise DataError(f"{path}: no valid 'Tr:' line of 12 numbers")


def camera_to_lidar_poses(camera_poses: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """KITTI camera-frame poses -> LiDAR-frame poses: inv(Tr) @ P_cam @ Tr for each pose."""
    return np.linalg.inv(tr) @ camera_poses @ tr


def _natural_key(path: Path) -> list:
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def _check_pose_count(poses: np.ndarray, sequence: "ScanSequence") -> np.ndarray:
    if poses.shape != (len(sequence), 4, 4):
        raise DataError(f"{sequence.name}: {len(poses)} poses for {len(sequence)} scans")
    return poses


def _kitti_sequence(folder: Path, poses_file: Path | None, use_labels: bool) -> ScanSequence:
    scans = tuple(sorted((folder / "velodyne").glob("*.bin"), key=_natural_key))
    if not scans:
        raise DataError(f"{folder / 'velodyne'}: no .bin scans")
    labels = None
    if use_labels and (folder / "labels").is_dir():
        labels = tuple(folder / "labels" / f"{scan.stem}.label" for scan in scans)
    sequence = ScanSequence(f"kitti-{folder.name}", "kitti-sequence", scans, None, labels)
    if poses_file is not None:
        return sequence.with_poses(read_poses(poses_file))
    for camera_poses in (folder / "poses.txt", folder.parent.parent / "poses" / f"{folder.name}.txt"):
        if camera_poses.is_file():
            tr = read_kitti_calibration(folder / "calib.txt")
            return sequence.with_poses(camera_to_lidar_poses(read_poses(camera_poses), tr))
    return sequence


def _detect_kitti_dataset(folder: Path, poses_file: Path | None, use_labels: bool) -> list[ScanSequence] | None:
    sequences = sorted(path for path in (folder / "sequences").glob("*") if (path / "velodyne").is_dir())
    if not sequences:
        return None
    if poses_file is not None:
        raise DataError(f"{folder}: holds {len(sequences)} sequences; --poses applies to one sequence folder")
    return [_kitti_sequence(path, None, use_labels) for path in sequences]


def _detect_kitti_sequence(folder: Path, poses_file: Path | None, use_labels: bool) -> list[ScanSequence] | None:
    if not (folder / "velodyne").is_dir():
        return None
    return [_kitti_sequence(folder, poses_file, use_labels)]


def _find_poses_file(folder: Path) -> Path | None:
    for name in POSES_FILE_NAMES:
        if (folder / name).is_file():
            return folder / name
    candidates = sorted(folder.glob("*poses*.txt"))
    if len(candidates) > 1:
        names = ", ".join(path.name for path in candidates)
        raise DataError(f"{folder}: several pose files ({names}); choose one with --poses")
    return candidates[0] if candidates else None


def _detect_scan_folder(folder: Path, poses_file: Path | None, use_labels: bool) -> list[ScanSequence] | None:
    scans = tuple(
        sorted(
            (path for path in folder.iterdir() if path.is_file() and path.name.lower().endswith(_SCAN_SUFFIXES)),
            key=_natural_key,
        )
    )
    if not scans:
        return None
    sequence = ScanSequence(folder.resolve().name, "scan-folder", scans, None)
    poses_file = poses_file or _find_poses_file(folder)
    return [sequence if poses_file is None else sequence.with_poses(read_poses(poses_file))]


LAYOUTS: dict[str, Callable[[Path, Path | None, bool], list[ScanSequence] | None]] = {
    "kitti-dataset": _detect_kitti_dataset,
    "kitti-sequence": _detect_kitti_sequence,
    "scan-folder": _detect_scan_folder,
}
"""Layout name -> detector(folder, poses_file, use_labels) returning the sequences, or None if not that layout."""


def open_sequences(
    folder: str | Path, poses_file: str | Path | None = None, use_labels: bool = True
) -> list[ScanSequence]:
    """The scan sequences in `folder` (first matching layout of LAYOUTS); poses may still be None."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"{folder}: no such folder")
    poses_file = None if poses_file is None else Path(poses_file)
    if poses_file is not None and not poses_file.is_file():
        raise DataError(f"{poses_file}: no such poses file")
    for detect in LAYOUTS.values():
        sequences = detect(folder, poses_file, use_labels)
        if sequences is not None:
            return sequences
    raise DataError(
        f"{folder}: no scans found (expected sequences/XX/velodyne, velodyne/*.bin or scan files "
        f"{', '.join(_SCAN_SUFFIXES)})"
    )


def estimate_poses(sequence: ScanSequence, progress: Callable[[Sequence], Sequence] | None = None) -> np.ndarray:
    """LiDAR-frame poses (N, 4, 4) of the sequence's scans estimated with KISS-ICP, relative to the first scan.

    Uses KISS-ICP's default configuration (max range 100 m, voxel 1 m) without deskewing (scans carry no
    per-point timestamps). `progress` optionally wraps the scan index range (e.g. a progress bar).
    Needs the optional dependency: pip install "mapsqueeze[poses]" (kiss-icp).
    """
    try:
        from kiss_icp.config import load_config
        from kiss_icp.kiss_icp import KissICP
    except ImportError:
        raise MapsqueezeError('pose estimation needs KISS-ICP: pip install "mapsqueeze[poses]"') from None
    config = load_config(None)
    config.data.deskew = False
    odometry = KissICP(config)
    indices = range(len(sequence))
    poses = np.empty((len(sequence), 4, 4))
    no_timestamps = np.empty(0)
    for index in progress(indices) if progress else indices:
        odometry.register_frame(sequence.read_scan(index), no_timestamps)
        poses[index] = odometry.last_pose
    return poses

