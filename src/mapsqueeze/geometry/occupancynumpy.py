"""`occupancy.occupancy_ious`, `patch_setting_ious` and `patch_option_ious` in numpy, without numba: the same
IoUs and patch choices, for the encoder's numpy path on small maps (`codec.compress.NUMPY_KERNEL_POINTS`). The
reworked patch points are `patchesnumpy`'s (the bytes of `patches`' kernel); the greedy search visits the patches
in Python, each patch's options at once in numpy, with the kernel's integer counts and floating-point operations
(math.log2: the C library's, as numba's; numpy's rounds differently)."""

from __future__ import annotations

import math
from functools import partial

import numpy as np

from mapsqueeze.geometry.bounds import bounding_box
from mapsqueeze.geometry.patchesnumpy import checked_points, fit_planes, reworked_axes, reworked_points

MAX_OCCUPANCY_VOXELS = 1 << 26
"""`occupancy._MAX_OCCUPANCY_VOXELS`."""


def occupancy_ious(original: np.ndarray, clouds: list[np.ndarray], frame_m: np.ndarray,
                   voxel_m: tuple[float, float, float]) -> list[float] | None:
    """`occupancy.occupancy_ious` (the same arguments and values)."""
    frame_m = np.asarray(frame_m, dtype=np.float64)
    voxel = np.asarray(voxel_m, dtype=np.float64)
    corners = list(bounding_box(original))
    corners += [corner.astype(np.float64) + frame_m for cloud in clouds if len(cloud) for corner in bounding_box(cloud)]
    low, shape = _voxel_box(corners, voxel)
    if np.prod(shape.astype(np.float64)) > MAX_OCCUPANCY_VOXELS:
        return None
    grid = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    _mark_voxels(original, np.zeros(3), voxel, low, shape, 1, grid)
    for bit, cloud in enumerate(clouds, start=1):
        _mark_voxels(cloud, frame_m, voxel, low, shape, 1 << bit, grid)
    return _grid_ious(grid, len(clouds))


def patch_setting_ious(original: np.ndarray, uncropped: np.ndarray, patch: int, strength: float, copies,
                       radius_m: float, upper: np.ndarray, frame_m: np.ndarray, voxel_m: tuple[float, float, float]
                       ) -> list[float] | None:
    """`occupancy.patch_setting_ious` (the same arguments and values): the settings' points made whole from one
    plane fit (`patchesnumpy`) and marked."""
    frame_m = np.asarray(frame_m, dtype=np.float64)
    voxel = np.asarray(voxel_m, dtype=np.float64)
    upper_m = np.asarray(upper).astype(np.float32).astype(np.float64)
    low, shape = _voxel_box(list(bounding_box(original)) + [frame_m, upper_m + frame_m], voxel)
    if np.prod(shape.astype(np.float64)) > MAX_OCCUPANCY_VOXELS:
        return None
    grid = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    _mark_voxels(original, np.zeros(3), voxel, low, shape, 1, grid)
    points, box_low, box = checked_points(np.asarray(uncropped), patch, upper, float32_kept=True)
    mark = partial(_mark_inside, box_low=box_low, box=box, frame=frame_m, voxel=voxel, low=low, shape=shape,
                   grid=grid)
    inside = [mark([points[:, a].astype(np.float32) for a in range(3)], 2)]
    planes = fit_planes(points, patch)
    n_moved = 0
    for c, count in enumerate(copies):
        moved, extra = [], []
        for coordinates, spread in reworked_axes(planes, 0, float(strength), int(count), float(radius_m)):
            if not c:
                moved.append(coordinates.astype(np.float32).ravel())
            if count:
                extra.append(spread.astype(np.float32).ravel())
        if not c:  # the settings' moved points are the same (one strength): marked once with all their bits
            n_moved = mark(moved, sum(1 << (2 + b) for b in range(len(copies))))
        inside.append(n_moved + (mark(extra, 1 << (2 + c)) if count else 0))
    if len(uncropped) and not all(inside):
        return None
    return _grid_ious(grid, len(inside))


