"""PLY: the vertex element's scalar properties (list properties are skipped) are x, y, z and the attributes.

Written binary little-endian (streamed chunk by chunk) or ascii (assembled in memory); x, y, z as float32 unless
that errs by more than FLOAT32_MAX_ERROR_M; every attribute as its own dtype (64-bit integers narrowed to 32 bits
when they fit, which PLY needs).
"""

import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np
import plyfile

from mapsqueeze.errors import InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.io.atomic import atomic_output
from mapsqueeze.io.pointcloud import (FLOAT32_MAX_ERROR_M, ChunkSource, CloudStats, PointCloud, float32_error_m,
                                     row_chunks, validate_points)

_PLY_INTEGER_TYPES = (np.int32, np.uint32)
_PLY_TYPE_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                   "f4": "float", "f8": "double"}


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


def ply_chunks(path: Path, chunk_points: int, attributes: bool = True) -> Iterator[PointCloud]:
    data, names = _ply_vertices(path)
    names = names if attributes else []
    if len(data) == 0:
        raise InvalidPointCloudError(f"{path}: the point cloud is empty")
    xyz_only = data.dtype == np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8")])  # each row is a point's 3 floats
    for first, part in zip(range(0, len(data), chunk_points), row_chunks(data, chunk_points)):
        points = part.view("<f8").reshape(-1, 3) if xyz_only else np.column_stack([part["x"], part["y"], part["z"]])
        points = validate_points(points, str(path), first, len(data))
        yield PointCloud(points, {name: part[name].copy() for name in names if name not in ("x", "y", "z")})


def _ply_dtype(name: str, dtype: np.dtype, chunks: ChunkSource) -> np.dtype:
    """The dtype a PLY property can hold losslessly: 64-bit integers narrow to 32 bits when they fit."""
    if dtype.kind == "f" or dtype.itemsize < 8:
        return dtype.newbyteorder("<")
    narrow = np.dtype(_PLY_INTEGER_TYPES[dtype.kind == "u"])
    for chunk in chunks():
        values = chunk.attributes[name]
        if values.min() < np.iinfo(narrow).min or values.max() > np.iinfo(narrow).max:
            raise InvalidPointCloudError(f"attribute {name!r} does not fit the 32-bit integers PLY can store")
    return narrow.newbyteorder("<")


def _vertex_dtype(chunks: ChunkSource, stats: CloudStats) -> np.dtype:
    xyz_code = "<f4" if stats.float32_error <= FLOAT32_MAX_ERROR_M else "<f8"
    layout = [(axis, xyz_code) for axis in ("x", "y", "z")]
    layout += [(name, _ply_dtype(name, dtype, chunks)) for name, dtype in stats.dtypes.items()]
    return np.dtype(layout)


def _vertices(chunk: PointCloud, dtype: np.dtype) -> np.ndarray:
    vertices = np.empty(len(chunk), dtype=dtype)
    for column, axis in enumerate(("x", "y", "z")):
        vertices[axis] = chunk.points[:, column]
    for name, values in chunk.attributes.items():
        vertices[name] = values
    return vertices


def write_ply(path: Path, chunks: ChunkSource, stats: CloudStats, text: bool) -> tuple[str, ...]:
    dtype = _vertex_dtype(chunks, stats)
    with atomic_output(path) as temp:
        if text:
            vertices = np.concatenate([_vertices(chunk, dtype) for chunk in chunks()])
            plyfile.PlyData([plyfile.PlyElement.describe(vertices, "vertex")], text=True).write(str(temp))
        else:
            with open(temp, "wb") as stream:
                stream.write(_binary_header(stats.n_points, dtype))
                for chunk in chunks():
                    stream.write(_vertices(chunk, dtype).view(np.uint8).data)
    return tuple(stats.dtypes)


def _binary_header(n_points: int, dtype: np.dtype) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", f"element vertex {n_points}",
             *(f"property {_PLY_TYPE_NAMES[dtype[name].str[1:]]} {name}" for name in dtype.names), "end_header"]
    return ("\n".join(lines) + "\n").encode("ascii")


MOVE_CHUNK_POINTS = 1 << 16
"""Points `write_ply_stream` checks for float32 at once, and moves or narrows at once (1.5 MB of float64)."""


def write_ply_stream(path: Path, clouds: Iterable[np.ndarray], float32_certain: bool,
                     estimate: Callable[[int], int]) -> int:
    """Binary PLY of x, y, z only, written as the (n, 3) clouds arrive, without a spill file or a statistics pass:
    the bytes `write_ply` writes for their concatenation; returns the point count. The points go after a header
    sized for estimate(first cloud's count) points, moved once when the count has another number of digits. x, y, z
    are float32 when `float32_certain` (the caller knows float32 errs by at most FLOAT32_MAX_ERROR_M), else float64,
    narrowed to float32 at the end when every point allows it."""
    code = "<f4" if float32_certain else "<f8"
    n_points, error, start = 0, 0.0, None
    with atomic_output(path) as temp, open(temp, "w+b") as stream:
        for cloud in clouds:
            points = validate_points(cloud, f"points for {path}", n_points)
            if start is None:
                start = len(_binary_header(estimate(len(points)), _xyz_dtype(code)))
                stream.seek(start)
            for first in range(0, len(points) if error <= FLOAT32_MAX_ERROR_M and not float32_certain else 0,
                               MOVE_CHUNK_POINTS):  # until one point needs float64; temporaries of a chunk
                error = max(error, float32_error_m(points[first:first + MOVE_CHUNK_POINTS]))
            stream.write(np.ascontiguousarray(points, dtype=code).data)
            n_points += len(points)
            del cloud, points  # released before the next cloud arrives
        if not n_points:
            raise InvalidPointCloudError(f"points for {path}: the point cloud is empty")
        final = "<f4" if error <= FLOAT32_MAX_ERROR_M else code
        header = _binary_header(n_points, _xyz_dtype(final))
        _move_rows(stream, start, code, len(header), final, 3 * n_points)
        stream.seek(0)
        stream.write(header)
        stream.truncate(len(header) + 3 * n_points * np.dtype(final).itemsize)
    return n_points


def _xyz_dtype(code: str) -> np.dtype:
    return np.dtype([(axis, code) for axis in ("x", "y", "z")])


def _move_rows(stream, source: int, source_code: str, target: int, target_code: str, count: int) -> None:
    """Move `count` values of dtype source_code at byte `source` of the file to byte `target` as target_code
    (a value at most as wide): forwards when each chunk's write ends before the next chunk's read starts (a
    narrower target gains step x (width - target width) bytes a chunk), else backwards (same width only)."""
    if source == target and source_code == target_code:
        return
    width, target_width = np.dtype(source_code).itemsize, np.dtype(target_code).itemsize
    step = 3 * MOVE_CHUNK_POINTS
    forward = target - source <= step * (width - target_width)
    if not forward and target_width != width:
        raise ValueError("a body moves to a later offset only at its own width")
    starts = range(0, count, step) if forward else reversed(range(0, count, step))
    handle = stream.fileno()
    stream.flush()
    for first in starts:
        size = min(step, count - first)
        values = np.frombuffer(os.pread(handle, size * width, source + first * width), dtype=source_code)
        os.pwrite(handle, values.astype(target_code).tobytes(), target + first * target_width)
