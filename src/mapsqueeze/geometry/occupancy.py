"""The occupancy-grid IoU (as `metrics.iou`) of several decodes of one tile against its points at once: one dense
grid of the voxels marked by a compiled kernel (no sort, no float64 copies), for the encoder's choice of a decode
post-filter."""

from __future__ import annotations

import numpy as np

from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.jit import compiled
from mapsqueeze.geometry.patches import patch_option_cells, patch_options, patch_setting_voxels


_MAX_OCCUPANCY_VOXELS = 1 << 26
"""Largest voxel box `occupancy_ious` holds as a dense occupancy grid (64 MB; a 40 x 40 x 15 m tile spans 6M
voxels)."""


def occupancy_ious(original: np.ndarray, clouds: list[np.ndarray], frame_m: np.ndarray,
                   voxel_m: tuple[float, float, float]) -> list[float] | None:
    """`metrics.iou(original, cloud + frame_m, voxel_m)` of each of at most 7 float32 tile-local clouds (original:
    world metres; voxels floor(p / voxel_m), metres), on one dense occupancy grid (bit 0 the original, bit i + 1
    cloud i); None when their box holds more than _MAX_OCCUPANCY_VOXELS voxels."""
    frame_m = np.asarray(frame_m, dtype=np.float64)
    voxel = np.asarray(voxel_m, dtype=np.float64)
    corners = list(bounding_box(original))
    corners += [corner.astype(np.float64) + frame_m for cloud in clouds if len(cloud) for corner in bounding_box(cloud)]
    low = np.floor(np.min(corners, axis=0) / voxel).astype(np.int64)
    shape = np.floor(np.max(corners, axis=0) / voxel).astype(np.int64) - low + 1
    if np.prod(shape.astype(np.float64)) > _MAX_OCCUPANCY_VOXELS:
        return None
    grid = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    _mark_voxels(np.ascontiguousarray(original, dtype=np.float64), np.zeros(3), voxel, low, shape, 1, grid)
    for bit, cloud in enumerate(clouds, start=1):
        _mark_voxels(np.ascontiguousarray(cloud), frame_m, voxel, low, shape, 1 << bit, grid)
    return _grid_ious(grid, len(clouds))


def patch_setting_ious(original: np.ndarray, uncropped: np.ndarray, patch: int, strength: float, copies,
                       radius_m: float, upper: np.ndarray, frame_m: np.ndarray, voxel_m: tuple[float, float, float]
                       ) -> list[float] | None:
    """`occupancy_ious(original, clouds, frame_m, voxel_m)` of the clouds of a decoded (K, 3) float32 cloud
    `uncropped` (tile-local, relative to the world point frame_m): its points inside the box [0, upper] (metres,
    `tilepoints.keep_inside`), then `patches.patch_planes(uncropped, patch, strength, c, radius_m, upper)` for each
    c of `copies` (at most 6), marked on one dense grid as they are made (`patches.patch_setting_voxels`: no cloud
    is stored). None when the grid of the original and the box [0, upper] holds more than _MAX_OCCUPANCY_VOXELS
    voxels, or a cloud has no point inside the box (its crop then clamps every point into it)."""
    frame_m = np.asarray(frame_m, dtype=np.float64)
    voxel = np.asarray(voxel_m, dtype=np.float64)
    upper_m = np.asarray(upper).astype(np.float32).astype(np.float64)  # the float32 box of the points
    low, shape = _voxel_box(list(bounding_box(original)) + [frame_m, upper_m + frame_m], voxel)
    if np.prod(shape.astype(np.float64)) > _MAX_OCCUPANCY_VOXELS:
        return None
    grid = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    _mark_voxels(np.ascontiguousarray(original, dtype=np.float64), np.zeros(3), voxel, low, shape, 1, grid)
    inside = patch_setting_voxels(uncropped, patch, strength, copies, radius_m, upper, frame_m, voxel, low, shape,
                                  grid)
    if len(uncropped) and not inside.all():
        return None
    return _grid_ious(grid, len(inside))


def _grid_ious(grid: np.ndarray, n_clouds: int) -> list[float]:
    """The IoU of bit 0 (the original) with each bit 1 .. n_clouds of an occupancy grid."""
    counts = np.zeros(256, dtype=np.int64)
    _count_values(grid, counts)
    values = np.arange(256)
    shared = [counts[values & values >> bit & 1 == 1].sum() for bit in range(1, n_clouds + 1)]
    either = [counts[(values | values >> bit) & 1 == 1].sum() for bit in range(1, n_clouds + 1)]
    return [float(common / max(1, union)) for common, union in zip(shared, either)]


@compiled
def _count_values(grid, counts):
    for value in grid:
        counts[value] += 1


