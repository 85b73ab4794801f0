"""Readers and writers of every supported point-cloud format, and the registry that picks one by extension.

Format names (`format=` overrides the extension):
- `bin`      KITTI scan, float32 N x 4 (x, y, z, reflectance), extension .bin
- `pcd.bin`  nuScenes sweep, float32 N x 5 (x, y, z, intensity, ring), extension .pcd.bin
- `ply`      PLY (binary little-endian when written; ascii or binary when read), extension .ply;
             `ply-ascii` writes ascii PLY
- `pcd`      PCD with DATA binary when written (ascii or binary when read), extension .pcd; `pcd-ascii` writes ascii
- `las`, `laz` LAS 1.4 point format 0 (laz: LAZ-compressed with lazrs), extensions .las, .laz
- `npy`      NumPy array N x 3, or N x (3 + k) with k attribute columns, extension .npy

Precision: x, y, z are float64 in memory. PLY and PCD store them as float32 when that errs by at most
FLOAT32_MAX_ERROR_M (1 mm) and as float64 otherwise (e.g. UTM coordinates). The float32-only .bin formats refuse
coordinates float32 would round by more than 1 mm. LAS/LAZ store integers with scale LAS_SCALE_M (0.1 mm) and an
offset of the cloud's minimum rounded down to whole metres: the error is at most 0.05 mm per axis, and the cloud's
extent must stay below 2^31 * 0.1 mm (about 214 km) per axis.
"""

import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import laspy
import lazrs
import numpy as np
import plyfile

from mapsqueeze.errors import InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.io.atomic import atomic_output
from mapsqueeze.io.pcd import read_pcd, write_pcd
from mapsqueeze.io.pointcloud import (
    FLOAT32_MAX_ERROR_M,
    PointCloud,
    float32_error_m,
    split_columns,
    validate_attributes,
    validate_points,
)

LAS_SCALE_M = 1e-4
"""LAS/LAZ coordinate resolution in metres (quantisation error at most half of it)."""

_LAS_POINT_FORMAT = 0
_LAS_INTEGER_LIMIT = 2**31 - 1

Writer = Callable[[Path, np.ndarray, dict[str, np.ndarray]], tuple[str, ...]]


ChunkReader = Callable[[Path, int], Iterator[np.ndarray]]

DEFAULT_CHUNK_POINTS = 1 << 21
"""Points per chunk of `iter_points` (48 MB of float64 x, y, z)."""


@dataclass(frozen=True)
class _Format:
    read: Callable[[Path], PointCloud]
    write: Writer
    chunks: ChunkReader | None = None  # memory-bounded reader; None: the whole file in one chunk


def _float32_columns(points: np.ndarray, columns: list[np.ndarray], label: str) -> bytes:
    """x, y, z plus extra columns as row-major float32 bytes; refuse coordinates float32 rounds by > 1 mm."""
    error = float32_error_m(points)
    if error > FLOAT32_MAX_ERROR_M:
        raise InvalidPointCloudError(
            f"{label} stores float32 x, y, z, which would move points by up to {error * 1e3:.1f} mm; "
            "shift the cloud towards the origin or write .ply/.las"
        )
    return np.column_stack([points, *columns]).astype("<f4").tobytes()


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


def _read_float32_columns(path: Path, names: tuple[str, ...], label: str) -> PointCloud:
    table = _float32_table(path, len(names), label)
    points = validate_points(table[:, :3], name=str(path))
    return PointCloud(points, {name: np.array(table[:, 3 + column]) for column, name in enumerate(names)})


def _chunks_float32_columns(path: Path, chunk_points: int, n_attributes: int, label: str) -> Iterator[np.ndarray]:
    table = _float32_table(path, n_attributes, label)
    for start in range(0, len(table), chunk_points):
        yield validate_points(table[start:start + chunk_points, :3], name=str(path))


def _read_kitti(path: Path) -> PointCloud:
    return _read_float32_columns(path, ("reflectance",), "KITTI .bin")


