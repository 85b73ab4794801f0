"""Point-cloud file I/O: the only place that knows file formats (KITTI .bin, nuScenes .pcd.bin, PLY, PCD,
LAS/LAZ, .npy). Points are (N, 3) float64 metres; see `formats` for each format's layout and precision."""

from mapsqueeze.io.atomic import atomic_output, atomic_write_bytes
from mapsqueeze.io.formats import (
    LAS_SCALE_M,
    SUPPORTED_FORMATS,
    format_name,
    iter_points,
    read_point_cloud,
    read_points,
    write_point_chunks,
    write_points,
)
from mapsqueeze.io.pointcloud import (
    FLOAT32_MAX_ERROR_M,
    MAX_ABS_COORDINATE_M,
    PointCloud,
    validate_attributes,
    validate_points,
)

__all__ = [
    "FLOAT32_MAX_ERROR_M",
    "LAS_SCALE_M",
    "MAX_ABS_COORDINATE_M",
    "SUPPORTED_FORMATS",
    "PointCloud",
    "atomic_output",
    "atomic_write_bytes",
    "format_name",
    "iter_points",
    "read_point_cloud",
    "read_points",
    "validate_attributes",
    "validate_points",
    "write_point_chunks",
    "write_points",
]