@compiled
def _mark_voxels(points, frame, voxel, low, shape, bit, grid):
    """Set `bit` in the grid cell of each point's IoU voxel floor((point + frame) / voxel) (as `voxel_indices`)."""
    for i in range(points.shape[0]):
        x = np.int64(np.floor((np.float64(points[i, 0]) + frame[0]) / voxel[0])) - low[0]
        y = np.int64(np.floor((np.float64(points[i, 1]) + frame[1]) / voxel[1])) - low[1]
        z = np.int64(np.floor((np.float64(points[i, 2]) + frame[2]) / voxel[2])) - low[2]
        grid[(x * shape[1] + y) * shape[2] + z] |= bit


def patch_option_ious(original: np.ndarray, uncropped: np.ndarray, patch: int, options, upper: np.ndarray,
                      start: np.ndarray, frame_m: np.ndarray, voxel_m: tuple[float, float, float], sweeps: int,
                      copy_weight: float = 0.0, bit_weight: float = 0.0, rate_sweeps: int = 0
                      ) -> tuple[np.ndarray, float, float] | None:
    """(choice per patch, IoU of `start`, IoU of the choices) of a greedy search for the option of each patch that
    maximises the occupancy-grid IoU (as `metrics.iou`) of the union of the patches' points with `original`, or,
    with weights, that IoU with two terms for the rate and D_e that the IoU does not see:

    - copy_weight: each extra point per point of an option (options[k][1]) counts as copy_weight more shared voxels,
      times the fraction of the option's distinct voxels of the patch that `original` occupies: extra points on the
      original's surfaces lower its points' distance to the decode (D_e) within voxels the IoU already counts;
    - bit_weight (IoU per bit), after the `sweeps` sweeps, `rate_sweeps` more that subtract bit_weight x the bits of
      the patch's option under the choices of the other patches (-log2 of its count + 1/2 over their number + 1/2
      per option, as the histogram coder will spend them).

    original: (N, 3) world metres; uncropped: a decoded cloud (tile-local, relative to the world point frame_m) of
    patches of `patch` points, each reworked under each of `options` and cropped to the box [0, upper] (metres) as
    `patches.patch_options` does; start: (n,) the first choice of each patch. Each sweep visits the patches in order
    and gives each the option (ties: its current one, then the lowest) that maximises the value with every other
    patch as chosen; each phase (the sweeps without, then those with the bits) stops after its count of sweeps or
    one that changes nothing. None when the voxel box of the
    original and the reworked points holds more than _MAX_OCCUPANCY_VOXELS voxels. The grid spans the original and
    the box [0, upper], unless that holds too many voxels; the reworked points are reduced to each patch's distinct
    voxels as they are made (`patches.patch_option_cells`), never stored."""
    frame_m = np.asarray(frame_m, dtype=np.float64)
    voxel = np.asarray(voxel_m, dtype=np.float64)
    upper_m = np.asarray(upper).astype(np.float32).astype(np.float64)  # the float32 box of the points
    low, shape = _voxel_box(list(bounding_box(original)) + [frame_m, upper_m + frame_m], voxel)
    if np.prod(shape.astype(np.float64)) > _MAX_OCCUPANCY_VOXELS:  # the reworked points' own box decides
        points = patch_options(uncropped, patch, options, upper)[0]
        corners = [corner.astype(np.float64) + frame_m for corner in bounding_box(points)] if len(points) else []
        low, shape = _voxel_box(list(bounding_box(original)) + corners, voxel)
        if np.prod(shape.astype(np.float64)) > _MAX_OCCUPANCY_VOXELS:
            return None
    grid = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    _mark_voxels(np.ascontiguousarray(original, dtype=np.float64), np.zeros(3), voxel, low, shape, 1, grid)
    n_original = int(np.count_nonzero(grid))
    cells, offsets = patch_option_cells(uncropped, patch, options, upper, frame_m, voxel, low, shape)
    listed = _compact_cells(grid, cells)  # the search's arrays span only the listed cells
    del grid
    choice = np.array(start, dtype=np.int64)
    bonus = copy_weight * np.array([option[1] for option in options], dtype=np.float64)
    before, after = _greedy_choices(listed, n_original, cells, offsets, len(options), len(choice), choice, sweeps,
                                    bonus, bit_weight, rate_sweeps)
    return choice, before, after


_BLOCK = 8
"""Grid cells per number kept by `_compact_cells`."""


