"""Run a GIL-releasing compiled kernel over contiguous ranges of its rows on torch.get_num_threads() threads."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

_pool: ThreadPoolExecutor | None = None
_pool_workers = 0


def _reset_pool_after_fork() -> None:
    global _pool, _pool_workers
    _pool, _pool_workers = None, 0  # a forked child has none of the parent's worker threads


os.register_at_fork(after_in_child=_reset_pool_after_fork)


def run_over_ranges(kernel: Callable[[int, int], object], n_rows: int, min_rows_per_thread: int = 256) -> None:
    """Calls kernel(first, stop) on contiguous ranges covering range(n_rows), at most one per torch thread and
    each of at least min_rows_per_thread rows, in parallel (the calling thread takes the first range); returns when
    all are done. The kernel must write disjoint outputs per range, so results do not depend on the thread count.
    One pool of worker threads serves every call (starting threads per call cost ~1 ms each)."""
    global _pool, _pool_workers
    n_ranges = max(1, min(torch.get_num_threads(), n_rows // max(1, min_rows_per_thread)))
    bounds = np.linspace(0, n_rows, n_ranges + 1).astype(np.int64)
    if n_ranges - 1 > _pool_workers:  # more torch threads than before: a larger pool replaces the old one
        if _pool is not None:
            _pool.shutdown(wait=False)
        _pool, _pool_workers = ThreadPoolExecutor(n_ranges - 1, thread_name_prefix="mapsqueeze-kernel"), n_ranges - 1
    others = [_pool.submit(kernel, int(a), int(b)) for a, b in zip(bounds[1:-1], bounds[2:])] if n_ranges > 1 else []
    kernel(int(bounds[0]), int(bounds[1]))
    for future in others:
        future.result()