def _write_kitti(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> tuple[str, ...]:
    reflectance = attributes.get("reflectance", np.zeros(len(points)))
    path.write_bytes(_float32_columns(points, [reflectance], "KITTI .bin"))
    return ("reflectance",) if "reflectance" in attributes else ()


_NUSCENES_ATTRIBUTES = ("intensity", "ring")


def _read_nuscenes(path: Path) -> PointCloud:
    return _read_float32_columns(path, _NUSCENES_ATTRIBUTES, "nuScenes .pcd.bin")


def _write_nuscenes(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> tuple[str, ...]:
    columns = [attributes.get(name, np.zeros(len(points))) for name in _NUSCENES_ATTRIBUTES]
    path.write_bytes(_float32_columns(points, columns, "nuScenes .pcd.bin"))
    return tuple(name for name in _NUSCENES_ATTRIBUTES if name in attributes)


def _ply_vertices(path: Path) -> tuple[np.ndarray, list[str]]:
    """The vertex table (memory-mapped for binary PLY) and its scalar property names."""
    try:
        ply = plyfile.PlyData.read(str(path), mmap="r")
        vertex = ply["vertex"]
    except KeyError:
        raise PointCloudFormatError(f"{path}: PLY file has no vertex element") from None
    except (plyfile.PlyParseError, ValueError, EOFError, UnicodeDecodeError, IndexError) as exc:
        raise PointCloudFormatError(f"{path}: corrupt PLY file ({exc})") from None
    names = [prop.name for prop in vertex.properties if not isinstance(prop, plyfile.PlyListProperty)]
    missing = [axis for axis in ("x", "y", "z") if axis not in names]
    if missing:
        raise PointCloudFormatError(f"{path}: PLY vertex element has no {', '.join(missing)} property")
    return vertex.data, names


def _read_ply(path: Path) -> PointCloud:
    data, names = _ply_vertices(path)
    points = validate_points(np.column_stack([data["x"], data["y"], data["z"]]), name=str(path))
    attributes = {name: np.array(data[name]) for name in names if name not in ("x", "y", "z")}
    return PointCloud(points, attributes)


def _chunks_ply(path: Path, chunk_points: int) -> Iterator[np.ndarray]:
    data, _ = _ply_vertices(path)
    if len(data) == 0:
        raise InvalidPointCloudError(f"{path}: the point cloud is empty")
    for start in range(0, len(data), chunk_points):
        part = data[start:start + chunk_points]
        yield validate_points(np.column_stack([part["x"], part["y"], part["z"]]), name=str(path))


_PLY_INTEGER_TYPES = (np.int32, np.uint32)


def _ply_dtype(name: str, values: np.ndarray) -> np.dtype:
    """The dtype a PLY property can hold losslessly: 64-bit integers narrow to 32 bits when they fit."""
    if values.dtype.kind == "f" or values.dtype.itemsize < 8:
        return values.dtype.newbyteorder("<")
    narrow = np.dtype(_PLY_INTEGER_TYPES[values.dtype.kind == "u"])
    if values.min() < np.iinfo(narrow).min or values.max() > np.iinfo(narrow).max:
        raise InvalidPointCloudError(f"attribute {name!r} does not fit the 32-bit integers PLY can store")
    return narrow.newbyteorder("<")


def _write_ply(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], text: bool) -> tuple[str, ...]:
    xyz_code = "<f4" if float32_error_m(points) <= FLOAT32_MAX_ERROR_M else "<f8"
    layout = [(axis, xyz_code) for axis in ("x", "y", "z")]
    layout += [(name, _ply_dtype(name, values)) for name, values in attributes.items()]
    vertices = np.empty(len(points), dtype=np.dtype(layout))
    for column, axis in enumerate(("x", "y", "z")):
        vertices[axis] = points[:, column]
    for name, values in attributes.items():
        vertices[name] = values
    ply = plyfile.PlyData([plyfile.PlyElement.describe(vertices, "vertex")], text=text, byte_order="<")
    ply.write(str(path))
    return tuple(attributes)


def _read_las(path: Path) -> PointCloud:
    """Scaled x, y, z as float64; attributes: `intensity` and every extra-bytes dimension."""
    try:
        las = laspy.read(path)
        if len(las.points) != las.header.point_count:
            raise PointCloudFormatError(
                f"{path}: LAS header declares {las.header.point_count:,} points, the file holds {len(las.points):,}"
            )
        points = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
        attributes = {"intensity": np.array(las.intensity)}
        for name in las.point_format.extra_dimension_names:
            attributes.update(split_columns(name, np.array(las[name])))
    except (laspy.errors.LaspyException, lazrs.LazrsError, ValueError, EOFError) as exc:
        raise PointCloudFormatError(f"{path}: corrupt LAS/LAZ file ({exc})") from None
    return PointCloud(validate_points(points, name=str(path)), attributes)


def _chunks_las(path: Path, chunk_points: int) -> Iterator[np.ndarray]:
    try:
        with laspy.open(path) as reader:
            declared, seen = reader.header.point_count, 0
            if declared == 0:
                raise InvalidPointCloudError(f"{path}: the point cloud is empty")
            for part in reader.chunk_iterator(chunk_points):
                seen += len(part)
                if len(part):
                    yield validate_points(np.column_stack([np.asarray(part.x), np.asarray(part.y),
                                                           np.asarray(part.z)]), name=str(path))
            if seen != declared:
                raise PointCloudFormatError(
                    f"{path}: LAS header declares {declared:,} points, the file holds {seen:,}")
    except (laspy.errors.LaspyException, lazrs.LazrsError, ValueError, EOFError) as exc:
        raise PointCloudFormatError(f"{path}: corrupt LAS/LAZ file ({exc})") from None


def _las_header(lowest: np.ndarray, highest: np.ndarray) -> laspy.LasHeader:
    """LAS 1.4 point format 0 header: scale LAS_SCALE_M, offset = the minimum rounded down to whole metres."""
    offset = np.floor(lowest)
    extent = (highest - offset) / LAS_SCALE_M
    if extent.max() > _LAS_INTEGER_LIMIT:
        raise InvalidPointCloudError(
            f"the cloud spans {extent.max() * LAS_SCALE_M / 1e3:.0f} km, more than LAS can hold at "
            f"{LAS_SCALE_M * 1e3:g} mm resolution (about {_LAS_INTEGER_LIMIT * LAS_SCALE_M / 1e3:.0f} km)"
        )
    header = laspy.LasHeader(version="1.4", point_format=_LAS_POINT_FORMAT)
    header.offsets = offset
    header.scales = np.full(3, LAS_SCALE_M)
    return header


def _write_las(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray], compress: bool) -> tuple[str, ...]:
    """LAS 1.4 point format 0, scale LAS_SCALE_M, offset = per-axis minimum rounded down to whole metres.

    `intensity` goes to the standard uint16 field (refused unless it fits exactly); other attributes become
    extra-bytes dimensions with their own dtype; names of other standard point-format-0 fields are refused.
    """
    header = _las_header(points.min(axis=0), points.max(axis=0))
    standard = {name.lower() for name in header.point_format.dimension_names}
    extra = {name: values for name, values in attributes.items() if name != "intensity"}
    clashing = [name for name in extra if name.lower() in standard]
    if clashing:
        raise InvalidPointCloudError(
            f"attribute {clashing[0]!r} is a standard LAS field mapsqueeze does not write; rename it"
        )
    header.add_extra_dims([laspy.ExtraBytesParams(name=name, type=values.dtype) for name, values in extra.items()])
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if "intensity" in attributes:
        intensity = attributes["intensity"]
        as_uint16 = intensity.astype(np.uint16)
        if not np.array_equal(as_uint16, intensity):
            raise InvalidPointCloudError(
                "LAS intensity is an integer in 0..65535 and attribute 'intensity' is not; "
                "rename it to store it as an extra dimension"
            )
        las.intensity = as_uint16
    for name, values in extra.items():
        las[name] = values
    with open(path, "wb") as stream:  # a stream: given a path, laspy would pick compression by its suffix
        las.write(stream, do_compress=compress, laz_backend=laspy.LazBackend.Lazrs if compress else None)
    return tuple(attributes)


