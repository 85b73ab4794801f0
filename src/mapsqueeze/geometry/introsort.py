"""An argsort that orders equal keys exactly as torch's CPU sort does, without torch.

`torch.argsort` (not stable) on the CPU sorts (value, index) pairs with the C++ standard library's introsort
(libstdc++ `std::sort`): quicksort with the median of the second, middle and last elements moved to the front as
pivot, heapsort below a depth of 2 floor(log2 n), insertion sort of runs of at most 16 at the end. Equal keys come
out in whatever order those steps leave them. Grid subsampling sorts float32 keys in which nearby points often tie,
so its kept points (and the reference checkpoints' embeddings) depend on that order: `introsort_argsort` replays
the same steps on the same comparisons (`key[a] < key[b]`, no NaN in the keys), which gives the same permutation
(tests/test_inference.py compares it with torch on ties, runs, sawtooth and adversarial inputs).
"""

from __future__ import annotations

import numpy as np

from mapsqueeze.geometry.jit import compiled

RUN = 16
"""Ranges of at most RUN elements are left to the final insertion sort."""


def introsort_argsort(keys: np.ndarray) -> np.ndarray:
    """Indices (int64) that sort the 1-D keys ascending, ties in torch's CPU `argsort` order."""
    keys = np.ascontiguousarray(keys)
    if keys.ndim != 1:
        raise ValueError(f"introsort_argsort sorts 1-D keys, got shape {keys.shape}")
    if np.isnan(keys).any():
        raise ValueError("introsort_argsort: keys must not be NaN")
    return _introsort(keys.copy(), np.arange(len(keys), dtype=np.int64))


@compiled
def _introsort(keys, index):
    """Sorts keys in place, carrying index along (the pairs' order); returns index."""
    n = len(keys)
    if n < 2:
        return index
    depth = 0
    while (n >> (depth + 1)) > 0:
        depth += 1
    # The loop sorts the left part of each partition itself and defers the right part (libstdc++ recurses on it,
    # then continues with the left): a stack of (first, last, depth left) visited in the same order.
    stack = np.empty((2 * depth + 2, 3), dtype=np.int64)
    stack[0, 0], stack[0, 1], stack[0, 2] = 0, n, 2 * depth
    top = 1
    while top > 0:
        top -= 1
        first, last, limit = stack[top, 0], stack[top, 1], stack[top, 2]
        while last - first > RUN:
            if limit == 0:
                _heap_sort(keys, index, first, last)
                break
            limit -= 1
            cut = _partition(keys, index, first, last)
            stack[top, 0], stack[top, 1], stack[top, 2] = cut, last, limit
            top += 1
            last = cut
    _insertion_sort(keys, index, 0, min(n, RUN))
    for i in range(RUN, n):  # the smallest key of the array lies in the first RUN: no bound check below
        _insert_unguarded(keys, index, i)
    return index


@compiled
def _swap(keys, index, a, b):
    keys[a], keys[b] = keys[b], keys[a]
    index[a], index[b] = index[b], index[a]


@compiled
def _partition(keys, index, first, last):
    """Moves the median of keys[first + 1], keys[mid], keys[last - 1] to first, partitions (first, last) around it
    (scans stop on keys equal to the pivot) and returns the start of the right part."""
    a, b, c = first + 1, first + (last - first) // 2, last - 1
    if keys[a] < keys[b]:
        median = b if keys[b] < keys[c] else (c if keys[a] < keys[c] else a)
    else:
        median = a if keys[a] < keys[c] else (c if keys[b] < keys[c] else b)
    _swap(keys, index, first, median)
    pivot = keys[first]
    left, right = first + 1, last
    while True:
        while keys[left] < pivot:
            left += 1
        right -= 1
        while pivot < keys[right]:
            right -= 1
        if not left < right:
            return left
        _swap(keys, index, left, right)
        left += 1


@compiled
def _insert_unguarded(keys, index, position):
    """Moves the element at position left past every larger key (a smaller or equal key lies before it)."""
    key, value = keys[position], index[position]
    while key < keys[position - 1]:
        keys[position], index[position] = keys[position - 1], index[position - 1]
        position -= 1
    keys[position], index[position] = key, value


@compiled
def _insertion_sort(keys, index, first, last):
    for i in range(first + 1, last):
        if keys[i] < keys[first]:  # a new minimum goes to the front, the others shift right by one
            key, value = keys[i], index[i]
            for j in range(i, first, -1):
                keys[j], index[j] = keys[j - 1], index[j - 1]
            keys[first], index[first] = key, value
        else:
            _insert_unguarded(keys, index, i)


@compiled
def _sift(keys, index, first, hole, length, key, value):
    """Heap of `length` elements at first: fills the hole by moving the larger child up down to a leaf, then moves
    (key, value) up from there to its place."""
    top = hole
    child = hole
    while child < (length - 1) // 2:
        child = 2 * (child + 1)
        if keys[first + child] < keys[first + child - 1]:
            child -= 1
        keys[first + hole], index[first + hole] = keys[first + child], index[first + child]
        hole = child
    if length % 2 == 0 and child == (length - 2) // 2:
        child = 2 * (child + 1)
        keys[first + hole], index[first + hole] = keys[first + child - 1], index[first + child - 1]
        hole = child - 1
    parent = (hole - 1) // 2
    while hole > top and keys[first + parent] < key:
        keys[first + hole], index[first + hole] = keys[first + parent], index[first + parent]
        hole = parent
        parent = (hole - 1) // 2
    keys[first + hole], index[first + hole] = key, value


@compiled
def _heap_sort(keys, index, first, last):
    """Builds a max-heap over [first, last), then moves its top to the end one element at a time."""
    length = last - first
    for parent in range((length - 2) // 2, -1, -1):
        _sift(keys, index, first, parent, length, keys[first + parent], index[first + parent])
    while last - first > 1:
        last -= 1
        key, value = keys[last], index[last]
        keys[last], index[last] = keys[first], index[first]
        _sift(keys, index, first, 0, last - first, key, value)
