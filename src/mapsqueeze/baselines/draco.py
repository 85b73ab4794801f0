"""Google Draco (through DracoPy) after an optional voxel filter, which is what lets it reach low rates.

Draco quantises each axis to `bits` bits over the cloud's largest extent: step = extent / (2**bits - 1), so a
decoded point lies within sqrt(3)/2 * step of its (voxel-filtered) input point. The bytes are Draco's own.
"""

from typing import ClassVar

import DracoPy
import numpy as np

from mapsqueeze.baselines.base import BaselineCodec, Setting, setting_number
from mapsqueeze.errors import BaselineError, ContainerError
from mapsqueeze.geometry.voxel import voxel_filter
from mapsqueeze.geometry.validation import MAX_ABS_COORDINATE_M, validate_points

VOXEL_SIZES_M = (0.0, 0.2, 0.4, 0.8, 1.6)
"""Voxel-filter sizes (metres) of the benchmark sweep; 0 keeps every point."""
QUANTIZATION_BITS = (6, 7, 8, 9, 10, 11, 12, 14)
"""Draco position quantisation bits of the benchmark sweep."""
COMPRESSION_LEVEL = 10
"""Draco's slowest, smallest setting (0..10)."""


class DracoCodec(BaselineCodec):
    """Setting {"voxel_m": voxel-filter size in metres (0 = none), "bits": quantisation bits 1..30}."""

    name: ClassVar[str] = "draco"

    def settings(self) -> list[Setting]:
        return [{"voxel_m": voxel, "bits": bits} for voxel in VOXEL_SIZES_M for bits in QUANTIZATION_BITS]

    def encode(self, points: np.ndarray, setting: Setting) -> bytes:
        points = validate_points(points)
        voxel = setting_number(setting, "voxel_m", self.name, 0.0, MAX_ABS_COORDINATE_M)
        bits = setting_number(setting, "bits", self.name, 1, 30)
        if not bits.is_integer():
            raise BaselineError(f"draco: bits must be an integer, got {bits!r}")
        if voxel > 0:
            points = voxel_filter(points, voxel)
        return bytes(DracoPy.encode(points, quantization_bits=int(bits), compression_level=COMPRESSION_LEVEL))

    def decode(self, data: bytes) -> np.ndarray:
        try:
            decoded = np.asarray(DracoPy.decode(bytes(data)).points, dtype=np.float64)
        except Exception as exc:  # DracoPy raises assorted types (FileTypeException, ValueError, ...)
            raise ContainerError(f"draco: cannot decode ({exc})") from None
        if decoded.ndim != 2 or decoded.shape[1] != 3 or len(decoded) == 0 or not np.isfinite(decoded).all():
            raise ContainerError(f"draco: decoded data is not a non-empty (K, 3) point cloud (shape {decoded.shape})")
        return decoded