def _npy_table(path: Path, mmap_mode: str | None) -> np.ndarray:
    """A numeric N x (>= 3) .npy array (memory-mapped with mmap_mode="r"), or raise."""
    try:
        table = np.load(path, mmap_mode=mmap_mode, allow_pickle=False)
    except (ValueError, EOFError) as exc:
        raise PointCloudFormatError(f"{path}: corrupt or non-numeric .npy file ({exc})") from None
    if not isinstance(table, np.ndarray) or table.dtype.kind not in "iuf":
        raise PointCloudFormatError(f"{path}: .npy holds {getattr(table, 'dtype', type(table))}, expected numbers")
    if table.ndim != 2 or table.shape[1] < 3:
        raise PointCloudFormatError(f"{path}: .npy array has shape {table.shape}, expected N x 3 or N x (>3)")
    return table


def _read_npy(path: Path) -> PointCloud:
    """Columns 0-2 are x, y, z; further columns become attributes `column3`, `column4`, ..."""
    table = _npy_table(path, None)
    points = validate_points(table[:, :3], name=str(path))
    return PointCloud(points, {f"column{column}": table[:, column].copy() for column in range(3, table.shape[1])})


def _chunks_npy(path: Path, chunk_points: int) -> Iterator[np.ndarray]:
    table = _npy_table(path, "r")
    if len(table) == 0:
        raise InvalidPointCloudError(f"{path}: the point cloud is empty")
    for start in range(0, len(table), chunk_points):
        yield validate_points(table[start:start + chunk_points, :3], name=str(path))


