"""Plain numeric tables: KITTI .bin (+ SemanticKITTI .label beside it), nuScenes .pcd.bin, NumPy .npy.

- KITTI .bin: float32 N x 4 (x, y, z, reflectance). A SemanticKITTI label file (uint32 a point: semantic label in
  the low 16 bits, instance id in the high 16) is read from `NAME.label` beside the scan or from
  `../labels/NAME.label` when the scan lies in a `velodyne` folder, as attributes `label` and `instance` (uint16);
  writing a cloud with `label` writes `NAME.label` beside the scan.
- nuScenes .pcd.bin: float32 N x 5 (x, y, z, intensity, ring); ring, the laser of each point, is read as uint8
  when every value is a whole number 0..255 (so that it is coded as categories), else as float32.
- .npy: floating-point N x 3 (x, y, z in metres), or N x (3 + k): columns 3.. are attributes `column3`, `column4`,
  ... (names are not stored). An integer array is refused: its unit (millimetres, centimetres, voxel indices) cannot
  be told from the file.
Binary tables are memory-mapped: chunked reading holds one chunk.
"""

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mapsqueeze.errors import InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.io.atomic import atomic_output
from mapsqueeze.io.pointcloud import ChunkSource, CloudStats, PointCloud, row_chunks, validate_points

KITTI_FIELDS = ("reflectance",)
SEMANTIC_KITTI_FIELDS = ("label", "instance")
NUSCENES_FIELDS = ("intensity", "ring")
NUSCENES_WHOLE_FIELDS = ("ring",)
_LABEL_LIMIT = 0xFFFF


def _float32_table(path: Path, n_attributes: int, label: str) -> np.ndarray:
    """The file as a memory-mapped (N, 3 + n_attributes) float32 table, after checking its size."""
    row_bytes = 4 * (3 + n_attributes)
    size = path.stat().st_size
    if size % row_bytes:
        raise PointCloudFormatError(
            f"{path}: {label} size {size:,} bytes is not a multiple of {row_bytes} (float32 x 3+{n_attributes}); "
            "truncated or not this format"
        )
    if size == 0:
        raise InvalidPointCloudError(f"{path}: the point cloud is empty")
    return np.memmap(path, dtype="<f4", mode="r").reshape(-1, 3 + n_attributes)


def label_path(scan: Path) -> Path | None:
    """The SemanticKITTI label file of a KITTI scan, if one exists (beside it, or in ../labels/ of velodyne/)."""
    beside = scan.with_suffix(".label")
    if beside.is_file():
        return beside
    if scan.parent.name == "velodyne":
        sibling = scan.parent.parent / "labels" / f"{scan.stem}.label"
        if sibling.is_file():
            return sibling
    return None


def _label_table(scan: Path, n_points: int) -> np.ndarray | None:
    path = label_path(scan)
    if path is None:
        return None
    if path.stat().st_size != 4 * n_points:
        raise PointCloudFormatError(
            f"{path}: SemanticKITTI labels hold {path.stat().st_size // 4:,} entries, the scan {n_points:,} points")
    return np.memmap(path, dtype="<u4", mode="r")


def _whole_bytes(column: np.ndarray) -> bool:
    """Whether every value of a float column is a whole number from 0 to 255."""
    return bool(np.all((column >= 0) & (column <= 255) & (column == np.floor(column))))


def _table_chunks(path: Path, chunk_points: int, names: tuple[str, ...], label: str, with_labels: bool,
                  attributes: bool, whole: tuple[str, ...] = ()) -> Iterator[PointCloud]:
    """The table's points and attribute columns in chunks; the columns named in `whole` as uint8 where every
    value of the file's column is a whole number 0..255 (checked on the whole file, so every chunk has one dtype)."""
    table = _float32_table(path, len(names), label)
    names = names if attributes else ()
    as_bytes = {name for column, name in enumerate(names) if name in whole and _whole_bytes(table[:, 3 + column])}
    labels = _label_table(path, len(table)) if with_labels and attributes else None
    label_parts = row_chunks(labels, chunk_points) if labels is not None else None
    for first, part in zip(range(0, len(table), chunk_points), row_chunks(table, chunk_points)):
        values = {name: part[:, 3 + column].astype(np.uint8) if name in as_bytes else part[:, 3 + column].copy()
                  for column, name in enumerate(names)}
        if label_parts is not None:
            packed = next(label_parts)
            values["label"] = (packed & _LABEL_LIMIT).astype(np.uint16)
            values["instance"] = (packed >> 16).astype(np.uint16)
        yield PointCloud(validate_points(part[:, :3], str(path), first, len(table)), values)


def kitti_chunks(path: Path, chunk_points: int, attributes: bool = True) -> Iterator[PointCloud]:
    return _table_chunks(path, chunk_points, KITTI_FIELDS, "KITTI .bin", True, attributes)


