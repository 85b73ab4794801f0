"""The check every point cloud passes where it enters the package: numeric (N, 3), finite, plausible metres."""

import numpy as np

from mapsqueeze.errors import InvalidPointCloudError

MAX_ABS_COORDINATE_M = 1e7
"""Coordinates at or beyond 10,000 km from the origin are rejected as absurd (UTM eastings/northings fit)."""


def validate_points(points, name: str = "point cloud") -> np.ndarray:
    """Return `points` as a C-contiguous (N, 3) float64 array, or raise InvalidPointCloudError.

    Checks: numeric, shape (N, 3) with N > 0, all finite, every |coordinate| < MAX_ABS_COORDINATE_M.
    """
    try:
        array = np.asarray(points)
    except (TypeError, ValueError) as exc:
        raise InvalidPointCloudError(f"{name}: not a numeric array ({exc})") from None
    if array.dtype.kind not in "iuf":
        raise InvalidPointCloudError(f"{name}: expected numeric x, y, z, got dtype {array.dtype}")
    if array.ndim != 2 or array.shape[1] != 3:
        raise InvalidPointCloudError(f"{name}: expected an (N, 3) array of x, y, z, got shape {array.shape}")
    if len(array) == 0:
        raise InvalidPointCloudError(f"{name}: the point cloud is empty")
    array = np.ascontiguousarray(array, dtype=np.float64)
    flat = array.reshape(-1)
    lowest, highest = flat.min(), flat.max()  # NaN and infinities propagate into them
    if not (np.isfinite(lowest) and np.isfinite(highest)):
        finite = np.isfinite(array).all(axis=1)
        raise InvalidPointCloudError(
            f"{name}: {np.count_nonzero(~finite):,} of {len(array):,} points have NaN or infinite coordinates"
        )
    largest = float(max(-lowest, highest))
    if largest >= MAX_ABS_COORDINATE_M:
        raise InvalidPointCloudError(
            f"{name}: absurd coordinate {largest:.6g} m (limit {MAX_ABS_COORDINATE_M:.0e} m from the origin)"
        )
    return array