def _write_npy(path: Path, points: np.ndarray, attributes: dict[str, np.ndarray]) -> tuple[str, ...]:
    """float64 N x (3 + k): x, y, z then the attributes in order (their names are not stored)."""
    with open(path, "wb") as stream:
        np.save(stream, np.column_stack([points, *attributes.values()]).astype(np.float64), allow_pickle=False)
    return tuple(attributes)


_FORMATS: dict[str, _Format] = {
    "bin": _Format(_read_kitti, _write_kitti,
                   partial(_chunks_float32_columns, n_attributes=1, label="KITTI .bin")),
    "pcd.bin": _Format(_read_nuscenes, _write_nuscenes,
                       partial(_chunks_float32_columns, n_attributes=len(_NUSCENES_ATTRIBUTES),
                               label="nuScenes .pcd.bin")),
    "ply": _Format(_read_ply, partial(_write_ply, text=False), _chunks_ply),
    "ply-ascii": _Format(_read_ply, partial(_write_ply, text=True), _chunks_ply),
    "pcd": _Format(read_pcd, partial(write_pcd, encoding="binary")),
    "pcd-ascii": _Format(read_pcd, partial(write_pcd, encoding="ascii")),
    "las": _Format(_read_las, partial(_write_las, compress=False), _chunks_las),
    "laz": _Format(_read_las, partial(_write_las, compress=True), _chunks_las),
    "npy": _Format(_read_npy, _write_npy, _chunks_npy),
}

SUPPORTED_FORMATS: tuple[str, ...] = tuple(_FORMATS)

# Longest suffix first: ".pcd.bin" must win over ".bin".
_EXTENSIONS = {".pcd.bin": "pcd.bin", ".bin": "bin", ".ply": "ply", ".pcd": "pcd", ".las": "las", ".laz": "laz",
               ".npy": "npy"}


def format_name(path: str | os.PathLike, format: str | None = None) -> str:
    """The format a path is read or written in: `format` when given, else from the extension (or raise)."""
    path = Path(path)
    if format is not None:
        name = format.lower().lstrip(".")
        if name not in _FORMATS:
            raise PointCloudFormatError(
                f"{path}: unknown point-cloud format {format!r} (supported: {', '.join(SUPPORTED_FORMATS)})"
            )
        return name
    lower = path.name.lower()
    for extension, name in _EXTENSIONS.items():
        if lower.endswith(extension):
            return name
    raise PointCloudFormatError(
        f"{path}: unknown point-cloud extension (known: {', '.join(_EXTENSIONS)}); set the format explicitly"
    )


