"""Patch planes in numpy, without numba: the same bytes as the compiled kernel of `geometry.patches` (every
floating-point operation in the kernel's order; sums added point by point, arccos and the patches' cos from the C
library as numba's), about 2x its time per call. The decoder uses it, so that no decoding process loads numba
(~120 MB and 0.4-0.9 CPU-s a process, BENCHMARKS.md "Throughput"); the encoder, which loads numba anyway, uses
the compiled kernel."""

from __future__ import annotations

import math
from collections.abc import Iterator
from functools import partial

import numpy as np

from mapsqueeze.geometry.rows import select_rows
from mapsqueeze.geometry.threads import run_shared
from mapsqueeze.geometry.surface import GOLDEN_ANGLE, GOLDEN_FRACTION

_BLOCK_POINTS = 1 << 15
"""Points reworked at once (whole patches; bounds the float64 temporaries to a few MB)."""


def checked_points(points: np.ndarray, patch: int, upper: np.ndarray | None, float32_kept: bool = False
                   ) -> tuple[np.ndarray, np.float32, np.ndarray]:
    """(contiguous float64 points, lower and upper float32 box bounds) of `patch_planes`'s arguments; ValueError
    unless the points are whole patches. `float32_kept`: float32 points stay float32 (`_block` widens each block's
    points as it transposes them, the same values)."""
    points = np.ascontiguousarray(points, dtype=np.float32 if float32_kept and points.dtype == np.float32
                                  else np.float64)
    if patch < 1 or len(points) % patch:
        raise ValueError(f"{len(points)} points are not whole patches of {patch}")
    low = np.float32(-np.inf if upper is None else 0.0)
    box = np.full(3, np.inf, dtype=np.float32) if upper is None else np.asarray(upper).astype(np.float32)
    return points, low, box


