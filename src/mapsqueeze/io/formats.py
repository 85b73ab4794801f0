"""The table of point-cloud formats (reader, chunked reader, writer, the fields each holds) and the API over it.

Format names (`format=` overrides the extension):
- `bin`      KITTI scan, float32 N x 4 (x, y, z, reflectance) + SemanticKITTI `label`/`instance` (io.tables)
- `pcd.bin`  nuScenes sweep, float32 N x 5 (x, y, z, intensity, ring), extension .pcd.bin
- `ply`      PLY (binary little-endian when written; ascii or binary when read), extension .ply;
             `ply-ascii` writes ascii PLY (io.ply)
- `pcd`      PCD with DATA binary when written (ascii, binary or LZF binary_compressed when read), extension .pcd;
             `pcd-ascii` writes ascii; points with a NaN coordinate (missing returns of organised clouds) are left
             out when read (io.pcd)
- `las`, `laz` LAS 1.2-1.4 with every standard field, extra bytes and the header's CRS records; uint8 colour
             written x 257 into LAS's 16-bit colour (io.las)
- `npy`      NumPy float array N x 3 (metres), or N x (3 + k) with k attribute columns, extension .npy; integer
             arrays are refused (their unit is unknown)

Precision: x, y, z are float64 in memory. PLY and PCD store them as float32 when that errs by at most
FLOAT32_MAX_ERROR_M (1 mm) and as float64 otherwise (e.g. UTM coordinates). The float32-only .bin formats refuse
coordinates float32 would round by more than 1 mm. LAS/LAZ store integers (see io.las for scale and offset).
"""

import os
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from mapsqueeze.errors import CrsNotWrittenWarning, InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.io import ply, tables
from mapsqueeze.io.pcd import pcd_chunks, write_pcd
from mapsqueeze.io.pointcloud import (
    ChunkSource,
    CloudStats,
    PointCloud,
    float32_error_m,
    validate_attributes,
    validate_points,
)

DEFAULT_CHUNK_POINTS = 1 << 18
"""Points per chunk of `iter_points` (6 MB of float64 x, y, z): compress tiles each chunk with several temporaries
of its size, so its coordinator peaks ~85 MB lower than with 1M-point chunks, at no more CPU (BENCHMARKS.md
"Throughput")."""

ANY_FIELDS = None
"""`Format.fields` of a format that holds attributes of any name."""


@dataclass(frozen=True)
class Format:
    """One row of the format table."""

    name: str
    extensions: tuple[str, ...]
    chunks: Callable[..., Iterator[PointCloud]]  # (path, n, attributes=True): PointCloud chunks of <= n points
    write: Callable[[Path, ChunkSource, CloudStats], tuple[str, ...]]  # atomic writer; returns the names stored
    fields: tuple[str, ...] | None  # attribute names it holds (ANY_FIELDS: any)
    streams: bool  # True: memory-mapped or chunked reading and chunk-by-chunk writing; False: whole in memory
    metadata: bool = False  # True: writes the file metadata (LAS header records: the CRS)
    names: bool = True  # False: attributes are stored as unnamed float64 columns (.npy), read back as column3, ...
    value_ranges: bool = False  # True: its writer needs each attribute's value range (`CloudStats.ranges`)

    def holds(self, name: str) -> bool:
        return self.fields is ANY_FIELDS or name in self.fields


def _las_chunks(path: Path, chunk_points: int, attributes: bool = True) -> Iterator[PointCloud]:
    from mapsqueeze.io import las  # laspy and lazrs (~0.03 CPU-s, 3 MB): imported for LAS/LAZ files only

    return las.las_chunks(path, chunk_points, attributes)


def _write_las(path: Path, chunks: ChunkSource, stats: CloudStats, compress: bool) -> tuple[str, ...]:
    from mapsqueeze.io import las

    return las.write_las(path, chunks, stats, compress)


