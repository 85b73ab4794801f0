"""Point-cloud file I/O: the only place that knows file formats (KITTI .bin, nuScenes .pcd.bin, PLY, PCD,
LAS/LAZ, .npy). Points are (N, 3) float64 metres with named per-point attributes and file metadata
(`PointCloud`); `formats` holds the table of formats, one module per family (tables, ply, pcd, las) their layouts
and precision."""

from mapsqueeze.io.atomic import atomic_output, atomic_write_bytes, check_output_path, work_dir
from mapsqueeze.io.folders import is_point_cloud_path, point_cloud_files
from mapsqueeze.io.formats import (
    DEFAULT_CHUNK_POINTS,
    FORMATS,
    SUPPORTED_FORMATS,
    dropped_fields,
    format_name,
    holds_crs,
    holds_metadata,
    iter_point_clouds,
    iter_points,
    read_point_cloud,
    read_points,
    unnamed_fields,
    warn_of_crs_loss,
    write_point_chunks,
    write_points,
)
from mapsqueeze.io.pointcloud import (
    FLOAT32_MAX_ERROR_M,
    MAX_ABS_COORDINATE_M,
    PointCloud,
    drop_zero_points,
    validate_attributes,
    validate_points,
)

__all__ = [
    "DEFAULT_CHUNK_POINTS",
    "FLOAT32_MAX_ERROR_M",
    "FORMATS",
    "LAS_SCALE_M",
    "MAX_ABS_COORDINATE_M",
    "SUPPORTED_FORMATS",
    "PointCloud",
    "atomic_output",
    "atomic_write_bytes",
    "check_output_path",
    "drop_zero_points",
    "dropped_fields",
    "format_name",
    "holds_crs",
    "holds_metadata",
    "is_point_cloud_path",
    "iter_point_clouds",
    "iter_points",
    "point_cloud_files",
    "read_point_cloud",
    "read_points",
    "unnamed_fields",
    "validate_attributes",
    "validate_points",
    "warn_of_crs_loss",
    "write_point_chunks",
    "work_dir",
    "write_points",
]


def __getattr__(name: str):
    """LAS_SCALE_M from io.las, imported (with laspy) when asked for."""
    if name == "LAS_SCALE_M":
        from mapsqueeze.io.las import LAS_SCALE_M

        return LAS_SCALE_M
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