def _compact_cells(grid: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Renumbers the grid cells in `cells` (in place) 0, 1, ... in grid order, without an index per grid cell: a
    cell's number is that of the first listed cell of its block of _BLOCK cells plus the listed cells before it in
    the block (bit 1 of the uint8 grid marks them, bits 2-4 hold that count); returns the grid value (bit 0) of
    each renumbered cell."""
    starts = np.empty(-(-len(grid) // _BLOCK), dtype=np.int32 if len(grid) < 2**31 else np.int64)
    listed = np.empty(_mark_listed(grid, cells, starts), dtype=np.uint8)
    _renumber_cells(grid, cells, starts, listed)
    return listed


@compiled
def _mark_listed(grid, cells, starts):
    """Sets bit 1 of the listed cells, and in bits 2-4 of each the listed cells before it in its block; starts[b]:
    the listed cells before block b; the count of listed cells."""
    for j in range(cells.shape[0]):
        grid[cells[j]] |= 2
    n = 0
    for block in range(starts.shape[0]):
        starts[block] = n
        for cell in range(block * _BLOCK, min((block + 1) * _BLOCK, grid.shape[0])):
            if grid[cell] & 2:
                grid[cell] |= (n - starts[block]) << 2
                n += 1
    return n


@compiled
def _renumber_cells(grid, cells, starts, listed):
    """cells[j] = its cell's number (`_compact_cells`); listed[number] = bit 0 of the cell."""
    for j in range(cells.shape[0]):
        cell = cells[j]
        number = starts[cell // _BLOCK] + (grid[cell] >> 2)
        cells[j] = number
        listed[number] = grid[cell] & 1


def _voxel_box(corners: list[np.ndarray], voxel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lowest voxel, shape in voxels) of the box of the IoU voxels of these world-metre corners."""
    low = np.floor(np.min(corners, axis=0) / voxel).astype(np.int64)
    return low, np.floor(np.max(corners, axis=0) / voxel).astype(np.int64) - low + 1


@compiled
def _greedy_choices(original, n_original, cells, offsets, n_options, n_patches, choice, sweeps, bonus, bit_weight,
                    rate_sweeps):
    """Greedy search of `patch_option_ious` on cell lists: patch i's distinct cells under option k are
    cells[offsets[k n + i]:offsets[k n + i + 1]], original[cell] whether the original occupies the cell (every
    listed cell, numbered from 0) and n_original the count of the original's cells, listed or not; bonus[k]:
    copy_weight x option k's extra points per point; `choice` updated in place; (IoU before, IoU after)."""
    occupied = np.zeros(original.shape[0], dtype=np.int32)  # chosen patches per cell
    for i in range(n_patches):
        k = choice[i] * n_patches + i
        for j in range(offsets[k], offsets[k + 1]):
            occupied[cells[j]] += 1
    shared = false = 0
    for cell in range(original.shape[0]):
        if occupied[cell] > 0:
            if original[cell]:
                shared += 1
            else:
                false += 1
    before = shared / max(1, n_original + false)
    counts = np.zeros(n_options, dtype=np.int64)  # patches per option
    for i in range(n_patches):
        counts[choice[i]] += 1
    for phase in range(2):
        rate = bit_weight if phase else 0.0
        for _ in range(rate_sweeps if phase else sweeps):
            changed, shared, false = _greedy_sweep(original, cells, offsets, n_options, n_patches, choice, bonus, rate,
                                                   counts, occupied, n_original, shared, false)
            if not changed:
                break
    return before, shared / max(1, n_original + false)


@compiled
def _greedy_sweep(original, cells, offsets, n_options, n_patches, choice, bonus, rate, counts, occupied, n_original,
                  shared, false):
    """One sweep of `_greedy_choices` (rate: IoU per bit of the choices, 0: none; a list's cells are distinct);
    (changed, shared, false)."""
    changed = False
    for i in range(n_patches):
        counts[choice[i]] -= 1
        k = choice[i] * n_patches + i
        for j in range(offsets[k], offsets[k + 1]):
            cell = cells[j]
            occupied[cell] -= 1
            if occupied[cell] == 0:
                if original[cell]:
                    shared -= 1
                else:
                    false -= 1
        best, best_value = choice[i], -np.inf
        for option in range(n_options):
            k = option * n_patches + i
            gained = empty = on_original = 0  # counted without a branch per cell (original[cell] is 0 or 1)
            if bonus[option] > 0.0:
                for j in range(offsets[k], offsets[k + 1]):
                    cell = cells[j]
                    free = np.int64(occupied[cell] == 0)
                    on_original += original[cell]
                    gained += free & original[cell]
                    empty += free
            else:
                for j in range(offsets[k], offsets[k + 1]):
                    cell = cells[j]
                    free = np.int64(occupied[cell] == 0)
                    gained += free & original[cell]
                    empty += free
            added = empty - gained
            credit = bonus[option] * on_original / max(1, offsets[k + 1] - offsets[k])
            value = (shared + gained + credit) / max(1, n_original + false + added)
            if rate > 0.0:
                value += rate * np.log2((counts[option] + 0.5) / (n_patches - 1 + 0.5 * n_options))
            if value > best_value or (value == best_value and option == choice[i]):
                best, best_value = option, value
        if best != choice[i]:
            changed = True
            choice[i] = best
        counts[best] += 1
        k = best * n_patches + i
        for j in range(offsets[k], offsets[k + 1]):
            cell = cells[j]
            if occupied[cell] == 0:
                if original[cell]:
                    shared += 1
                else:
                    false += 1
            occupied[cell] += 1
    return changed, shared, false
