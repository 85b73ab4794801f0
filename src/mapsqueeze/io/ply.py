"""PLY: the vertex element's scalar properties (list properties are skipped) are x, y, z and the attributes.

Written binary little-endian (streamed chunk by chunk) or ascii (assembled in memory); x, y, z as float32 unless
that errs by more than FLOAT32_MAX_ERROR_M; every attribute as its own dtype (64-bit integers narrowed to 32 bits
when they fit, which PLY needs).
"""

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import plyfile

from mapsqueeze.errors import InvalidPointCloudError, PointCloudFormatError
from mapsqueeze.io.atomic import atomic_output
from mapsqueeze.io.pointcloud import (FLOAT32_MAX_ERROR_M, ChunkSource, CloudStats, PointCloud, row_chunks,
                                     validate_points)

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
    for part in row_chunks(data, chunk_points):
        points = validate_points(np.column_stack([part["x"], part["y"], part["z"]]), name=str(path))
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
            header = ["ply", "format binary_little_endian 1.0", f"element vertex {stats.n_points}",
                      *(f"property {_PLY_TYPE_NAMES[dtype[name].str[1:]]} {name}" for name in dtype.names),
                      "end_header"]
            with open(temp, "wb") as stream:
                stream.write(("\n".join(header) + "\n").encode("ascii"))
                for chunk in chunks():
                    stream.write(_vertices(chunk, dtype).view(np.uint8).data)
    return tuple(stats.dtypes)