def patch_option_ious(original: np.ndarray, uncropped: np.ndarray, patch: int, options, upper: np.ndarray,
                      start: np.ndarray, frame_m: np.ndarray, voxel_m: tuple[float, float, float], sweeps: int,
                      copy_weight: float = 0.0, bit_weight: float = 0.0, rate_sweeps: int = 0
                      ) -> tuple[np.ndarray, float, float] | None:
    """`occupancy.patch_option_ious` (the same arguments and results): the patches' planes fitted once
    (`patchesnumpy`), each option's reworked points made whole (disk samples numbered from each patch's first
    point) and reduced to each patch's distinct cells (an option with extra points: the cells of its moved points,
    those of the option with its strength and none, and of its extra points), then the greedy search
    (`_greedy_choices`)."""
    frame_m = np.asarray(frame_m, dtype=np.float64)
    voxel = np.asarray(voxel_m, dtype=np.float64)
    points, box_low, box = checked_points(np.asarray(uncropped), patch, upper, float32_kept=True)
    n_patches = len(points) // patch
    planes = fit_planes(points, patch)
    upper_m = np.asarray(upper).astype(np.float32).astype(np.float64)
    low, shape = _voxel_box(list(bounding_box(original)) + [frame_m, upper_m + frame_m], voxel)
    if np.prod(shape.astype(np.float64)) > MAX_OCCUPANCY_VOXELS:  # the reworked points' own box decides
        kept = np.concatenate([out[inside] for out, inside in (
            reworked_points(planes, 0, float(strength), int(copies), float(radius_m), box_low, box, per_patch=True)
            for strength, copies, radius_m in options)])
        corners = [corner.astype(np.float64) + frame_m for corner in bounding_box(kept)] if len(kept) else []
        low, shape = _voxel_box(list(bounding_box(original)) + corners, voxel)
        if np.prod(shape.astype(np.float64)) > MAX_OCCUPANCY_VOXELS:
            return None
    grid = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    _mark_voxels(original, np.zeros(3), voxel, low, shape, 1, grid)
    n_original = int(np.count_nonzero(grid))
    lists, counts = [], []  # per option: the patches' distinct cells, patch after patch, and their counts
    moved: dict = {}  # strength -> the voxels of its moved points and whether they are inside the box
    for strength, copies, radius_m in options:
        cells, per_patch = _option_cells(planes, float(strength), int(copies), float(radius_m), box_low, box,
                                         frame_m, voxel, low, shape, moved)
        lists.append(cells)
        counts.append(per_patch)
    cells = np.concatenate(lists) if lists else np.zeros(0, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(np.concatenate(counts) if counts else [])]).astype(np.int64)
    listed_cells = _distinct(cells)  # the listed cells renumbered in grid order
    choice = np.array(start, dtype=np.int64)
    bonus = [copy_weight * option[1] for option in options]
    before, after = _greedy_choices((grid[listed_cells] & 1).astype(bool), n_original,
                                    np.searchsorted(listed_cells, cells), offsets, len(options), n_patches, choice,
                                    sweeps, bonus, bit_weight, rate_sweeps)
    return choice, before, after


CHUNK_ROWS = 1 << 15
"""Reworked points made and reduced to their cells at once by `_option_cells` (their temporaries stay in the CPU's
cache)."""


