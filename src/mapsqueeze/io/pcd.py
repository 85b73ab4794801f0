"""PCD files (Point Cloud Library, header v0.7) with DATA ascii or binary: a small reader and writer.

Fields with COUNT k > 1 become attributes `name_0` .. `name_{k-1}`; padding fields named `_` are dropped.
Points whose x, y or z is NaN, the "no return" marker of organised clouds written by PCL and ROS drivers, are left
out with their attributes and counted (`PointCloud.nan_points_dropped`); infinite coordinates are refused.
DATA binary_compressed (LZF) is refused with a PointCloudFormatError.
"""

import io
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mapsqueeze.errors import InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.io.atomic import atomic_output
from mapsqueeze.io.pointcloud import (
    FLOAT32_MAX_ERROR_M,
    ChunkSource,
    CloudStats,
    PointCloud,
    split_columns,
    validate_points,
)

_MAX_HEADER_BYTES = 64 * 1024
_TYPE_CODES = {"F": "f", "I": "i", "U": "u"}
_VALID_SIZES = {"F": (4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}
_PADDING_FIELD = "_"


def _parse_header(data: bytes, path: Path) -> tuple[dict[str, list[str]], int]:
    """Header keywords (upper case) -> their values, and the byte offset where the point data starts."""
    header: dict[str, list[str]] = {}
    offset = 0
    while True:
        end = data.find(b"\n", offset, _MAX_HEADER_BYTES)
        if end < 0:
            raise PointCloudFormatError(f"{path}: not a PCD file (no DATA line in the first 64 KiB)")
        try:
            line = data[offset:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise PointCloudFormatError(f"{path}: not a PCD file (binary bytes in the header)") from None
        offset = end + 1
        if not line or line.startswith("#"):
            continue
        keyword, *values = line.split()
        header[keyword.upper()] = values
        if keyword.upper() == "DATA":
            return header, offset


def _header_int(header: dict[str, list[str]], keyword: str, path: Path) -> int:
    values = header.get(keyword)
    if not values or len(values) != 1 or not values[0].isdigit():
        raise PointCloudFormatError(f"{path}: PCD header needs {keyword} as one non-negative integer, got {values}")
    return int(values[0])


def _record_dtype(header: dict[str, list[str]], path: Path) -> np.dtype:
    """The little-endian structured dtype of one point, from FIELDS/SIZE/TYPE/COUNT."""
    fields = header.get("FIELDS")
    if not fields:
        raise PointCloudFormatError(f"{path}: PCD header has no FIELDS line")
    sizes, types = header.get("SIZE", []), header.get("TYPE", [])
    counts = header.get("COUNT", ["1"] * len(fields))
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise PointCloudFormatError(
            f"{path}: PCD header FIELDS/SIZE/TYPE/COUNT have {len(fields)}/{len(sizes)}/{len(types)}/{len(counts)}"
            " entries, expected the same number"
        )
    layout = []
    for index, (name, size, kind, count) in enumerate(zip(fields, sizes, types, counts)):
        kind = kind.upper()
        if kind not in _VALID_SIZES or not size.isdigit() or int(size) not in _VALID_SIZES[kind]:
            raise PointCloudFormatError(f"{path}: PCD field {name!r} has unsupported TYPE {kind} SIZE {size}")
        if not count.isdigit() or int(count) < 1:
            raise PointCloudFormatError(f"{path}: PCD field {name!r} has bad COUNT {count!r}")
        if name == _PADDING_FIELD:
            name = f"{_PADDING_FIELD}{index}"
        code = f"<{_TYPE_CODES[kind]}{size}"
        layout.append((name, code, (int(count),)) if int(count) > 1 else (name, code))
    try:
        dtype = np.dtype(layout)
    except ValueError as exc:
        raise PointCloudFormatError(f"{path}: bad PCD FIELDS ({exc})") from None
    for axis in ("x", "y", "z"):
        if axis not in dtype.names or dtype[axis].shape != ():
            raise PointCloudFormatError(f"{path}: PCD file has no scalar {axis} field (FIELDS {' '.join(fields)})")
    return dtype


def _parse_ascii(body: bytes, dtype: np.dtype, num_points: int, path: Path) -> np.ndarray:
    values_per_point = sum(int(np.prod(dtype[name].shape)) for name in dtype.names)
    try:
        rows = np.loadtxt(io.StringIO(body.decode("ascii")), dtype=np.float64, ndmin=2)
    except (UnicodeDecodeError, ValueError) as exc:  # without numpy's advice to pass `usecols`, not ours to follow
        reason = str(exc).split("; use `usecols`")[0]
        raise PointCloudFormatError(f"{path}: corrupt PCD ascii data ({reason})") from None
    if rows.shape != (num_points, values_per_point):
        raise PointCloudFormatError(
            f"{path}: PCD header declares {num_points:,} points of {values_per_point} values, "
            f"the ascii data has {rows.shape[0]:,} rows of {rows.shape[1]}"
        )
    records = np.empty(num_points, dtype=dtype)
    column = 0
    for name in dtype.names:
        width = int(np.prod(dtype[name].shape))
        records[name] = rows[:, column : column + width].reshape(records[name].shape)
        column += width
    return records


def pcd_chunks(path: Path, chunk_points: int, attributes: bool = True) -> Iterator[PointCloud]:
    """A PCD file is read whole: one chunk whatever chunk_points."""
    cloud = read_pcd(path)
    yield cloud if attributes else PointCloud(cloud.points, nan_points_dropped=cloud.nan_points_dropped)


def _missing_returns(xyz: np.ndarray, path: Path) -> np.ndarray:
    """(N,) bool: the points of (N, 3) float64 `xyz` with a NaN coordinate (missing returns). Raises
    InvalidPointCloudError for an infinite coordinate (no missing-return marker) or when every point is missing."""
    missing = np.isnan(xyz).any(axis=1)
    infinite = np.flatnonzero(np.isinf(xyz).any(axis=1) & ~missing)
    if len(infinite):
        verb = "has" if len(infinite) == 1 else "have"
        raise InvalidPointCloudError(
            f"{path}: {len(infinite):,} of {len(xyz):,} points {verb} infinite coordinates (the first: point "
            f"{int(infinite[0]):,}, counting from 0; NaN marks a missing return in PCD, infinity does not)"
        )
    if len(xyz) and missing.all():
        raise InvalidPointCloudError(f"{path}: no points: all {len(xyz):,} points have NaN coordinates (PCD 'no "
                                     "return' values)")
    return missing


def read_pcd(path: Path) -> PointCloud:
    """Read a PCD file with DATA ascii or binary, without the points whose x, y or z is NaN (counted in
    `nan_points_dropped`)."""
    data = path.read_bytes()
    header, data_offset = _parse_header(data, path)
    dtype = _record_dtype(header, path)
    width, height = _header_int(header, "WIDTH", path), _header_int(header, "HEIGHT", path)
    num_points = _header_int(header, "POINTS", path) if "POINTS" in header else width * height
    if width * height != num_points:
        raise PointCloudFormatError(
            f"{path}: PCD header WIDTH x HEIGHT = {width * height:,} but POINTS = {num_points:,}"
        )
    encoding = " ".join(header["DATA"]).lower()
    body = data[data_offset:]
    if encoding == "binary":
        expected = num_points * dtype.itemsize
        if len(body) != expected:
            raise PointCloudFormatError(
                f"{path}: PCD header declares {num_points:,} points of {dtype.itemsize} bytes ({expected:,} bytes), "
                f"the file holds {len(body):,} bytes of data"
            )
        records = np.frombuffer(body, dtype=dtype, count=num_points)
    elif encoding == "ascii":
        records = _parse_ascii(body, dtype, num_points, path) if num_points else np.empty(0, dtype)
    elif encoding == "binary_compressed":
        raise PointCloudFormatError(
            f"{path}: PCD DATA binary_compressed is not supported; re-save it with DATA binary or ascii"
        )
    else:
        raise PointCloudFormatError(f"{path}: unknown PCD DATA encoding {encoding!r}")
    xyz = np.column_stack([records["x"], records["y"], records["z"]]).astype(np.float64, copy=False)
    missing = _missing_returns(xyz, path)
    n_missing = int(np.count_nonzero(missing))
    if n_missing:
        xyz, records = xyz[~missing], records[~missing]
    points = validate_points(xyz, name=str(path))
    attributes = {}
    for name in dtype.names:
        if name not in ("x", "y", "z") and not name.startswith(_PADDING_FIELD):
            attributes.update(split_columns(name, records[name].copy()))
    return PointCloud(points, attributes, nan_points_dropped=n_missing)


def _format_spec(dtype: np.dtype) -> tuple[str, str, str]:
    """PCD TYPE, SIZE and the ascii printf format of one scalar field."""
    if dtype.kind == "f":
        return "F", str(dtype.itemsize), "%.9g" if dtype.itemsize == 4 else "%.17g"
    return dtype.kind.upper(), str(dtype.itemsize), "%d"


def write_pcd(path: Path, chunks: ChunkSource, stats: CloudStats, encoding: str) -> tuple[str, ...]:
    """Write PCD with DATA `encoding` ('binary' or 'ascii'), assembled in memory; x, y, z as float32 unless that
    errs > 1 mm."""
    xyz_code = "<f4" if stats.float32_error <= FLOAT32_MAX_ERROR_M else "<f8"
    layout = [(axis, xyz_code) for axis in ("x", "y", "z")]
    layout += [(name, dtype.newbyteorder("<")) for name, dtype in stats.dtypes.items()]
    parts = []
    for chunk in chunks():
        part = np.empty(len(chunk), dtype=np.dtype(layout))
        for column, axis in enumerate(("x", "y", "z")):
            part[axis] = chunk.points[:, column]
        for name, values in chunk.attributes.items():
            part[name] = values
        parts.append(part)
    records = np.concatenate(parts)
    specs = [_format_spec(records.dtype[name]) for name in records.dtype.names]
    header = "\n".join(
        [
            "# .PCD v0.7 - Point Cloud Data file format (written by mapsqueeze)",
            "VERSION 0.7",
            "FIELDS " + " ".join(records.dtype.names),
            "SIZE " + " ".join(size for _, size, _ in specs),
            "TYPE " + " ".join(kind for kind, _, _ in specs),
            "COUNT " + " ".join("1" for _ in specs),
            f"WIDTH {len(records)}",
            "HEIGHT 1",
            "VIEWPOINT 0 0 0 1 0 0 0",
            f"POINTS {len(records)}",
            f"DATA {encoding}",
        ]
    )
    if encoding == "binary":
        body = records.tobytes()
    else:
        text = io.StringIO()
        np.savetxt(text, records, fmt=[fmt for _, _, fmt in specs])
        body = text.getvalue().encode("ascii")
    with atomic_output(path) as temp:
        temp.write_bytes(header.encode("ascii") + b"\n" + body)
    return tuple(stats.dtypes)
