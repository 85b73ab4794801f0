"""PCD files (Point Cloud Library, header v0.7): a reader of DATA ascii, binary and binary_compressed, a writer of
DATA ascii and binary.

Fields with COUNT k > 1 become attributes `name_0` .. `name_{k-1}`; padding fields named `_` are dropped.
PCL's packed colour, `rgb` (a float32 in pcl::PointXYZRGB, a NaN bit pattern when alpha is 255; in ascii, as PCL writes
it, the bits as an unsigned integer, or else the floats' values) or `rgba` (uint32), 0xAARRGGBB, is read as uint8
attributes `red`, `green`, `blue` (and `alpha` for rgba) and written back packed the same way.
Points whose x, y or z is NaN, the "no return" marker of organised clouds written by PCL and ROS drivers, are left
out with their attributes and counted (`PointCloud.nan_points_dropped`); infinite coordinates are refused.
DATA binary_compressed (pcl::io::savePCDFileBinaryCompressed, Autoware maps) is a uint32 compressed size, a uint32
uncompressed size (points x point size, else refused) and an LZF block (io.lzf) of each field for every point in
turn; bytes after the block are ignored, as PCL does.
"""

import io
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mapsqueeze.errors import InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.io import lzf
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
_COMPRESSED_SIZES = struct.Struct("<II")  # binary_compressed: compressed, uncompressed bytes
_COLOUR_CHANNELS = ("red", "green", "blue", "alpha")  # bytes 2, 1, 0, 3 of a packed colour (0xAARRGGBB)
_PACKED_COLOURS = {"rgb": _COLOUR_CHANNELS[:3], "rgba": _COLOUR_CHANNELS}
"""PCL's packed colour fields and the uint8 channels each holds."""
_RGB_ALPHA = 255
"""Alpha written into a packed `rgb` float, as pcl::PointXYZRGB sets it."""


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
        values = rows[:, column : column + width].reshape(records[name].shape)
        if name in _PACKED_COLOURS and dtype[name] == np.dtype("<f4"):
            values = _packed_colour_text(values)
        records[name] = values
        column += width
    return records


def _packed_colour_text(values: np.ndarray) -> np.ndarray:
    """An ascii `rgb` float field's (N,) values -> float32 with the packed bits. PCL writes the bits as unsigned
    integers, other writers the float's value: one reading for the whole column, integers only where every value is
    a whole number in [0, 2^32), so that a float that happens to be whole (1.0: bits 0x3F800000) is not read as 1."""
    whole = (values == np.floor(values)) & (values >= 0) & (values < 2.0**32)
    return values.astype("<u4").view("<f4") if whole.all() else values.astype("<f4")


def _fields(path: Path) -> tuple[dict[str, np.ndarray], int]:
    """The file's fields in header order, each an (N,) or (N, k) array over the file's data or its decompressed
    block (padding fields included), and N, the point count."""
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
    if encoding == "binary":
        expected, held = num_points * dtype.itemsize, len(data) - data_offset
        if held != expected:
            raise PointCloudFormatError(
                f"{path}: PCD header declares {num_points:,} points of {dtype.itemsize} bytes ({expected:,} bytes), "
                f"the file holds {held:,} bytes of data"
            )
        records = np.frombuffer(data, dtype=dtype, count=num_points, offset=data_offset)
    elif encoding == "ascii":
        records = _parse_ascii(data[data_offset:], dtype, num_points, path) if num_points else np.empty(0, dtype)
    elif encoding == "binary_compressed":
        return _decompressed_fields(data, data_offset, dtype, num_points, path), num_points
    else:
        raise PointCloudFormatError(f"{path}: unknown PCD DATA encoding {encoding!r}")
    return {name: records[name] for name in dtype.names}, num_points