def patch_planes(points: np.ndarray, patch: int, strength: float, copies: int, radius_m: float,
                 upper: np.ndarray | None = None) -> np.ndarray:
    """A decoded (K, 3) cloud reworked per decoder patch, no neighbour search: rows [i patch, (i + 1) patch) are
    the points one parent spawned (K a multiple of `patch`). Each patch's PCA plane (centroid, unit normal of the
    smallest covariance eigenvalue in closed form, its largest component made positive); its points moved
    `strength` (0..1) of their offset along the normal towards it, each followed by its `copies` extra points on
    the disk of `radius_m` metres around it in that plane (the pattern of `surface.disk_samples`, sample
    s = i copies + j). Returns float32 points in that order, only those inside the box [0, upper] (float32
    comparison, like `codec.tilepoints.keep_inside`) when `upper` (metres) is given."""
    points, low, box = checked_points(np.asarray(points), patch, upper, float32_kept=True)
    step = max(1, _BLOCK_POINTS // patch) * patch
    blocks = [select_rows(*_block(points[start:start + step], start, patch, float(strength), copies, float(radius_m),
                                  low, box)) for start in range(0, len(points), step)]
    return blocks[0] if len(blocks) == 1 else np.concatenate(blocks or [np.zeros((0, 3), dtype=np.float32)])


def patch_planes_chosen(points: np.ndarray, patch: int, options, choices: np.ndarray,
                        upper: np.ndarray | None = None) -> np.ndarray:
    """`patch_planes` of each patch alone (its disk samples numbered from its first point) with its own
    (strength, copies, radius_m) = options[choices[i]], the patches' points concatenated in patch order: the
    bytes of calling `patches.patch_planes` patch by patch, with the patches of one option reworked at once."""
    points, low, box = checked_points(np.asarray(points), patch, upper, float32_kept=True)
    n_patches = len(points) // patch
    choices = np.asarray(choices)
    if len(choices) != n_patches:
        raise ValueError(f"{len(choices)} choices for {n_patches} patches")
    grouped = points.reshape(n_patches, patch, 3)
    pieces: list = [None] * n_patches

    def rework(chosen: np.ndarray, strength: float, copies: int, radius_m: float) -> None:
        out, inside = _block(grouped[chosen].reshape(-1, 3), 0, patch, float(strength), copies, float(radius_m),
                             low, box, per_patch=True)
        kept = select_rows(out, inside)
        ends = np.cumsum(inside.reshape(len(chosen), -1).sum(axis=1)).tolist()
        for index, start, end in zip(chosen.tolist(), [0] + ends[:-1], ends):
            pieces[index] = kept[start:end]

    step = max(1, _BLOCK_POINTS // patch)
    tasks = []
    for option in np.unique(choices).tolist():
        members = np.flatnonzero(choices == option)
        tasks += [partial(rework, members[first:first + step], *options[option])
                  for first in range(0, len(members), step)]
    run_shared(tasks)  # blocks of distinct patches: idle decoding threads may take some
    return np.concatenate(pieces) if pieces else np.zeros((0, 3), dtype=np.float32)


def _block(points: np.ndarray, first: int, patch: int, strength: float, copies: int, radius_m: float,
           low: np.float32, box: np.ndarray, per_patch: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """`patch_planes` of whole patches whose first point is row `first` of the cloud (the disk samples' index;
    per_patch: numbered from each patch's first point instead), before the crop: the (K (1 + copies), 3) float32
    points and the mask of those inside the box."""
    return reworked_points(fit_planes(points, patch), first, strength, copies, radius_m, low, box, per_patch)


def fit_planes(points: np.ndarray, patch: int) -> tuple:
    """The planes of whole patches, what `reworked_points` needs of them under any option: the points' x, y, z
    ((n_patches, patch) float64 each), the patches' unit normals and tangents (x, y, z of each: (n_patches,)) and
    each point's offset from its patch's plane before the pull strength ((n_patches, patch))."""
    n_patches = len(points) // patch
    x, y, z = np.ascontiguousarray(points.T, dtype=np.float64).reshape(3, n_patches, patch)
    by_rank = np.ascontiguousarray(points.reshape(n_patches, patch, 3).transpose(1, 2, 0),
                                   dtype=np.float64)  # (patch, 3, n_patches)
    mean = _running_sum(by_rank) / patch
    offsets = by_rank - mean
    products = np.empty((patch, 6, n_patches))
    for row, (first_axis, second_axis) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
        np.multiply(offsets[:, first_axis], offsets[:, second_axis], out=products[:, row])
    nx, ny, nz = _smallest_eigenvectors(*_running_sum(products))
    # tangents as `surface._tangents`: t1 = normalise(n x e), e the axis of n's smallest component; t2 = n x t1
    ax, ay, az = np.abs(nx), np.abs(ny), np.abs(nz)
    zero = np.zeros(n_patches)
    x_smallest, y_smallest = (ax <= ay) & (ax <= az), ay <= az
    fx = np.where(x_smallest, zero, np.where(y_smallest, -nz, ny))
    fy = np.where(x_smallest, nz, np.where(y_smallest, zero, -nx))
    fz = np.where(x_smallest, -ny, np.where(y_smallest, nx, zero))
    length = np.sqrt(fx * fx + fy * fy + fz * fz)
    fx, fy, fz = fx / length, fy / length, fz / length
    sx, sy, sz = ny * fz - nz * fy, nz * fx - nx * fz, nx * fy - ny * fx
    # offset = (x - mean) n_x + (y - mean) n_y + (z - mean) n_z (times the strength later): each difference and
    # product rounded as before, added in that order
    offset = np.subtract(x, mean[0][:, None])
    offset *= nx[:, None]
    term = np.empty_like(offset)
    for column, centre, normal in ((y, mean[1], ny), (z, mean[2], nz)):
        np.subtract(column, centre[:, None], out=term)
        term *= normal[:, None]
        offset += term
    return x, y, z, (nx, ny, nz), (fx, fy, fz), (sx, sy, sz), offset


def reworked_points(planes: tuple, first: int, strength: float, copies: int, radius_m: float, low: np.float32,
                    box: np.ndarray, per_patch: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """`_block`'s points and mask from the patches' `fit_planes` (the same bytes as fitting them again)."""
    n_patches, patch = planes[0].shape
    out = np.empty((n_patches * patch, 1 + copies, 3), dtype=np.float32)
    for axis, (moved, extra) in enumerate(reworked_axes(planes, first, strength, copies, radius_m, per_patch)):
        out[:, 0, axis] = moved.ravel()
        if copies:
            out[:, 1:, axis] = extra.reshape(-1, copies)
    out = out.reshape(-1, 3)
    inside = out[:, 0] >= low  # in place, as `tilepoints.keep_inside`
    inside &= out[:, 0] <= box[0]
    for axis in (1, 2):
        inside &= out[:, axis] >= low
        inside &= out[:, axis] <= box[axis]
    return out, inside


def reworked_axes(planes: tuple, first: int, strength: float, copies: int, radius_m: float,
                  per_patch: bool = False) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """`reworked_points`'s float64 coordinates before their float32 rounding, axis after axis: the moved points'
    ((n_patches, patch)) and their extra points' ((n_patches, patch, copies); None without), in arrays that the
    next axis overwrites."""
    x, y, z, normals, first_tangents, second_tangents, unscaled = planes
    n_patches, patch = x.shape
    offset = unscaled * strength
    along = None
    if copies:
        sample = np.arange(0 if per_patch else first * copies,
                           (patch if per_patch else first + n_patches * patch) * copies, dtype=np.float64)
        product = sample * GOLDEN_FRACTION
        radius = radius_m * np.sqrt(product - np.floor(product))  # % 1.0 of these non-negative numbers, exactly
        angle = sample * GOLDEN_ANGLE
        u = (radius * np.cos(angle)).reshape(-1, patch, copies)  # (1, patch, copies) per patch: the same samples
        v = (radius * np.sin(angle)).reshape(-1, patch, copies)
        along, across = np.empty((n_patches, patch, copies)), np.empty((n_patches, patch, copies))
    moved = np.empty_like(offset)
    for column, normal, first_tangent, second_tangent in zip((x, y, z), normals, first_tangents, second_tangents):
        np.multiply(offset, normal[:, None], out=moved)
        np.subtract(column, moved, out=moved)
        if copies:
            np.multiply(u, first_tangent[:, None, None], out=along)
            along += moved[..., None]
            np.multiply(v, second_tangent[:, None, None], out=across)
            along += across
        yield moved, along


def _running_sum(values: np.ndarray) -> np.ndarray:
    """The sum over the first axis added row by row from 0.0, as the kernel adds its points: numpy reduces an
    axis that is not the innermost one row after row (it adds pairwise only along the contiguous axis it loops
    over innermost; tests/test_patchesnumpy.py checks the order)."""
    return np.add.reduce(values, axis=0, initial=0.0)


def _smallest_eigenvectors(xx, yy, zz, xy, xz, yz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per patch, the kernel's `_smallest_eigenvector` of the symmetric 3 x 3 matrices of these (n,) entries:
    (n,) x, y, z of the unit eigenvector of the smallest eigenvalue, its largest component positive; (0, 0, 1)
    where the matrix is a multiple of the identity (or 0)."""
    n = len(xx)
    best_x, best_y, best_z, best = np.zeros(n), np.zeros(n), np.ones(n), np.zeros(n)
    q = (xx + yy + zz) / 3.0
    p2 = (xx - q) ** 2 + (yy - q) ** 2 + (zz - q) ** 2 + 2.0 * (xy * xy + xz * xz + yz * yz)
    p = np.sqrt(p2 / 6.0)
    spread = p > 0.0
    if spread.any():
        q, p = q[spread], p[spread]
        xx, yy, zz, xy, xz, yz = (value[spread] for value in (xx, yy, zz, xy, xz, yz))
        b00, b11, b22, b01, b02, b12 = (xx - q) / p, (yy - q) / p, (zz - q) / p, xy / p, xz / p, yz / p
        r = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)) / 2.0
        third = 2.0 * np.pi / 3.0  # numpy's arccos rounds differently from the C library's on some CPUs
        cosine = np.array([math.cos(math.acos(min(1.0, max(-1.0, value))) / 3.0 + third) for value in r.tolist()])
        smallest = q + 2.0 * p * cosine
        a0, a1, a2 = xx - smallest, xy, xz
        c0, c1, c2 = xy, yy - smallest, yz
        e0, e1, e2 = xz, yz, zz - smallest
        kept_x, kept_y, kept_z, kept = best_x[spread], best_y[spread], best_z[spread], best[spread]
        for ux, uy, uz, vx, vy, vz in ((a0, a1, a2, c0, c1, c2), (a0, a1, a2, e0, e1, e2),
                                       (c0, c1, c2, e0, e1, e2)):
            nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
            norm = nx * nx + ny * ny + nz * nz
            larger = norm > kept
            kept_x, kept_y, kept_z = np.where(larger, nx, kept_x), np.where(larger, ny, kept_y), \
                np.where(larger, nz, kept_z)
            kept = np.where(larger, norm, kept)
        unit = kept > 0.0
        scale = 1.0 / np.sqrt(np.where(unit, kept, 1.0))
        kept_x, kept_y, kept_z = (np.where(unit, value * scale, value) for value in (kept_x, kept_y, kept_z))
        best_x[spread], best_y[spread], best_z[spread] = kept_x, kept_y, kept_z
    largest = np.where(np.abs(best_y) > np.abs(best_x), best_y, best_x)
    largest = np.where(np.abs(best_z) > np.abs(largest), best_z, largest)
    flip = largest < 0.0
    return np.where(flip, -best_x, best_x), np.where(flip, -best_y, best_y), np.where(flip, -best_z, best_z)