def nuscenes_chunks(path: Path, chunk_points: int, attributes: bool = True) -> Iterator[PointCloud]:
    return _table_chunks(path, chunk_points, NUSCENES_FIELDS, "nuScenes .pcd.bin", False, attributes,
                         NUSCENES_WHOLE_FIELDS)


def _write_float32_table(path: Path, chunks: ChunkSource, stats: CloudStats, names: tuple[str, ...],
                         label: str) -> tuple[str, ...]:
    stats.require_float32(label)
    with atomic_output(path) as temp, open(temp, "wb") as stream:
        for chunk in chunks():
            columns = [chunk.attributes.get(name, np.zeros(len(chunk))) for name in names]
            stream.write(np.column_stack([chunk.points, *columns]).astype("<f4").tobytes())
    return tuple(name for name in names if name in stats.dtypes)


def _write_labels(path: Path, chunks: ChunkSource) -> None:
    with atomic_output(path.with_suffix(".label")) as temp, open(temp, "wb") as stream:
        for chunk in chunks():
            label = chunk.attributes["label"]
            instance = chunk.attributes.get("instance", np.zeros(len(chunk), np.uint16))
            for name, values in (("label", label), ("instance", instance)):
                if len(values) and (values.min() < 0 or values.max() > _LABEL_LIMIT
                                    or not np.array_equal(values, np.round(values))):
                    raise InvalidPointCloudError(f"SemanticKITTI {name} must be integers in 0..{_LABEL_LIMIT}")
            packed = label.astype(np.uint32) | (instance.astype(np.uint32) << 16)
            stream.write(packed.astype("<u4").tobytes())


def write_kitti(path: Path, chunks: ChunkSource, stats: CloudStats) -> tuple[str, ...]:
    """float32 x, y, z, reflectance (0 where absent); `label` (+ `instance`) into NAME.label beside it."""
    stored = _write_float32_table(path, chunks, stats, KITTI_FIELDS, "KITTI .bin")
    if "label" in stats.dtypes:
        _write_labels(path, chunks)
        stored += tuple(name for name in SEMANTIC_KITTI_FIELDS if name in stats.dtypes)
    return stored


def write_nuscenes(path: Path, chunks: ChunkSource, stats: CloudStats) -> tuple[str, ...]:
    return _write_float32_table(path, chunks, stats, NUSCENES_FIELDS, "nuScenes .pcd.bin")


def _npy_table(path: Path, mmap_mode: str | None) -> np.ndarray:
    """A floating-point N x (>= 3) .npy array (memory-mapped with mmap_mode="r"), or raise."""
    try:
        table = np.load(path, mmap_mode=mmap_mode, allow_pickle=False)
    except (ValueError, EOFError) as exc:  # numpy's advice for object arrays (allow pickles) would run their code
        reason = "it holds Python objects, not an N x 3 array of numbers" if "allow_pickle" in str(exc) else exc
        raise PointCloudFormatError(f"{path}: corrupt or non-numeric .npy file ({reason})") from None
    if not isinstance(table, np.ndarray) or table.dtype.kind not in "iuf":
        raise PointCloudFormatError(f"{path}: .npy holds {getattr(table, 'dtype', type(table))}, expected numbers")
    if table.dtype.kind != "f":  # millimetres, centimetres or voxel indices: no unit to guess
        raise PointCloudFormatError(
            f"{path}: .npy holds {table.dtype} integers, whose unit is unknown; x, y, z must be floats in metres: "
            "save the array scaled to metres (e.g. centimetres: np.save(path, table * 0.01))")
    if table.ndim != 2 or table.shape[1] < 3:
        raise PointCloudFormatError(f"{path}: .npy array has shape {table.shape}, expected N x 3 or N x (>3)")
    return table


def npy_chunks(path: Path, chunk_points: int, attributes: bool = True) -> Iterator[PointCloud]:
    """Columns 0-2 are x, y, z; further columns become attributes `column3`, `column4`, ..."""
    table = _npy_table(path, "r")
    if len(table) == 0:
        raise InvalidPointCloudError(f"{path}: the point cloud is empty")
    columns = range(3, table.shape[1]) if attributes else ()
    for first, part in zip(range(0, len(table), chunk_points), row_chunks(table, chunk_points)):
        yield PointCloud(validate_points(part[:, :3], str(path), first, len(table)),
                         {f"column{column}": part[:, column].copy() for column in columns})


def write_npy(path: Path, chunks: ChunkSource, stats: CloudStats) -> tuple[str, ...]:
    """float64 N x (3 + k): x, y, z then the attributes in order (their names are not stored)."""
    width = 3 + len(stats.dtypes)
    with atomic_output(path) as temp, open(temp, "wb") as stream:
        np.lib.format.write_array_header_1_0(
            stream, {"descr": "<f8", "fortran_order": False, "shape": (stats.n_points, width)})
        for chunk in chunks():
            table = np.column_stack([chunk.points, *(chunk.attributes[name] for name in stats.dtypes)])
            stream.write(np.ascontiguousarray(table, dtype="<f8").tobytes())
    return tuple(stats.dtypes)