FORMATS: dict[str, Format] = {fmt.name: fmt for fmt in (
    Format("bin", (".bin",), tables.kitti_chunks, tables.write_kitti,
           tables.KITTI_FIELDS + tables.SEMANTIC_KITTI_FIELDS, True),
    Format("pcd.bin", (".pcd.bin",), tables.nuscenes_chunks, tables.write_nuscenes, tables.NUSCENES_FIELDS, True),
    Format("ply", (".ply",), ply.ply_chunks, partial(ply.write_ply, text=False), ANY_FIELDS, True),
    Format("ply-ascii", (), ply.ply_chunks, partial(ply.write_ply, text=True), ANY_FIELDS, False),
    Format("pcd", (".pcd",), pcd_chunks, partial(write_pcd, encoding="binary"), ANY_FIELDS, False),
    Format("pcd-ascii", (), pcd_chunks, partial(write_pcd, encoding="ascii"), ANY_FIELDS, False),
    Format("las", (".las",), _las_chunks, partial(_write_las, compress=False), ANY_FIELDS, True, True,
           value_ranges=True),
    Format("laz", (".laz",), _las_chunks, partial(_write_las, compress=True), ANY_FIELDS, True, True,
           value_ranges=True),
    Format("npy", (".npy",), tables.npy_chunks, tables.write_npy, ANY_FIELDS, True, names=False),
)}

SUPPORTED_FORMATS: tuple[str, ...] = tuple(FORMATS)

# Longest suffix first: ".pcd.bin" must win over ".bin".
_EXTENSIONS = sorted(((ext, fmt.name) for fmt in FORMATS.values() for ext in fmt.extensions),
                     key=lambda item: -len(item[0]))


def format_name(path: str | os.PathLike, format: str | None = None) -> str:
    """The format a path is read or written in: `format` when given, else from the extension (or raise; a
    directory is no point-cloud file whatever its name)."""
    path = Path(path)
    if path.is_dir():
        raise PointCloudFormatError(f"{path}: is a directory, not a point-cloud file")
    if format is not None:
        name = format.lower().lstrip(".")
        if name not in FORMATS:
            raise PointCloudFormatError(
                f"{path}: unknown point-cloud format {format!r} (supported: {', '.join(SUPPORTED_FORMATS)})"
            )
        return name
    lower = path.name.lower()
    for extension, name in _EXTENSIONS:
        if lower.endswith(extension):
            return name
    if lower.endswith(".msq"):
        raise PointCloudFormatError(f"{path}: a .msq file is a mapsqueeze container, not a point cloud (decompress "
                                    "reads one, compress writes one)")
    raise PointCloudFormatError(
        f"{path}: unknown point-cloud extension (known: {', '.join(ext for ext, _ in _EXTENSIONS)}); "
        "set the format explicitly"
    )


def dropped_fields(names: Iterable[str], path: str | os.PathLike, format: str | None = None) -> list[str]:
    """The attribute names a file of this format cannot hold (before writing it)."""
    fmt = FORMATS[format_name(path, format)]
    return [name for name in names if not fmt.holds(name)]


def unnamed_fields(names: Iterable[str], path: str | os.PathLike, format: str | None = None) -> list[str]:
    """The attribute names a file of this format stores without their names and dtypes (as .npy's float64 columns
    3, 4, ..., in this order), before writing it."""
    fmt = FORMATS[format_name(path, format)]
    return [] if fmt.names else [name for name in names if fmt.holds(name)]


def holds_metadata(path: str | os.PathLike, format: str | None = None) -> bool:
    """Whether a file of this format keeps the file metadata (`PointCloud.metadata`: LAS header records, the CRS)."""
    return FORMATS[format_name(path, format)].metadata


def holds_crs(metadata: dict, path: str | os.PathLike, format: str | None = None) -> bool:
    """Whether a file of this format, written with `metadata`, keeps its CRS (`metadata["crs"]`): LAS/LAZ from the
    LAS records it was read from or from a WKT (io.las.keeps_crs), no other format."""
    if not holds_metadata(path, format):
        return False
    from mapsqueeze.io import las

    return las.keeps_crs(metadata)


