"""Patch planes as a compiled kernel: the same bytes as `geometry.patchesnumpy.patch_planes`, about half its
time per call, but it loads numba; the encoder's, which loads numba anyway (`codec.postfilter`).
Deterministic: a single-threaded compiled kernel, fixed sample pattern, no random numbers."""

from __future__ import annotations

import math

import numpy as np

from mapsqueeze.geometry.jit import compiled
from mapsqueeze.geometry.patchesnumpy import checked_points
from mapsqueeze.geometry.surface import GOLDEN_ANGLE, GOLDEN_FRACTION


def patch_planes(points: np.ndarray, patch: int, strength: float, copies: int, radius_m: float,
                 upper: np.ndarray | None = None) -> np.ndarray:
    """`geometry.patchesnumpy.patch_planes` (same arguments and result) in the compiled kernel."""
    out, ends = _rework(points, patch, ((strength, copies, radius_m),), False, upper)
    return out[:ends[-1] if len(ends) else 0]


def patch_options(points: np.ndarray, patch: int, options, upper: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Every patch of a decoded (K, 3) cloud (rows [i patch, (i + 1) patch)) reworked alone under each of `options`
    ((strength, copies, radius_m) as `patch_planes`): the bytes of `patch_planes` called on each patch alone (its
    disk samples numbered from its first point), its plane fitted once. Returns (float32 points, option after
    option and within an option patch after patch; ends: (len(options) n_patches,) int64, the row after patch i
    under option k at [k n_patches + i]); only the points inside [0, upper] when `upper` (metres) is given."""
    out, ends = _rework(points, patch, options, True, upper)
    return out[:ends[-1] if len(ends) else 0], ends


def patch_option_cells(points: np.ndarray, patch: int, options, upper: np.ndarray | None, frame_m: np.ndarray,
                       voxel_m: np.ndarray, low: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct IoU voxels of `patch_options`'s points, without the points: (int32 cells, int64 offsets), list
    l = k n_patches + i (patch i under option k) in cells[offsets[l]:offsets[l + 1]]; a point's cell is that of its
    float32 value p in the grid of `shape` voxels from voxel `low`, the voxel of floor((p + frame_m) / voxel_m)
    (metres; as `occupancy._mark_voxels`). The grid must hold every point inside [0, upper] (fewer than 2^31
    cells). An option with extra points whose pull strength an earlier option without extra points has starts
    from that option's cells of the patch (the same moved points), then adds its extra points' cells: a third less
    work for PATCH_OPTIONS; the cells of a list come in no particular order. The lists are made patch by patch
    (`_option_cells_kernel`: the options of equal strength share the patch's moved points), each option's in turn,
    then gathered in list order (`_gather_lists`). They are written into a reservation of CELLS_RESERVED_PART of the
    reworked points (made again whole when too short), not one per point: the search's peak memory, on every tile
    (malloc's kept heap maps in what any tile touches)."""
    points, box_low, box = checked_points(points, patch, upper)
    strengths, copies, radii = _option_arrays(options)
    n_patches = len(points) // patch
    distinct = list(dict.fromkeys(strengths.tolist()))
    moved_row = np.array([distinct.index(strength) for strength in strengths.tolist()], dtype=np.int64)
    starts = np.zeros(len(options) * n_patches, dtype=np.int64)  # where each list was made, and its length
    lengths = np.zeros(len(options) * n_patches, dtype=np.int64)
    seen = np.zeros(int(np.prod(shape)), dtype=np.uint8)  # 1: in the list being made (cleared after it)
    base = np.array([next((j for j in range(k) if strengths[j] == strengths[k] and copies[j] == 0), -1)
                     if copies[k] else -1 for k in range(len(options))], dtype=np.int64)
    most = len(points) * int(np.sum(1 + copies))  # one cell per reworked point
    for size in (min(most, most // CELLS_RESERVED_PART + patch * int(1 + copies.max(initial=0))), most):
        made = np.empty(size, dtype=np.int32)
        n_cells = _option_cells_kernel(points, patch, strengths, copies, radii, moved_row, len(distinct), box_low,
                                       box, GOLDEN_ANGLE, GOLDEN_FRACTION, starts, lengths,
                                       np.asarray(frame_m, dtype=np.float64), np.asarray(voxel_m, dtype=np.float64),
                                       np.asarray(low, dtype=np.int64), np.asarray(shape, dtype=np.int64), seen,
                                       made, base)
        if n_cells >= 0:
            del seen
            cells = np.empty(n_cells, dtype=np.int32)
            offsets = np.zeros(len(options) * n_patches + 1, dtype=np.int64)
            _gather_lists(made, starts, lengths, cells, offsets)
            return cells, offsets
    raise AssertionError("unreachable: one cell per reworked point fits")


CELLS_RESERVED_PART = 4
"""`patch_option_cells` first reserves this part of one cell per reworked point (plus one patch's points): the
distinct cells of the 25-tile KITTI map's and the real submaps' tiles take 6-12 % of it (e0..e3); when they need
more, the kernel stops at the list that would not fit and runs again with room for every reworked point."""


def patch_setting_voxels(points: np.ndarray, patch: int, strength: float, copies, radius_m: float,
                         upper: np.ndarray, frame_m: np.ndarray, voxel_m: np.ndarray, low: np.ndarray,
                         shape: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Marks the IoU voxels of several patch-plane settings of one decoded (K, 3) cloud in `grid` without making
    their points: bit 1 for the cloud's own points inside the box [0, upper] (metres; `tilepoints.keep_inside`'s
    crop), bit 2 + c for those of `patch_planes(points, patch, strength, copies[c], radius_m, upper)`. A point's
    cell is that of its float32 value p in the flat uint8 grid of `shape` voxels from voxel `low`, the voxel of
    floor((p + frame_m) / voxel_m) (as `occupancy._mark_voxels`); the grid must hold the box. The settings share
    the planes and the disk samples (sample s is extra point s % c of point s // c under c copies: with 1 and 2
    copies, two samples per point instead of three), made in blocks of SAMPLE_BLOCK_POINTS samples or a few more.
    Returns the points marked per bit (the cloud's, then each setting's)."""
    points, box_low, box = checked_points(points, patch, upper)
    copies = np.asarray(copies, dtype=np.int64)
    inside = np.zeros(1 + len(copies), dtype=np.int64)
    whole = math.lcm(*(int(c) for c in copies if c > 0))  # every point's samples in one block
    block = whole * -(-SAMPLE_BLOCK_POINTS // whole)
    _patch_settings_kernel(points, patch, float(strength), copies, float(radius_m), GOLDEN_ANGLE, GOLDEN_FRACTION,
                           block, box_low, box,
                           np.asarray(frame_m, dtype=np.float64), np.asarray(voxel_m, dtype=np.float64),
                           np.asarray(low, dtype=np.int64), np.asarray(shape, dtype=np.int64), grid, inside)
    return inside


SAMPLE_BLOCK_POINTS = 4096
"""Disk samples `patch_setting_voxels` makes at once (rounded up to a multiple of every setting's copies), before
the settings' extra points: 64 KB of them, which stay in the CPU's cache."""


def _option_arrays(options) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(strengths, copies, radii) of (strength, copies, radius_m) options."""
    return (np.array([option[0] for option in options], dtype=np.float64),
            np.array([option[1] for option in options], dtype=np.int64),
            np.array([option[2] for option in options], dtype=np.float64))


def _rework(points: np.ndarray, patch: int, options, per_patch: bool, upper: np.ndarray | None
           ) -> tuple[np.ndarray, np.ndarray]:
    """(float32 points, ends) of `patch_options`; disk samples numbered from each patch's first point when
    per_patch, else from the cloud's."""
    points, low, box = checked_points(points, patch, upper)
    strengths, copies, radii = _option_arrays(options)
    out = np.empty((len(points) * int(np.sum(1 + copies)), 3), dtype=np.float32)
    ends = np.empty(len(options) * (len(points) // patch), dtype=np.int64)
    _patch_planes_kernel(points, patch, strengths, copies, radii, per_patch, low, box, GOLDEN_ANGLE,
                         GOLDEN_FRACTION, out, ends)
    return out, ends


@compiled
def _smallest_eigenvector(xx, yy, zz, xy, xz, yz):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3 x 3 matrix (trigonometric eigenvalues, then
    the largest cross product of two rows of A - l I), its largest component positive; (0, 0, 1) for A = 0."""
    q = (xx + yy + zz) / 3.0
    p2 = (xx - q) ** 2 + (yy - q) ** 2 + (zz - q) ** 2 + 2.0 * (xy * xy + xz * xz + yz * yz)
    p = np.sqrt(p2 / 6.0)
    if not p > 0.0:
        return 0.0, 0.0, 1.0
    b00, b11, b22, b01, b02, b12 = (xx - q) / p, (yy - q) / p, (zz - q) / p, xy / p, xz / p, yz / p
    r = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)) / 2.0
    smallest = q + 2.0 * p * np.cos(np.arccos(min(1.0, max(-1.0, r))) / 3.0 + 2.0 * np.pi / 3.0)
    a0, a1, a2 = xx - smallest, xy, xz
    c0, c1, c2 = xy, yy - smallest, yz
    e0, e1, e2 = xz, yz, zz - smallest
    best_x, best_y, best_z, best = 0.0, 0.0, 1.0, 0.0
    for ux, uy, uz, vx, vy, vz in ((a0, a1, a2, c0, c1, c2), (a0, a1, a2, e0, e1, e2), (c0, c1, c2, e0, e1, e2)):
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        norm = nx * nx + ny * ny + nz * nz
        if norm > best:
            best_x, best_y, best_z, best = nx, ny, nz, norm
    if best > 0.0:
        scale = 1.0 / np.sqrt(best)
        best_x, best_y, best_z = best_x * scale, best_y * scale, best_z * scale
    largest = best_x
    if abs(best_y) > abs(largest):
        largest = best_y
    if abs(best_z) > abs(largest):
        largest = best_z
    if largest < 0.0:
        return -best_x, -best_y, -best_z
    return best_x, best_y, best_z


@compiled
def _store_inside(out, kept, x, y, z, low, box):
    """Write (x, y, z) as float32 at row `kept` when inside [low, box]; the next free row."""
    fx, fy, fz = np.float32(x), np.float32(y), np.float32(z)
    if fx >= low and fy >= low and fz >= low and fx <= box[0] and fy <= box[1] and fz <= box[2]:
        out[kept, 0], out[kept, 1], out[kept, 2] = fx, fy, fz
        return kept + 1
    return kept


@compiled
def _fit_planes(points, patch):
    """(n_patches, 12) float64: each patch's plane, its centroid, unit normal (`_smallest_eigenvector`) and the
    two tangents of `surface._tangents`."""
    n_patches = points.shape[0] // patch
    planes = np.empty((n_patches, 12))
    for index in range(n_patches):
        start = index * patch
        mx = my = mz = 0.0
        for i in range(start, start + patch):
            mx += points[i, 0]
            my += points[i, 1]
            mz += points[i, 2]
        mx, my, mz = mx / patch, my / patch, mz / patch
        xx = yy = zz = xy = xz = yz = 0.0
        for i in range(start, start + patch):
            dx, dy, dz = points[i, 0] - mx, points[i, 1] - my, points[i, 2] - mz
            xx += dx * dx
            yy += dy * dy
            zz += dz * dz
            xy += dx * dy
            xz += dx * dz
            yz += dy * dz
        nx, ny, nz = _smallest_eigenvector(xx, yy, zz, xy, xz, yz)
        # tangents as `surface._tangents`: t1 = normalise(n x e), e the axis of n's smallest component; t2 = n x t1
        ax, ay, az = abs(nx), abs(ny), abs(nz)
        if ax <= ay and ax <= az:
            fx, fy, fz = 0.0, nz, -ny
        elif ay <= az:
            fx, fy, fz = -nz, 0.0, nx
        else:
            fx, fy, fz = ny, -nx, 0.0
        length = np.sqrt(fx * fx + fy * fy + fz * fz)
        fx, fy, fz = fx / length, fy / length, fz / length
        sx, sy, sz = ny * fz - nz * fy, nz * fx - nx * fz, nx * fy - ny * fx
        plane = planes[index]
        plane[0], plane[1], plane[2], plane[3], plane[4], plane[5] = mx, my, mz, nx, ny, nz
        plane[6], plane[7], plane[8], plane[9], plane[10], plane[11] = fx, fy, fz, sx, sy, sz
    return planes


@compiled
def _patch_planes_kernel(points, patch, strengths, copies, radii, per_patch, low, box, golden_angle, golden_fraction,
                         out, ends):
    """`_rework`'s kernel: each patch's plane (centroid, normal, tangents) fitted once, then the patches reworked
    option after option; ends[k n_patches + i]: the row after patch i under option k. Per patch, every patch has
    the same disk samples: those of its first patch are kept and reused (no sine or cosine for the others).
    Returns the rows stored."""
    n_patches = points.shape[0] // patch
    planes = _fit_planes(points, patch)
    disk = np.empty((patch * max(copies.max(), 0) if per_patch else 0, 2))  # per patch: every patch's samples
    kept = 0
    for option in range(strengths.shape[0]):
        strength, n_copies, radius_m = strengths[option], copies[option], radii[option]
        for index in range(n_patches):
            start = index * patch
            first = start if per_patch else 0
            reuse = per_patch and index > 0  # the disk samples of patch 0, computed as they were used
            plane = planes[index]
            mx, my, mz, nx, ny, nz = plane[0], plane[1], plane[2], plane[3], plane[4], plane[5]
            fx, fy, fz, sx, sy, sz = plane[6], plane[7], plane[8], plane[9], plane[10], plane[11]
            for i in range(start, start + patch):
                offset = strength * ((points[i, 0] - mx) * nx + (points[i, 1] - my) * ny + (points[i, 2] - mz) * nz)
                px, py, pz = points[i, 0] - offset * nx, points[i, 1] - offset * ny, points[i, 2] - offset * nz
                kept = _store_inside(out, kept, px, py, pz, low, box)
                for j in range(n_copies):
                    sample = (i - first) * n_copies + j
                    if reuse:
                        u, v = disk[sample, 0], disk[sample, 1]
                    else:
                        u, v = _disk_sample(sample, radius_m, golden_angle, golden_fraction)
                        if per_patch:
                            disk[sample, 0], disk[sample, 1] = u, v
                    kept = _store_inside(out, kept, px + u * fx + v * sx, py + u * fy + v * sy,
                                         pz + u * fz + v * sz, low, box)
            ends[option * n_patches + index] = kept
    return kept


@compiled
def _option_cells_kernel(points, patch, strengths, copies, radii, moved_row, n_moved, low, box, golden_angle,
                         golden_fraction, starts, lengths, frame, voxel, grid_low, grid_shape, seen, cells, base):
    """`patch_option_cells`'s kernel: the points of `_patch_planes_kernel` per patch (disk samples numbered from
    each patch's first point, computed once) reduced to their distinct voxel cells as they are made, patch after
    patch and within a patch option after option: list l = k n_patches + i (patch i under option k) in
    cells[starts[l]:starts[l] + lengths[l]]. A patch's moved points under strength row moved_row[k] (of n_moved
    distinct strengths) are made once, in a loop of their own; each extra point's copy of them in another; their
    cells in a third (`_cells_inside`: no branch, so the compiler vectorises it); then the cells are listed in the
    points' order, each once (seen: 0 per grid cell, a work array, cleared after each list). A patch under an
    option with base[option] >= 0 starts from the cells of option base[option] (the same strength, no extra
    points), its moved points' cells. Returns the cells listed, or -1 (`seen` clear) when `cells` lacks room for
    the most cells of a list: one per point of its patch and extra point."""
    n_patches = points.shape[0] // patch
    n_options = strengths.shape[0]
    planes = _fit_planes(points, patch)
    most_copies = max(copies.max(), 0)
    disk_u, disk_v = np.empty((n_options, most_copies, patch)), np.empty((n_options, most_copies, patch))
    for option in range(n_options):
        for i in range(patch):
            for j in range(copies[option]):
                disk_u[option, j, i], disk_v[option, j, i] = _disk_sample(i * copies[option] + j, radii[option],
                                                                          golden_angle, golden_fraction)
    moved = np.empty((n_moved, 3, patch))  # the patch's moved points per strength
    made = np.zeros(n_moved, dtype=np.bool_)
    extra_x, extra_y, extra_z = np.empty(patch), np.empty(patch), np.empty(patch)
    own = np.empty(patch, dtype=np.int64)  # the moved points' cells, -1 outside the box
    extra = np.empty((most_copies, patch), dtype=np.int64)  # each copy's cells
    n_cells = 0
    for index in range(n_patches):
        start = index * patch
        plane = planes[index]
        mx, my, mz, nx, ny, nz = plane[0], plane[1], plane[2], plane[3], plane[4], plane[5]
        fx, fy, fz, sx, sy, sz = plane[6], plane[7], plane[8], plane[9], plane[10], plane[11]
        made[:] = False
        for option in range(n_options):
            n_copies = copies[option]
            # the most cells of this list: its patch's points (or the copied cells of them) and extra points
            if n_cells + patch * (1 + n_copies) > cells.shape[0]:
                return -1  # `cells` too short; `seen` is clear
            listed = n_cells
            copied = base[option] >= 0
            if copied:
                source = base[option] * n_patches + index
                for j in range(starts[source], starts[source] + lengths[source]):
                    seen[cells[j]] = 1
                    cells[n_cells] = cells[j]
                    n_cells += 1
            row = moved_row[option]
            moved_x, moved_y, moved_z = moved[row, 0], moved[row, 1], moved[row, 2]
            if not made[row]:
                made[row] = True
                strength = strengths[option]
                for i in range(patch):
                    p = start + i
                    offset = strength * ((points[p, 0] - mx) * nx + (points[p, 1] - my) * ny
                                         + (points[p, 2] - mz) * nz)
                    moved_x[i] = points[p, 0] - offset * nx
                    moved_y[i] = points[p, 1] - offset * ny
                    moved_z[i] = points[p, 2] - offset * nz
            if not copied:
                _cells_inside(moved_x, moved_y, moved_z, low, box, frame, voxel, grid_low, grid_shape, own)
            for j in range(n_copies):
                for i in range(patch):
                    u, v = disk_u[option, j, i], disk_v[option, j, i]
                    extra_x[i] = moved_x[i] + u * fx + v * sx
                    extra_y[i] = moved_y[i] + u * fy + v * sy
                    extra_z[i] = moved_z[i] + u * fz + v * sz
                _cells_inside(extra_x, extra_y, extra_z, low, box, frame, voxel, grid_low, grid_shape, extra[j])
            for i in range(patch):
                if not copied:
                    cell = own[i]
                    if cell >= 0 and seen[cell] == 0:
                        seen[cell] = 1
                        cells[n_cells] = cell
                        n_cells += 1
                for j in range(n_copies):
                    cell = extra[j, i]
                    if cell >= 0 and seen[cell] == 0:
                        seen[cell] = 1
                        cells[n_cells] = cell
                        n_cells += 1
            entry = option * n_patches + index
            starts[entry], lengths[entry] = listed, n_cells - listed
            for j in range(listed, n_cells):
                seen[cells[j]] = 0
    return n_cells


@compiled
def _gather_lists(made, starts, lengths, cells, offsets):
    """The lists made[starts[l]:starts[l] + lengths[l]] one after the other in `cells`, list l ending at
    offsets[l + 1]."""
    n = 0
    for entry in range(starts.shape[0]):
        for j in range(starts[entry], starts[entry] + lengths[entry]):
            cells[n] = made[j]
            n += 1
        offsets[entry + 1] = n


@compiled
def _cells_inside(x, y, z, low, box, frame, voxel, grid_low, grid_shape, out):
    """out[i]: the grid cell of the float32 point (x[i], y[i], z[i]), voxel floor((p + frame) / voxel) from
    grid_low, when it lies inside [low, box] (as `_store_inside`), else -1; both computed for every point, then one
    selected (no branch; the bounds held in locals, which the stores to `out` would otherwise make the loop read
    again)."""
    box_x, box_y, box_z = box[0], box[1], box[2]
    frame_x, frame_y, frame_z = frame[0], frame[1], frame[2]
    voxel_x, voxel_y, voxel_z = voxel[0], voxel[1], voxel[2]
    low_x, low_y, low_z = grid_low[0], grid_low[1], grid_low[2]
    shape_y, shape_z = grid_shape[1], grid_shape[2]
    for i in range(out.shape[0]):
        fx, fy, fz = np.float32(x[i]), np.float32(y[i]), np.float32(z[i])
        inside = (fx >= low) & (fy >= low) & (fz >= low) & (fx <= box_x) & (fy <= box_y) & (fz <= box_z)
        cx = np.int64(np.floor((np.float64(fx) + frame_x) / voxel_x)) - low_x
        cy = np.int64(np.floor((np.float64(fy) + frame_y) / voxel_y)) - low_y
        cz = np.int64(np.floor((np.float64(fz) + frame_z) / voxel_z)) - low_z
        out[i] = (cx * shape_y + cy) * shape_z + cz if inside else -1


@compiled
def _disk_sample(sample, radius_m, golden_angle, golden_fraction):
    """(u, v): the in-plane offsets of disk sample `sample` (a non-negative integer) on a disk of radius_m. The
    fraction of sample x golden_fraction is that number less its floor: its % 1.0, exactly (a subtraction instead
    of the C library's fmod)."""
    product = sample * golden_fraction
    radius = radius_m * np.sqrt(product - np.floor(product))
    angle = sample * golden_angle
    return radius * np.cos(angle), radius * np.sin(angle)


@compiled
def _patch_settings_kernel(points, patch, strength, copies, radius_m, golden_angle, golden_fraction, block, low, box,
                           frame, voxel, grid_low, grid_shape, grid, inside):
    """`patch_setting_voxels`'s kernel: the points of `_patch_planes_kernel` (one option at a time, samples
    numbered from the cloud's first point) marked in the grid, in an order of their own (the marks are ORed, the
    counts summed): patch by patch the cloud's and the moved points, then `block` disk samples at a time (a
    multiple of every setting's copies) each setting's extra points of the points whose samples they are. Each
    group of points is made in a loop of its own, its cells computed in another (`_cells_inside`: no branch, so
    the compiler vectorises it) and marked in a third."""
    n = points.shape[0]
    planes = _fit_planes(points, patch)
    moved_bits = 0
    most = 0
    for c in range(copies.shape[0]):
        moved_bits |= 1 << (2 + c)
        most = max(most, copies[c])
    n_plain = n_moved = 0
    moved_x, moved_y, moved_z = np.empty(patch), np.empty(patch), np.empty(patch)
    plain_cells, moved_cells = np.empty(patch, dtype=np.int64), np.empty(patch, dtype=np.int64)
    for index in range(n // patch):
        plane = planes[index]
        mx, my, mz, nx, ny, nz = plane[0], plane[1], plane[2], plane[3], plane[4], plane[5]
        start = index * patch
        own = points[start:start + patch]
        _cells_inside(own[:, 0], own[:, 1], own[:, 2], low, box, frame, voxel, grid_low, grid_shape, plain_cells)
        for r in range(patch):
            i = start + r
            offset = strength * ((points[i, 0] - mx) * nx + (points[i, 1] - my) * ny + (points[i, 2] - mz) * nz)
            moved_x[r], moved_y[r], moved_z[r] = (points[i, 0] - offset * nx, points[i, 1] - offset * ny,
                                                  points[i, 2] - offset * nz)
        _cells_inside(moved_x, moved_y, moved_z, low, box, frame, voxel, grid_low, grid_shape, moved_cells)
        for r in range(patch):
            if plain_cells[r] >= 0:
                grid[plain_cells[r]] |= 2
                n_plain += 1
            if moved_cells[r] >= 0:
                grid[moved_cells[r]] |= moved_bits
                n_moved += 1
    disk_u, disk_v = np.empty(block), np.empty(block)
    extra_x, extra_y, extra_z = np.empty(block), np.empty(block), np.empty(block)
    cells = np.empty(block, dtype=np.int64)
    for first in range(0, n * most, block):
        last = min(first + block, n * most)
        for sample in range(first, last):
            disk_u[sample - first], disk_v[sample - first] = _disk_sample(sample, radius_m, golden_angle,
                                                                          golden_fraction)
        for c in range(copies.shape[0]):
            k = copies[c]
            if k <= 0 or first >= n * k:
                continue
            begin, end = first // k, min(last // k, n)  # the points whose samples this block holds
            index = begin // patch
            plane = planes[index]
            mx, my, mz, nx, ny, nz = plane[0], plane[1], plane[2], plane[3], plane[4], plane[5]
            fx, fy, fz, sx, sy, sz = plane[6], plane[7], plane[8], plane[9], plane[10], plane[11]
            for i in range(begin, end):
                if i == (index + 1) * patch:
                    index += 1
                    plane = planes[index]
                    mx, my, mz, nx, ny, nz = plane[0], plane[1], plane[2], plane[3], plane[4], plane[5]
                    fx, fy, fz, sx, sy, sz = plane[6], plane[7], plane[8], plane[9], plane[10], plane[11]
                offset = strength * ((points[i, 0] - mx) * nx + (points[i, 1] - my) * ny + (points[i, 2] - mz) * nz)
                px, py, pz = points[i, 0] - offset * nx, points[i, 1] - offset * ny, points[i, 2] - offset * nz
                for j in range(k):
                    r = i * k + j - first
                    u, v = disk_u[r], disk_v[r]
                    extra_x[r], extra_y[r], extra_z[r] = (px + u * fx + v * sx, py + u * fy + v * sy,
                                                          pz + u * fz + v * sz)
            made = (end - begin) * k
            _cells_inside(extra_x[:made], extra_y[:made], extra_z[:made], low, box, frame, voxel, grid_low,
                          grid_shape, cells[:made])
            bit = 1 << (2 + c)
            for r in range(made):
                if cells[r] >= 0:
                    grid[cells[r]] |= bit
                    inside[1 + c] += 1
    inside[0] += n_plain
    for c in range(copies.shape[0]):
        inside[1 + c] += n_moved
