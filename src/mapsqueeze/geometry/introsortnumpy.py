"""`introsort.introsort_argsort` in numpy, without numba: the same permutation (torch's CPU tie order), for the
encoder's numpy path (`model.inference`, small maps: `codec.compress.NUMPY_KERNEL_POINTS`).

The introsort's partitions of disjoint ranges do not depend on one another, so every range of one depth of its
recursion is partitioned at once (a few dozen numpy operations per depth, not a Python loop per element). Hoare's
partition is computed from where its two scans stop: the left scan's stops are the range's keys >= pivot in
ascending position (L_0, L_1, ...), the right scan's those <= pivot in descending position (R_0, R_1, ...);
it swaps L_j with R_j while L_j < R_j (m swaps, a prefix: L rises and R falls), each scan seeing only keys it
has not swapped, and returns the left scan's last stop, min(L_m, R_{m-1}) (the first stop L_0 when m = 0; R_{m-1}
then holds the swapped key L_{m-1} held, which is >= pivot). A range still longer than RUN at the depth limit is
heap sorted as the kernel does (a Python loop; only adversarial keys reach it). The final insertion sort is a
stable sort of the keys as the partitions left them."""

from __future__ import annotations

import numpy as np

RUN = 16
"""Ranges of at most RUN elements are left to the final insertion sort (`introsort.RUN`)."""


def introsort_argsort(keys: np.ndarray) -> np.ndarray:
    """Indices (int64) that sort the 1-D keys ascending, ties in torch's CPU `argsort` order: the permutation of
    `introsort.introsort_argsort`."""
    keys = np.ascontiguousarray(keys)
    if keys.ndim != 1:
        raise ValueError(f"introsort_argsort sorts 1-D keys, got shape {keys.shape}")
    if np.isnan(keys).any():
        raise ValueError("introsort_argsort: keys must not be NaN")
    n = len(keys)
    keys, index = keys.copy(), np.arange(n, dtype=np.int64)
    if n < 2:
        return index
    first = np.zeros(1, dtype=np.int64)
    last = np.full(1, n, dtype=np.int64)
    limit = 2 * (n.bit_length() - 1)  # 2 floor(log2 n): the same for every range of one depth
    while len(first):
        long = last - first > RUN
        first, last = first[long], last[long]
        if not len(first):
            break
        if limit == 0:
            for start, stop in zip(first.tolist(), last.tolist()):
                _heap_sort(keys, index, start, stop)
            break
        limit -= 1
        cut = _partition(keys, index, first, last)
        first, last = np.concatenate([first, cut]), np.concatenate([cut, last])
    return index[np.argsort(keys, kind="stable")]


def _partition(keys: np.ndarray, index: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """`introsort._partition` of each of the disjoint ranges [first, last) (all longer than RUN), in place; the
    start of each one's right part."""
    n_ranges = len(first)
    a, b, c = first + 1, first + (last - first) // 2, last - 1
    ka, kb, kc = keys[a], keys[b], keys[c]
    median = np.where(ka < kb, np.where(kb < kc, b, np.where(ka < kc, c, a)),
                      np.where(ka < kc, a, np.where(kb < kc, c, b)))
    _swap(keys, index, first, median)
    pivot = keys[first]
    # every range's positions first + 1 .. last - 1, range after range
    sizes = last - first - 1
    owner = np.repeat(np.arange(n_ranges), sizes)
    position = np.arange(len(owner), dtype=np.int64) + np.repeat(first + 1 - (np.cumsum(sizes) - sizes), sizes)
    values, pivots = keys[position], pivot[owner]
    left_stops, right_stops = values >= pivots, values <= pivots
    left, left_owner = position[left_stops], owner[left_stops]
    right, right_owner = position[right_stops], owner[right_stops]
    n_left = np.bincount(left_owner, minlength=n_ranges)
    n_right = np.bincount(right_owner, minlength=n_ranges)
    left_start, right_start = np.cumsum(n_left) - n_left, np.cumsum(n_right) - n_right
    rank = np.arange(len(left)) - left_start[left_owner]  # j of L_j
    paired = rank < n_right[left_owner]
    partner = np.full(len(left), -1, dtype=np.int64)  # R_j
    partner[paired] = right[(right_start + n_right - 1)[left_owner[paired]] - rank[paired]]
    swapped = partner > left
    _swap(keys, index, left[swapped], partner[swapped])
    m = np.bincount(left_owner[swapped], minlength=n_ranges)
    next_left = np.where(m < n_left, left[np.minimum(left_start + m, len(left) - 1)], np.iinfo(np.int64).max)
    last_right = right[np.maximum(right_start + n_right - m, 0) % max(1, len(right))]
    return np.where(m > 0, np.minimum(next_left, last_right), next_left)


def _swap(keys: np.ndarray, index: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """Swap the elements at positions a and b (disjoint sets of positions)."""
    keys[a], keys[b] = keys[b], keys[a].copy()
    index[a], index[b] = index[b], index[a].copy()


def _heap_sort(keys: np.ndarray, index: np.ndarray, first: int, last: int) -> None:
    """`introsort._heap_sort` of [first, last) in Python (the same moves)."""
    key_list, index_list = keys[first:last].tolist(), index[first:last].tolist()
    length = last - first
    for parent in range((length - 2) // 2, -1, -1):
        _sift(key_list, index_list, parent, length, key_list[parent], index_list[parent])
    end = length
    while end > 1:
        end -= 1
        key, value = key_list[end], index_list[end]
        key_list[end], index_list[end] = key_list[0], index_list[0]
        _sift(key_list, index_list, 0, end, key, value)
    keys[first:last], index[first:last] = key_list, index_list


def _sift(keys: list, index: list, hole: int, length: int, key, value) -> None:
    """`introsort._sift` on a heap at the lists' start."""
    top = child = hole
    while child < (length - 1) // 2:
        child = 2 * (child + 1)
        if keys[child] < keys[child - 1]:
            child -= 1
        keys[hole], index[hole] = keys[child], index[child]
        hole = child
    if length % 2 == 0 and child == (length - 2) // 2:
        child = 2 * (child + 1)
        keys[hole], index[hole] = keys[child - 1], index[child - 1]
        hole = child - 1
    parent = (hole - 1) // 2
    while hole > top and keys[parent] < key:
        keys[hole], index[hole] = keys[parent], index[parent]
        hole = parent
        parent = (hole - 1) // 2
    keys[hole], index[hole] = key, value
