"""The check every point cloud passes where it enters the package: numeric (N, 3), finite, plausible metres."""

import numpy as np

from mapsqueeze.errors import InvalidPointCloudError

MAX_ABS_COORDINATE_M = 1e7
"""Coordinates at or beyond 10,000 km from the origin are rejected as absurd (UTM eastings/northings fit)."""


def validate_points(points, name: str = "point cloud", first: int | None = None,
                    total: int | None = None) -> np.ndarray:
    """Return `points` as a C-contiguous (N, 3) float64 array, or raise InvalidPointCloudError.

    Checks: numeric, shape (N, 3) with N > 0, all finite, every |coordinate| < MAX_ABS_COORDINATE_M. A chunk of a
    cloud read or written in parts gives `first`, the cloud's number of its first point (counting from 0), and
    `total`, the cloud's point count when known, so that an error names points of the cloud, not of the chunk
    (first None: the array is the whole cloud).
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
        raise InvalidPointCloudError(_non_finite_message(name, np.isfinite(array).all(axis=1), first, total))
    largest = float(max(-lowest, highest))
    if largest >= MAX_ABS_COORDINATE_M:
        raise InvalidPointCloudError(
            f"{name}: absurd coordinate {largest:.6g} m (limit {MAX_ABS_COORDINATE_M:.0e} m from the origin)"
        )
    return array


def _non_finite_message(name: str, finite: np.ndarray, first: int | None, total: int | None) -> str:
    """One line: how many of the points numbered first.. (one per entry of `finite`) have a NaN or infinite
    coordinate, which is the first of them, and, for a chunk of a larger cloud, which points were not checked."""
    whole = first is None or (first == 0 and total == len(finite))
    first = first or 0
    bad = np.flatnonzero(~finite)
    count, last = len(bad), first + len(finite) - 1
    verb = "has" if count == 1 else "have"
    where = f"the first: point {first + int(bad[0]):,}, counting from 0"
    if whole:
        return f"{name}: {count:,} of {len(finite):,} points {verb} NaN or infinite coordinates ({where})"
    unchecked = ("; any later points are not checked" if total is None
                 else f"; points from {last + 1:,} on are not checked" if last + 1 < total else "")
    of_total = "" if total is None else f" (of {total:,})"
    return (f"{name}: {count:,} of points {first:,} to {last:,}{of_total} {verb} NaN or infinite coordinates "
            f"({where}{unchecked})")