def _decompressed_fields(data: bytes, offset: int, dtype: np.dtype, num_points: int,
                         path: Path) -> dict[str, np.ndarray]:
    """The fields of a DATA binary_compressed body at byte `offset` of `data`: uint32 compressed and uncompressed
    sizes, then an LZF block holding each field for every point in turn (structure of arrays). The sizes are
    checked against the header and the file before the uncompressed block is allocated."""
    if len(data) - offset < _COMPRESSED_SIZES.size:
        raise PointCloudFormatError(f"{path}: PCD binary_compressed data ends before its sizes (truncated?)")
    compressed, uncompressed = _COMPRESSED_SIZES.unpack_from(data, offset)
    expected, held = num_points * dtype.itemsize, len(data) - offset - _COMPRESSED_SIZES.size
    if uncompressed != expected:
        raise PointCloudFormatError(
            f"{path}: PCD header declares {num_points:,} points of {dtype.itemsize} bytes ({expected:,} bytes), "
            f"the binary_compressed data says {uncompressed:,} bytes uncompressed"
        )
    if compressed > held:
        raise PointCloudFormatError(
            f"{path}: PCD binary_compressed data declares {compressed:,} compressed bytes, the file holds {held:,} "
            "after the header (truncated?)"
        )
    if uncompressed > compressed * lzf.MAX_EXPANSION:
        raise PointCloudFormatError(
            f"{path}: PCD binary_compressed data declares {uncompressed:,} bytes uncompressed from {compressed:,} "
            f"compressed, more than LZF can expand to ({lzf.MAX_EXPANSION}x)"
        )
    start = offset + _COMPRESSED_SIZES.size
    try:
        block = lzf.decompress(memoryview(data)[start : start + compressed], uncompressed)
    except lzf.LZFError as exc:
        raise PointCloudFormatError(f"{path}: corrupt PCD binary_compressed data (LZF: {exc})") from None
    fields, position = {}, 0
    for name in dtype.names:
        field = dtype[name]
        fields[name] = np.frombuffer(block, dtype=field.base, count=num_points * int(np.prod(field.shape)),
                                     offset=position).reshape(num_points, *field.shape)
        position += num_points * field.itemsize
    return fields


def _missing_returns(fields: dict[str, np.ndarray], num_points: int, path: Path) -> np.ndarray:
    """(N,) bool: the points with a NaN x, y or z (missing returns). Raises InvalidPointCloudError for an infinite
    coordinate (no missing-return marker) or when every point is missing."""
    missing, infinite = np.zeros(num_points, bool), np.zeros(num_points, bool)
    for axis in ("x", "y", "z"):
        missing |= np.isnan(fields[axis])
        infinite |= np.isinf(fields[axis])
    infinite = np.flatnonzero(infinite & ~missing)
    if len(infinite):
        verb = "has" if len(infinite) == 1 else "have"
        raise InvalidPointCloudError(
            f"{path}: {len(infinite):,} of {num_points:,} points {verb} infinite coordinates (the first: point "
            f"{int(infinite[0]):,}, counting from 0; NaN marks a missing return in PCD, infinity does not)"
        )
    if num_points and missing.all():
        raise InvalidPointCloudError(f"{path}: no points: all {num_points:,} points have NaN coordinates (PCD 'no "
                                     "return' values)")
    return missing


def pcd_chunks(path: Path, chunk_points: int, attributes: bool = True) -> Iterator[PointCloud]:
    """A PCD file's points in chunks of at most chunk_points, without the points whose x, y or z is NaN (counted in
    the first chunk's `nan_points_dropped`). The file is read whole (a binary_compressed block decompressed whole:
    it stores each field for every point in turn), so memory is its data plus one chunk."""
    fields, num_points = _fields(path)
    missing = _missing_returns(fields, num_points, path)
    n_missing = int(np.count_nonzero(missing))
    kept = np.flatnonzero(~missing) if n_missing else None
    n_kept = num_points - n_missing
    names = [name for name in fields if name not in ("x", "y", "z") and not name.startswith(_PADDING_FIELD)]
    packed = _packed_colour_fields(fields)
    for first in range(0, max(n_kept, 1), chunk_points):
        rows = slice(first, first + chunk_points) if kept is None else kept[first : first + chunk_points]
        xyz = np.column_stack([fields[axis][rows] for axis in ("x", "y", "z")]).astype(np.float64, copy=False)
        points = validate_points(xyz, str(path), first, n_kept)
        chunk_attributes = {}
        for name in names if attributes else ():
            if name in packed:
                chunk_attributes.update(_unpack_colour(np.array(fields[name][rows]), _PACKED_COLOURS[name]))
            else:
                chunk_attributes.update(split_columns(name, np.array(fields[name][rows])))
        yield PointCloud(points, chunk_attributes, nan_points_dropped=n_missing if first == 0 else 0)