def crs_loss(metadata: dict, path: str | os.PathLike, format: str | None = None) -> str | None:
    """Why a file of this format, written with `metadata`, does not keep its CRS (`metadata["crs"]`: "EPSG:n" or a
    WKT from a LAS file, any JSON value from the API), or None when it keeps it or there is none."""
    crs = (metadata or {}).get("crs")
    if not crs or holds_crs(metadata, path, format):
        return None
    text = str(crs)
    shown = "a WKT" if "[" in text else text
    given = " as given: LAS takes a WKT or the LAS records it was read from" if holds_metadata(path, format) else ""
    return f"{Path(path).name} cannot hold the CRS ({shown}){given}; not written"


def warn_of_crs_loss(metadata: dict, path: str | os.PathLike, format: str | None = None) -> None:
    """A CrsNotWrittenWarning where a file of this format, written with `metadata`, drops its CRS (`crs_loss`)."""
    reason = crs_loss(metadata, path, format)
    if reason:
        warnings.warn(CrsNotWrittenWarning(reason), stacklevel=3)


def _existing_file(path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.is_dir():
        raise PointCloudFormatError(f"{path}: is a directory, not a point-cloud file")
    if not path.exists():
        raise PointCloudFormatError(f"{path}: no such file")
    return path


def iter_point_clouds(path: str | os.PathLike, format: str | None = None,
                      chunk_points: int = DEFAULT_CHUNK_POINTS, attributes: bool = True) -> Iterator[PointCloud]:
    """Yield a file's points with their attributes (and the file's metadata) as PointCloud chunks, in file order.

    Binary PLY, .bin, .pcd.bin and .npy are memory-mapped and LAS/LAZ read chunk by chunk, so memory stays
    bounded by one chunk; ASCII PLY is read whole (one chunk); PCD is read whole and yielded in chunks (memory: its
    data plus one chunk; a binary_compressed PCD's block, which stores each field for every point in turn, is
    decompressed whole before the first chunk). Errors (PointCloudFormatError,
    InvalidPointCloudError, each one line naming the file) are raised when the bad part is reached.
    attributes=False reads the points only (no attribute columns, no SemanticKITTI label file).
    """
    path = _existing_file(path)
    if chunk_points < 1:
        raise ValueError("chunk_points must be >= 1")
    reader = FORMATS[format_name(path, format)].chunks
    try:
        yield from reader(path, chunk_points, attributes)
    except OSError as exc:
        raise PointCloudFormatError(f"{path}: cannot read ({exc.strerror or exc})") from None


def iter_points(path: str | os.PathLike, format: str | None = None,
                chunk_points: int = DEFAULT_CHUNK_POINTS) -> Iterator[np.ndarray]:
    """Yield a file's points only, as validated (<= chunk_points, 3) float64 chunks (see `iter_point_clouds`)."""
    for chunk in iter_point_clouds(path, format, chunk_points, attributes=False):
        yield chunk.points


def read_point_cloud(path: str | os.PathLike, format: str | None = None, attributes: bool = True) -> PointCloud:
    """Read points (N, 3) float64 metres, per-point attributes (dtypes kept; none if not attributes) and file
    metadata; the format comes from the extension unless `format` (one of SUPPORTED_FORMATS) is given. A PCD's
    points with a NaN coordinate are left out and counted (`PointCloud.nan_points_dropped`)."""
    chunks = list(iter_point_clouds(path, format, chunk_points=1 << 62, attributes=attributes))
    if len(chunks) == 1:
        return chunks[0]
    if not chunks:
        raise InvalidPointCloudError(f"{path}: the point cloud is empty")
    return PointCloud(np.concatenate([c.points for c in chunks]),
                      {name: np.concatenate([c.attributes[name] for c in chunks]) for name in chunks[0].attributes},
                      chunks[0].metadata, sum(c.nan_points_dropped for c in chunks))


def read_points(path: str | os.PathLike, format: str | None = None) -> np.ndarray:
    """Read only the points, (N, 3) float64 metres (see `read_point_cloud`)."""
    return read_point_cloud(path, format, attributes=False).points


def _as_cloud(chunk) -> PointCloud:
    return chunk if isinstance(chunk, PointCloud) else PointCloud(chunk)


def _checked_chunks(chunks: Callable[[], Iterable], path: Path) -> ChunkSource:
    """chunks() with every chunk validated (PointCloud or bare (n, 3) array) and its attributes in one order."""
    def source() -> Iterator[PointCloud]:
        names, first = None, 0
        for chunk in map(_as_cloud, chunks()):
            points = validate_points(chunk.points, f"points for {path}", first)
            first += len(points)
            attributes = validate_attributes(chunk.attributes, len(points), name=f"points for {path}")
            if names is None:
                names = {name: values.dtype for name, values in attributes.items()}
            elif {name: values.dtype for name, values in attributes.items()} != names:
                raise InvalidPointCloudError(f"points for {path}: chunks differ in their attributes or dtypes")
            yield PointCloud(points, {name: attributes[name] for name in names}, chunk.metadata)
    return source


def _value_range(values: np.ndarray) -> tuple[float, float, bool]:
    """(smallest, largest, whether every value is a whole number) of a non-empty attribute column."""
    whole = values.dtype.kind in "iub" or bool(np.array_equal(values, np.round(values)))
    return float(values.min()), float(values.max()), whole


def _cloud_stats(chunks: ChunkSource, path: Path, value_ranges: bool) -> CloudStats:
    """The statistics of a pass over the chunks; each attribute's value range only with `value_ranges`."""
    n, lowest, highest, error, dtypes, metadata = 0, np.full(3, np.inf), np.full(3, -np.inf), 0.0, {}, {}
    ranges: dict[str, tuple[float, float, bool]] = {}
    for index, chunk in enumerate(chunks()):
        if index == 0:
            dtypes, metadata = {name: values.dtype for name, values in chunk.attributes.items()}, chunk.metadata
        n += len(chunk)
        if not len(chunk):
            continue
        chunk_low, chunk_high = bounding_box(chunk.points)
        lowest, highest = np.minimum(lowest, chunk_low), np.maximum(highest, chunk_high)
        error = max(error, float32_error_m(chunk.points))
        for name, values in chunk.attributes.items() if value_ranges else ():
            low, high, whole = _value_range(values)
            if name in ranges:
                low, high, whole = min(low, ranges[name][0]), max(high, ranges[name][1]), whole and ranges[name][2]
            ranges[name] = (low, high, whole)
    if n == 0:
        raise InvalidPointCloudError(f"points for {path}: the point cloud is empty")
    return CloudStats(n, lowest, highest, error, dtypes, metadata, ranges)


def _write(path: Path, chunks: Callable[[], Iterable], format: str | None) -> tuple[CloudStats, tuple[str, ...]]:
    fmt = FORMATS[format_name(path, format)]
    source = _checked_chunks(chunks, path)
    stats = _cloud_stats(source, path, fmt.value_ranges)
    try:
        stored = fmt.write(path, source, stats)
    except OSError as exc:
        raise PointCloudFormatError(f"{path}: cannot write ({exc.strerror or exc})") from None
    except InvalidPointCloudError as exc:
        raise InvalidPointCloudError(f"{path}: {exc}") from None
    warn_of_crs_loss(stats.metadata, path, format)
    return stats, stored


def write_point_chunks(path: str | os.PathLike, chunks: Callable[[], Iterable], format: str | None = None) -> int:
    """Write the chunks of chunks() atomically; returns the point count.

    chunks() is called at least twice (statistics, then data) and yields the same (n, 3) arrays or PointClouds
    (same attribute names and dtypes; the first chunk's metadata counts) each time. Streaming formats are written
    chunk by chunk (memory bounded by one chunk); ASCII PLY and PCD are assembled in memory. Attributes a format
    has no place for are not written (`dropped_fields` names them).
    """
    stats, _ = _write(Path(path), chunks, format)
    return stats.n_points


def write_points(
    path: str | os.PathLike,
    points: np.ndarray,
    format: str | None = None,
    attributes: dict[str, np.ndarray] | None = None,
    metadata: dict | None = None,
) -> tuple[str, ...]:
    """Write points (N, 3) metres, optional attributes and metadata atomically; returns the attribute names stored.

    The format comes from the extension unless `format` is given. Attributes a format has no place for
    (e.g. `ring` in a KITTI .bin) are not written: compare the returned names with the ones passed.
    """
    cloud = PointCloud(points, attributes or {}, metadata or {})
    return _write(Path(path), lambda: [cloud], format)[1]