def _option_cells(planes: tuple, strength: float, copies: int, radius_m: float, box_low: np.float32,
                  box: np.ndarray, frame: np.ndarray, voxel: np.ndarray, low: np.ndarray, shape: np.ndarray,
                  moved: dict) -> tuple[np.ndarray, np.ndarray]:
    """(the distinct grid cells of each patch, ascending, patch after patch; their count per patch) of the
    points of the patches (`fit_planes`) under one option (`reworked_points`, disk samples numbered from each
    patch's first point) that lie inside the box. Made patch range by patch range; each patch's cells are numbered
    within the box of its voxels and marked on one bitmap of all the patches' boxes (no sort), or sorted where
    those boxes are too large for it. `moved`: strength -> the voxels of the moved points of an option with no
    extra points and whether they lie inside the box (((patches, patch) per axis), (patches, patch)), kept here
    for the options with that strength and extra points, whose moved points are the same."""
    n_patches, patch = planes[0].shape
    known = moved.get(strength) if copies else None
    step = max(1, CHUNK_ROWS // (patch * (1 + copies)))
    local, corner, dims, made = [], [], [], []  # per chunk: each kept point's number in its patch's box; the boxes
    for first in range(0, n_patches, step):
        part = tuple(_patch_rows(value, first, first + step) for value in planes)
        count = len(part[0])
        own = patch * copies if known is not None else patch * (1 + copies)  # the points made here, per patch:
        values = [np.empty((count, own), dtype=np.float32) for _ in range(3)]  # its moved, then its extra points
        for a, (coordinates, extra) in enumerate(reworked_axes(part, 0, strength, copies, radius_m,
                                                               per_patch=True)):
            if known is None:
                values[a][:, :patch] = coordinates
            if copies:
                values[a][:, own - patch * copies:] = extra.reshape(count, -1)
        axes, inside = _voxels(values, box_low, box, frame, voxel, low)
        if known is not None:
            axes = [np.concatenate([known[0][a][first:first + count], axes[a]], axis=1) for a in range(3)]
            inside = np.concatenate([known[1][first:first + count], inside], axis=1)
        elif not copies:
            made.append((axes, inside))
        lowest = np.stack([values.min(axis=1) for values in axes], axis=1)
        sizes = np.stack([values.max(axis=1) for values in axes], axis=1) - lowest + 1
        number = axes[0] - lowest[:, 0, None]
        for a in (1, 2):
            number *= sizes[:, a, None]
            number += axes[a]
            number -= lowest[:, a, None]
        local.append((number, inside))
        corner.append(lowest)
        dims.append(sizes)
    if not n_patches:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if made and strength not in moved:
        moved[strength] = ([np.concatenate([axes[a] for axes, _ in made]) for a in range(3)],
                           np.concatenate([inside for _, inside in made]))
    corner, dims = np.concatenate(corner), np.concatenate(dims)
    volume = np.prod(dims, axis=1)
    start = np.cumsum(volume) - volume  # each patch's box on the bitmap
    n_kept = sum(int(np.count_nonzero(inside)) for _, inside in local)
    patch_first = 0
    keys = []
    for number, inside in local:
        rows = len(number)
        number += start[patch_first:patch_first + rows, None]
        keys.append(number[inside])
        patch_first += rows
    keys = np.concatenate(keys)
    if int(volume.sum()) <= 8 * n_kept + (1 << 20):
        marked = np.zeros(int(volume.sum()), dtype=bool)
        marked[keys] = True
        keys = np.flatnonzero(marked)
    else:
        keys = _distinct(keys)
    owner = np.searchsorted(start, keys, side="right") - 1
    within = keys - start[owner]
    size = dims[owner]
    z = within % size[:, 2] + corner[owner, 2]
    within //= size[:, 2]
    y = within % size[:, 1] + corner[owner, 1]
    x = within // size[:, 1] + corner[owner, 0]
    return (x * shape[1] + y) * shape[2] + z, np.bincount(owner, minlength=n_patches)


def _patch_rows(value, first: int, stop: int):
    """Patches first .. stop - 1 of one of `fit_planes`'s arrays (or of a tuple of them)."""
    return tuple(item[first:stop] for item in value) if isinstance(value, tuple) else value[first:stop]


def _distinct(values: np.ndarray) -> np.ndarray:
    """The distinct values, ascending (a sort: faster than np.unique's hash here)."""
    values = np.sort(values)
    if len(values) < 2:
        return values
    keep = np.empty(len(values), dtype=bool)
    keep[0] = True
    np.not_equal(values[1:], values[:-1], out=keep[1:])
    return values[keep]


def _voxels(values: list[np.ndarray], box_low: np.float32, box: np.ndarray, frame: np.ndarray, voxel: np.ndarray,
            low: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """(per axis the voxel index from `low` of floor((float64(p) + frame) / voxel), which points lie inside the box
    [box_low, box]) of points given as their float32 x, y and z arrays (`occupancy._mark_voxels`,
    `patches._cells_inside`)."""
    inside = np.ones(values[0].shape, dtype=bool)
    axes = []
    for a, coordinate in enumerate(values):
        inside &= coordinate >= box_low
        inside &= coordinate <= box[a]
        wide = np.add(coordinate, frame[a], dtype=np.float64)  # the float32 value widened exactly, then added
        wide /= voxel[a]
        np.floor(wide, out=wide)
        index = wide.astype(np.int64)
        index -= low[a]
        axes.append(index)
    return axes, inside


def _mark_inside(values: list[np.ndarray], bits: int, box_low: np.float32, box: np.ndarray, frame: np.ndarray,
                 voxel: np.ndarray, low: np.ndarray, shape: np.ndarray, grid: np.ndarray) -> int:
    """Set `bits` in the grid cell of each point (given as its float32 x, y and z arrays) inside the box
    (`patches._patch_settings_kernel`); the count of those points."""
    voxels, inside = _voxels(values, box_low, box, frame, voxel, low)
    cells = ((voxels[0] * shape[1] + voxels[1]) * shape[2] + voxels[2])[inside]
    grid[cells] |= np.uint8(bits)
    return len(cells)


def _voxel_box(corners: list[np.ndarray], voxel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lowest voxel, shape in voxels) of the box of the IoU voxels of these world-metre corners."""
    low = np.floor(np.min(corners, axis=0) / voxel).astype(np.int64)
    return low, np.floor(np.max(corners, axis=0) / voxel).astype(np.int64) - low + 1


def _cells(points: np.ndarray, frame: np.ndarray, voxel: np.ndarray, low: np.ndarray, shape: np.ndarray
           ) -> np.ndarray:
    """The flat grid cell of each point's IoU voxel floor((float64(point) + frame) / voxel) (`occupancy._mark_voxels`,
    `patches._cells_inside`)."""
    index = np.floor((points.astype(np.float64) + frame) / voxel).astype(np.int64) - low
    return (index[:, 0] * shape[1] + index[:, 1]) * shape[2] + index[:, 2]


def _mark_voxels(points: np.ndarray, frame: np.ndarray, voxel: np.ndarray, low: np.ndarray, shape: np.ndarray,
                 bit: int, grid: np.ndarray) -> None:
    """`occupancy._mark_voxels`: set `bit` in the cell of each point."""
    cells = _cells(np.asarray(points), frame, voxel, low, shape)
    grid[cells] |= np.uint8(bit)


def _grid_ious(grid: np.ndarray, n_clouds: int) -> list[float]:
    """`occupancy._grid_ious`: the IoU of bit 0 with each bit 1 .. n_clouds."""
    counts = np.bincount(grid, minlength=256)
    values = np.arange(256)
    shared = [counts[values & values >> bit & 1 == 1].sum() for bit in range(1, n_clouds + 1)]
    either = [counts[(values | values >> bit) & 1 == 1].sum() for bit in range(1, n_clouds + 1)]
    return [float(common / max(1, union)) for common, union in zip(shared, either)]


def _greedy_choices(original: np.ndarray, n_original: int, cells: np.ndarray, offsets: np.ndarray, n_options: int,
                    n_patches: int, choice: np.ndarray, sweeps: int, bonus: list[float], bit_weight: float,
                    rate_sweeps: int) -> tuple[float, float]:
    """`occupancy._greedy_choices` (the same arguments, with bonus a list; `choice` updated in place; the same
    (IoU before, IoU after)). A patch's options are valued at once, each value with the kernel's operations (the
    counts are whole numbers, exact in float64); the best is the patch's current option where it reaches the
    largest value, else the first that does (the kernel's order of comparisons)."""
    occupied = np.zeros(len(original), dtype=np.int32)  # chosen patches per cell
    lists = [[cells[offsets[k * n_patches + i]:offsets[k * n_patches + i + 1]] for k in range(n_options)]
             for i in range(n_patches)]
    together = [np.concatenate(patch_lists) for patch_lists in lists]  # a patch's lists, option after option
    option_of = [np.repeat(np.arange(n_options), [len(cells) for cells in patch_lists]) for patch_lists in lists]
    on_original = [original[listed] for listed in together]
    weights = np.array(bonus, dtype=np.float64)
    credit = [weights * np.bincount(options, weights=listed & (weights > 0.0)[options], minlength=n_options)
              / np.array([max(1, len(cells)) for cells in patch_lists], dtype=np.float64)
              for options, listed, patch_lists in zip(option_of, on_original, lists)]
    # the bits' term of an option chosen by `count` other patches: -log2 of its share, as the kernel (the C library's)
    log_share = np.array([math.log2((count + 0.5) / (n_patches - 1 + 0.5 * n_options))
                          for count in range(n_patches + 1)])
    for i in range(n_patches):
        np.add.at(occupied, lists[i][choice[i]], 1)
    held = occupied > 0
    shared = int(np.count_nonzero(held & original))
    false = int(np.count_nonzero(held)) - shared
    before = shared / max(1, n_original + false)
    counts = np.bincount(choice, minlength=n_options)  # patches per option
    for phase in range(2):
        rate = bit_weight if phase else 0.0
        for _ in range(rate_sweeps if phase else sweeps):
            changed = False
            for i in range(n_patches):
                current = int(choice[i])
                counts[current] -= 1
                listed = lists[i][current]
                occupied[listed] -= 1
                emptied = original[listed[occupied[listed] == 0]]
                shared -= int(np.count_nonzero(emptied))
                false -= len(emptied) - int(np.count_nonzero(emptied))
                free = occupied[together[i]] == 0
                gained = np.bincount(option_of[i], weights=free & on_original[i], minlength=n_options)
                added = np.bincount(option_of[i], weights=free, minlength=n_options) - gained
                values = (shared + gained + credit[i]) / np.maximum(1.0, n_original + false + added)
                if rate > 0.0:
                    values += rate * log_share[counts]
                best = current if values[current] == values.max() else int(np.argmax(values))
                if best != current:
                    changed = True
                    choice[i] = best
                counts[best] += 1
                listed = lists[i][best]
                filled = original[listed[occupied[listed] == 0]]
                shared += int(np.count_nonzero(filled))
                false += len(filled) - int(np.count_nonzero(filled))
                occupied[listed] += 1
            if not changed:
                break
    return before, shared / max(1, n_original + false)