def _packed_colour_fields(fields: dict[str, np.ndarray]) -> set[str]:
    """The packed colour fields to read as channels: `rgb` / `rgba` of 4 bytes a point, at most one, and only where
    no field already has a channel's name."""
    packed = {name for name in _PACKED_COLOURS if name in fields and fields[name].ndim == 1
              and fields[name].dtype.itemsize == 4}
    if len(packed) != 1 or any(channel in fields for channel in _COLOUR_CHANNELS):
        return set()
    return packed


def _unpack_colour(values: np.ndarray, channels: tuple[str, ...]) -> dict[str, np.ndarray]:
    """A packed colour field's (N,) 4-byte values (0xAARRGGBB, any dtype) -> uint8 channels."""
    bits = values.view("<u4")
    shifts = {"red": 16, "green": 8, "blue": 0, "alpha": 24}
    return {channel: (bits >> shifts[channel] & 0xFF).astype(np.uint8) for channel in channels}


def _packed_colour(dtypes: dict[str, np.dtype]) -> str | None:
    """The packed field that uint8 `red`, `green`, `blue` (and `alpha`) attributes are written as: `rgba` with
    alpha, else `rgb`; None where they are missing, not uint8, or a field has a packed field's name."""
    channels = _COLOUR_CHANNELS if "alpha" in dtypes else _COLOUR_CHANNELS[:3]
    if any(dtypes.get(channel) != np.uint8 for channel in channels) or any(name in dtypes for name in _PACKED_COLOURS):
        return None
    return "rgba" if "alpha" in dtypes else "rgb"


def _pack_colour(attributes: dict[str, np.ndarray], field: str) -> np.ndarray:
    """uint8 channels -> PCL's packed colour: `rgb` a float32 (alpha _RGB_ALPHA), `rgba` a uint32."""
    alpha = attributes["alpha"] if field == "rgba" else _RGB_ALPHA
    bits = (np.uint32(alpha) << 24 | attributes["red"].astype(np.uint32) << 16
            | attributes["green"].astype(np.uint32) << 8 | attributes["blue"].astype(np.uint32)).astype("<u4")
    return bits.view("<f4") if field == "rgb" else bits


def _format_spec(dtype: np.dtype) -> tuple[str, str, str]:
    """PCD TYPE, SIZE and the ascii printf format of one scalar field."""
    if dtype.kind == "f":
        return "F", str(dtype.itemsize), "%.9g" if dtype.itemsize == 4 else "%.17g"
    return dtype.kind.upper(), str(dtype.itemsize), "%d"


def write_pcd(path: Path, chunks: ChunkSource, stats: CloudStats, encoding: str) -> tuple[str, ...]:
    """Write PCD with DATA `encoding` ('binary' or 'ascii'), assembled in memory; x, y, z as float32 unless that
    errs > 1 mm; uint8 red, green, blue (and alpha) packed as PCL's `rgb` (`rgba`) in place of the first of them."""
    xyz_code = "<f4" if stats.float32_error <= FLOAT32_MAX_ERROR_M else "<f8"
    colour = _packed_colour(stats.dtypes)
    channels = set(_PACKED_COLOURS[colour]) if colour else set()
    layout = [(axis, xyz_code) for axis in ("x", "y", "z")]
    for name, dtype in stats.dtypes.items():
        if name not in channels:
            layout.append((name, dtype.newbyteorder("<")))
        elif name == "red":
            layout.append((colour, "<f4" if colour == "rgb" else "<u4"))
    parts = []
    for chunk in chunks():
        part = np.empty(len(chunk), dtype=np.dtype(layout))
        for column, axis in enumerate(("x", "y", "z")):
            part[axis] = chunk.points[:, column]
        for name, values in chunk.attributes.items():
            if name not in channels:
                part[name] = values
        if colour:
            part[colour] = _pack_colour(chunk.attributes, colour)
        parts.append(part)
    records = np.concatenate(parts)
    specs = [_format_spec(records.dtype[name]) for name in records.dtype.names]
    text_records = records
    if colour == "rgb":  # in ascii its bits as an unsigned integer, as PCL writes it (alpha 255: each float a NaN)
        specs[records.dtype.names.index("rgb")] = ("F", "4", "%d")
        text_records = records.view([(name, "<u4" if name == "rgb" else records.dtype[name])
                                     for name in records.dtype.names])
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
        np.savetxt(text, text_records, fmt=[fmt for _, _, fmt in specs])
        body = text.getvalue().encode("ascii")
    with atomic_output(path) as temp:
        temp.write_bytes(header.encode("ascii") + b"\n" + body)
    return tuple(stats.dtypes)
