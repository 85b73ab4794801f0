"""The in-memory point cloud and the checks every reader and writer applies to it."""

import re
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from mapsqueeze.errors import InvalidPointCloudError
# the check every io reader and writer applies, re-exported with io's API
from mapsqueeze.geometry.validation import MAX_ABS_COORDINATE_M, validate_points  # noqa: F401

FLOAT32_MAX_ERROR_M = 1e-3
"""Largest rounding error (metres) accepted when x, y, z are stored as float32; beyond it float64 is used
(PLY, PCD) or the write is refused (KITTI/nuScenes .bin, which are float32 by definition)."""
FLOAT32_SAFE_ABS_M = 2.0**15
"""Coordinates of smaller magnitude (metres) round to float32 by at most 2^-10 m, within FLOAT32_MAX_ERROR_M."""

_ATTRIBUTE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,31}")


@dataclass
class PointCloud:
    """Points (N, 3) float64 in metres, per-point attributes (each a 1-D array of length N, its dtype kept) and
    file metadata (JSON-serialisable; e.g. `las`: the LAS header's point format, scales, offsets, CRS records).
    nan_points_dropped: the points of the file the reader left out because a coordinate is NaN (a PCD's "no
    return" marker; `io.pcd`), not in `points`."""

    points: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)
    nan_points_dropped: int = 0

    def __len__(self) -> int:
        return len(self.points)


def row_chunks(table: np.ndarray, chunk_rows: int) -> Iterator[np.ndarray]:
    """Consecutive ranges of at most chunk_rows rows of a table, in order, each an in-memory copy. A C-ordered
    memory-mapped table (np.memmap of a whole file region) is read from its file one range at a time, by plain
    reads: the pages of a map a process has read count as its resident memory, so reading a large file through one
    map would grow with the file, and mapping each range in turn faults its pages in one by one (2-3x the CPU time of
    a read); this way holds one chunk."""
    mapped = isinstance(table, np.memmap) and table.filename is not None and table.flags.c_contiguous
    row_shape = table.shape[1:]
    row_bytes = table.dtype.itemsize * int(np.prod(row_shape, dtype=np.int64))
    for start in range(0, len(table), chunk_rows):
        stop = min(start + chunk_rows, len(table))
        if not mapped:
            yield np.array(table[start:stop])
            continue
        count = (stop - start) * int(np.prod(row_shape, dtype=np.int64))
        rows = np.fromfile(table.filename, dtype=table.dtype, count=count, offset=table.offset + start * row_bytes)
        if rows.size != count:
            raise OSError("the file ended while it was being read")
        yield rows.reshape(stop - start, *row_shape)


ChunkSource = Callable[[], Iterable[PointCloud]]
"""Called once per pass, yields the same PointCloud chunks (same attribute names and dtypes) in the same order."""


@dataclass(frozen=True)
class CloudStats:
    """What a writer needs before the first chunk: count, extent, float32 rounding error, attribute dtypes, and for
    the formats that ask (`Format.value_ranges`: LAS) each attribute's values as (smallest, largest, whether all
    are whole numbers)."""

    n_points: int
    lowest: np.ndarray
    highest: np.ndarray
    float32_error: float
    dtypes: dict[str, np.dtype]
    metadata: dict
    ranges: dict[str, tuple[float, float, bool]]

    def require_float32(self, label: str) -> None:
        """Refuse a float32-only format when float32 would move points by more than FLOAT32_MAX_ERROR_M."""
        if self.float32_error > FLOAT32_MAX_ERROR_M:
            raise InvalidPointCloudError(
                f"{label} stores float32 x, y, z, which would move points by up to {self.float32_error * 1e3:.1f} "
                "mm; shift the cloud towards the origin or write .ply/.las"
            )


def drop_zero_points(points: np.ndarray, name: str = "point cloud",
                     allow_empty: bool = False) -> tuple[np.ndarray, int]:
    """(points without the rows at exactly (0, 0, 0), how many were dropped). Sensors write (0, 0, 0) for "no
    return" (7 % of a real binary PCD); kept, they decode to a blob at the sensor. A cloud of only such points
    raises InvalidPointCloudError unless allow_empty."""
    zero = points[:, 0] == 0  # column by column: ~10x faster than any() along the (N, 3) array's rows
    zero &= points[:, 1] == 0
    zero &= points[:, 2] == 0
    n_zero = int(np.count_nonzero(zero))
    if not n_zero:
        return points, 0
    if n_zero == len(points) and not allow_empty:
        raise InvalidPointCloudError(f"{name}: all {n_zero:,} points lie at (0, 0, 0) (sensor 'no return' "
                                     "values); keep them with --keep-zero-points")
    return points[~zero], n_zero


def validate_attributes(attributes: dict | None, num_points: int, name: str = "point cloud") -> dict[str, np.ndarray]:
    """Return the attributes as 1-D numeric arrays of length `num_points`, or raise InvalidPointCloudError.

    Names must be identifiers of at most 32 characters other than x, y, z (valid in PLY, PCD and LAS).
    bool becomes uint8, float16 becomes float32 (types every format can store); byte order becomes native.
    """
    checked = {}
    for key, values in (attributes or {}).items():
        if not isinstance(key, str) or not _ATTRIBUTE_NAME.fullmatch(key) or key.lower() in ("x", "y", "z"):
            raise InvalidPointCloudError(
                f"{name}: bad attribute name {key!r} (an identifier of at most 32 characters, not x, y or z)"
            )
        try:
            array = np.asarray(values)
        except (TypeError, ValueError) as exc:
            raise InvalidPointCloudError(f"{name}: attribute {key!r} is not an array ({exc})") from None
        if array.dtype == np.bool_:
            array = array.astype(np.uint8)
        elif array.dtype == np.float16:
            array = array.astype(np.float32)
        if array.dtype.kind not in "iuf":
            raise InvalidPointCloudError(f"{name}: attribute {key!r} is not numeric (dtype {array.dtype})")
        if array.shape != (num_points,):
            raise InvalidPointCloudError(
                f"{name}: attribute {key!r} has shape {array.shape}, expected ({num_points},) (one value per point)"
            )
        checked[key] = array.astype(array.dtype.newbyteorder("="), copy=False)
    return checked


def float32_error_m(points: np.ndarray) -> float:
    """Largest absolute error (metres) that storing these float64 coordinates as float32 would introduce."""
    return float(np.abs(points.astype(np.float32).astype(np.float64) - points).max())


def split_columns(name: str, values: np.ndarray) -> dict[str, np.ndarray]:
    """A per-point field as 1-D attributes: (N,) stays `name`, (N, k) becomes `name_0` .. `name_{k-1}`."""
    if values.ndim == 1:
        return {name: values}
    flat = values.reshape(len(values), -1)
    return {f"{name}_{column}": flat[:, column].copy() for column in range(flat.shape[1])}