def _resolve_format(path: Path, format: str | None) -> _Format:
    return _FORMATS[format_name(path, format)]


def read_point_cloud(path: str | os.PathLike, format: str | None = None) -> PointCloud:
    """Read points (N, 3) float64 metres and per-point attributes; the format comes from the extension
    unless `format` (one of SUPPORTED_FORMATS) is given. Raises PointCloudFormatError/InvalidPointCloudError."""
    path = Path(path)
    if path.is_dir():
        raise PointCloudFormatError(f"{path}: is a directory, not a point-cloud file")
    if not path.exists():
        raise PointCloudFormatError(f"{path}: no such file")
    reader = _resolve_format(path, format).read
    try:
        return reader(path)
    except OSError as exc:
        raise PointCloudFormatError(f"{path}: cannot read ({exc.strerror or exc})") from None


def iter_points(path: str | os.PathLike, format: str | None = None,
                chunk_points: int = DEFAULT_CHUNK_POINTS) -> Iterator[np.ndarray]:
    """Yield a file's points as validated (<= chunk_points, 3) float64 chunks, in file order.

    Binary PLY, .bin, .pcd.bin and .npy are memory-mapped and LAS/LAZ read chunk by chunk, so memory stays
    bounded by one chunk; ASCII PLY and PCD are read whole (one chunk). Errors as `read_point_cloud`, raised when
    the bad part is reached.
    """
    path = Path(path)
    if path.is_dir():
        raise PointCloudFormatError(f"{path}: is a directory, not a point-cloud file")
    if not path.exists():
        raise PointCloudFormatError(f"{path}: no such file")
    if chunk_points < 1:
        raise ValueError("chunk_points must be >= 1")
    chunks = _resolve_format(path, format).chunks
    try:
        if chunks is None:
            yield read_point_cloud(path, format).points
        else:
            yield from chunks(path, chunk_points)
    except OSError as exc:
        raise PointCloudFormatError(f"{path}: cannot read ({exc.strerror or exc})") from None


def read_points(path: str | os.PathLike, format: str | None = None) -> np.ndarray:
    """Read only the points, (N, 3) float64 metres (see `read_point_cloud`)."""
    return read_point_cloud(path, format).points


@dataclass(frozen=True)
class _ChunkStats:
    """What a format's header needs before the first chunk is written."""

    n_points: int
    lowest: np.ndarray
    highest: np.ndarray
    float32_error: float


def _chunk_stats(chunks: Callable[[], Iterable[np.ndarray]], path: Path) -> _ChunkStats:
    n, lowest, highest, error = 0, np.full(3, np.inf), np.full(3, -np.inf), 0.0
    for chunk in chunks():
        chunk = validate_points(chunk, name=f"points for {path}")
        n += len(chunk)
        chunk_low, chunk_high = bounding_box(chunk)
        lowest, highest = np.minimum(lowest, chunk_low), np.maximum(highest, chunk_high)
        error = max(error, float32_error_m(chunk))
    if n == 0:
        raise InvalidPointCloudError(f"points for {path}: the point cloud is empty")
    return _ChunkStats(n, lowest, highest, error)


def _stream_float32_columns(stream, chunks, stats: _ChunkStats, n_attributes: int, label: str) -> None:
    if stats.float32_error > FLOAT32_MAX_ERROR_M:
        raise InvalidPointCloudError(
            f"{label} stores float32 x, y, z, which would move points by up to {stats.float32_error * 1e3:.1f} mm; "
            "shift the cloud towards the origin or write .ply/.las"
        )
    for chunk in chunks():
        stream.write(np.column_stack([chunk, np.zeros((len(chunk), n_attributes))]).astype("<f4").tobytes())


def _stream_ply(stream, chunks, stats: _ChunkStats) -> None:
    """Binary little-endian PLY with one vertex element x, y, z (float32 unless that errs > 1 mm)."""
    xyz_code, ply_type = ("<f4", "float") if stats.float32_error <= FLOAT32_MAX_ERROR_M else ("<f8", "double")
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {stats.n_points}",
              *(f"property {ply_type} {axis}" for axis in "xyz"), "end_header"]
    stream.write(("\n".join(header) + "\n").encode("ascii"))
    for chunk in chunks():
        stream.write(chunk.astype(xyz_code).tobytes())


def _stream_npy(stream, chunks, stats: _ChunkStats) -> None:
    np.lib.format.write_array_header_1_0(
        stream, {"descr": "<f8", "fortran_order": False, "shape": (stats.n_points, 3)})
    for chunk in chunks():
        stream.write(np.ascontiguousarray(chunk, dtype="<f8").tobytes())


def _stream_las(stream, chunks, stats: _ChunkStats, compress: bool) -> None:
    """As _write_las (same scale, offset and limits), chunk by chunk."""
    header = _las_header(stats.lowest, stats.highest)
    with laspy.open(stream, mode="w", header=header, do_compress=compress, closefd=False,
                    laz_backend=laspy.LazBackend.Lazrs if compress else None) as writer:
        for chunk in chunks():
            record = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=header)
            record.x, record.y, record.z = chunk[:, 0], chunk[:, 1], chunk[:, 2]
            writer.write_points(record)


_CHUNK_WRITERS = {
    "bin": partial(_stream_float32_columns, n_attributes=1, label="KITTI .bin"),
    "pcd.bin": partial(_stream_float32_columns, n_attributes=len(_NUSCENES_ATTRIBUTES), label="nuScenes .pcd.bin"),
    "ply": _stream_ply,
    "npy": _stream_npy,
    "las": partial(_stream_las, compress=False),
    "laz": partial(_stream_las, compress=True),
}


def write_point_chunks(path: str | os.PathLike, chunks: Callable[[], Iterable[np.ndarray]],
                       format: str | None = None) -> int:
    """Write the points of chunks() (called twice: statistics, then data) atomically; returns the point count.

    Binary PLY, .bin, .pcd.bin, .npy and LAS/LAZ are written chunk by chunk (memory bounded by one chunk), with
    the same layout and precision rules as `write_points`; ASCII PLY and PCD are assembled in memory.
    """
    path = Path(path)
    name = format_name(path, format)
    stats = _chunk_stats(chunks, path)
    if name not in _CHUNK_WRITERS:
        write_points(path, np.concatenate(list(chunks())), format=name)
        return stats.n_points
    try:
        with atomic_output(path) as temp, open(temp, "wb") as stream:
            _CHUNK_WRITERS[name](stream, chunks, stats)
    except OSError as exc:
        raise PointCloudFormatError(f"{path}: cannot write ({exc.strerror or exc})") from None
    except InvalidPointCloudError as exc:
        raise InvalidPointCloudError(f"{path}: {exc}") from None
    return stats.n_points


def write_points(
    path: str | os.PathLike,
    points: np.ndarray,
    format: str | None = None,
    attributes: dict[str, np.ndarray] | None = None,
) -> tuple[str, ...]:
    """Write points (N, 3) metres and optional attributes atomically; returns the attribute names stored.

    The format comes from the extension unless `format` is given. Attributes a format has no place for
    (e.g. `ring` in a KITTI .bin) are not written: compare the returned names with the ones passed.
    """
    path = Path(path)
    writer = _resolve_format(path, format).write
    points = validate_points(points, name=f"points for {path}")
    checked = validate_attributes(attributes, len(points), name=f"points for {path}")
    try:
        with atomic_output(path) as temp:
            return writer(temp, points, checked)
    except OSError as exc:
        raise PointCloudFormatError(f"{path}: cannot write ({exc.strerror or exc})") from None
    except InvalidPointCloudError as exc:
        raise InvalidPointCloudError(f"{path}: {exc}") from None
