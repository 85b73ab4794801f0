"""The package's CPU thread count: compiled kernels run over contiguous ranges of their rows on that many threads,
and matrix products (numpy's BLAS, torch) run on one thread where their results must not depend on it."""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

_pools = threading.local()  # each calling thread's pool of kernel threads (`run_over_ranges`)
_threads = 0  # set_threads's count (0: the default, `default_threads`)
_kernel_threads = 0  # the caller's torch thread count while `one_torch_thread` holds torch at one (0: none held)
_pin_lock = threading.Lock()
_pin_depth = 0
_blas = None  # the loaded BLAS libraries, process-wide and per-thread (`_blas_libraries`, found on first use)
_blas_lock = threading.Lock()
_blas_depth = 0  # one_blas_thread blocks open in all threads of this process
_blas_saved: list = []  # (setter, count before) of the process-wide BLAS libraries while _blas_depth > 0
_shared = threading.Condition()  # guards _offers and every _Offer's counts; notified as tasks end or jobs finish
_offers: deque = deque()  # the `run_shared` calls with tasks left to take, oldest first


def default_threads() -> int:
    """OMP_NUM_THREADS when set to a positive integer, else the cores this process may run on."""
    try:
        configured = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        configured = 0
    return configured if configured > 0 else max(1, len(os.sched_getaffinity(0)))


def threads() -> int:
    """Threads of the compiled kernels (`run_over_ranges`)."""
    return _threads or default_threads()


def set_threads(count: int) -> None:
    """Run the compiled kernels, and torch if this process has imported it, on `count` threads."""
    global _threads
    _threads = max(1, int(count))
    torch = sys.modules.get("torch")
    if torch is not None and torch.get_num_threads() != _threads:
        torch.set_num_threads(_threads)


@contextlib.contextmanager
def kernel_threads(count: int) -> Iterator[None]:
    """The compiled kernels (and torch, if imported) run on `count` threads inside the block (`set_threads`); the
    caller's setting is restored on exit."""
    global _threads
    saved = _threads
    set_threads(count)
    try:
        yield
    finally:
        set_threads(saved or default_threads())
        _threads = saved


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """numpy's matrix products run on one BLAS thread inside the block, so their sums are added in one order
    whatever the thread count (OpenBLAS and MKL split and block a product differently for 1 and 2 threads). The
    compiled kernels of `run_over_ranges`, whose rows are independent, keep `threads()`.

    Blocks nest and overlap across threads: a BLAS library with one thread count for the whole process (OpenBLAS
    on pthreads, BLIS) is set to one thread when the first block of any thread opens and set back when the last
    one closes, by its own function (threadpoolctl lets one thread at a time change OpenBLAS's count and ignores the
    others' calls, so two decoding runs in two threads of a process would give one of them back its full count
    while it still decodes); a library with a count per thread (OpenMP, MKL) is limited in this thread for the
    block."""
    global _blas_depth, _blas_saved
    process_wide, per_thread = _blas_libraries()
    with _blas_lock:
        if _blas_depth == 0:
            _blas_saved = [(setter, getter()) for getter, setter in process_wide]
            for setter, _ in _blas_saved:
                setter(1)
        _blas_depth += 1
    saved = [(library, library.get_num_threads()) for library in per_thread]
    for library, _ in saved:
        library.set_num_threads(1)
    try:
        yield
    finally:
        for library, count in reversed(saved):
            library.set_num_threads(count)
        with _blas_lock:
            _blas_depth -= 1
            if _blas_depth == 0:
                for setter, count in _blas_saved:
                    setter(count)
                _blas_saved = []


def _blas_libraries() -> tuple[list[tuple[Callable[[], int], Callable[[int], object]]], list]:
    """(getter, setter) of each loaded BLAS library whose thread count is the process's, and threadpoolctl's
    controllers of those whose count is per thread (found once per process)."""
    global _blas
    if _blas is None:
        from threadpoolctl import ThreadpoolController

        process_wide, per_thread = [], []
        for library in ThreadpoolController().select(user_api="blas").lib_controllers:
            if getattr(library, "threading_layer", None) == "openmp" or library.internal_api == "mkl":
                per_thread.append(library)
            else:
                process_wide.append((library.get_num_threads, _process_wide_setter(library)))
        _blas = process_wide, per_thread
    return _blas


def _process_wide_setter(library) -> Callable[[int], object]:
    """OpenBLAS's own openblas_set_num_threads (under the symbol prefixes and suffixes of its builds, as
    threadpoolctl looks them up), which takes effect whichever thread calls it; another library's threadpoolctl
    setter."""
    if library.internal_api == "openblas":
        for prefix in ("", "scipy_"):
            for suffix in ("", "64_", "_64"):
                function = getattr(library.dynlib, f"{prefix}openblas_set_num_threads{suffix}", None)
                if function is not None:
                    return function
    return library.set_num_threads


@contextlib.contextmanager
def one_torch_thread() -> Iterator[None]:
    """torch's CPU operations run on one thread inside the block (as `one_blas_thread` for numpy), so encoding on
    torch gives the same bytes every time; the compiled kernels keep the caller's torch thread count. Nests; the
    caller's setting is restored on exit. Imports torch (the torch network's passes only)."""
    global _kernel_threads, _pin_depth
    import torch

    with _pin_lock:
        if _pin_depth == 0:
            _kernel_threads = torch.get_num_threads()
            if _kernel_threads > 1:
                torch.set_num_threads(1)
        _pin_depth += 1
    try:
        yield
    finally:
        with _pin_lock:
            _pin_depth -= 1
            if _pin_depth == 0:
                if _kernel_threads > 1:
                    torch.set_num_threads(_kernel_threads)
                _kernel_threads = 0


class _Offer:
    """The tasks of one `run_shared` call: the next one to take, how many are running, the first error."""

    def __init__(self, tasks: Sequence[Callable[[], object]]):
        self.tasks, self.taken, self.running, self.error = tasks, 0, 0, None


def run_shared(tasks: Sequence[Callable[[], object]]) -> None:
    """Run independent tasks (each writes outputs of its own, so the results do not depend on the thread that runs
    it) in this thread, in order, while threads waiting in `help_shared` may take the next ones; returns once all
    have run, raising the first error (the tasks not yet taken are then dropped). A decoding thread pool's idle
    threads help the tiles still being decoded (`codec.executor.ThreadExecutor`), so both cores work until the
    last tile is done."""
    if len(tasks) < 2:
        for task in tasks:
            task()
        return
    offer = _Offer(tasks)
    with _shared:
        _offers.append(offer)
        _shared.notify_all()
    while _run_next(offer):
        pass
    with _shared:
        while offer.running:
            _shared.wait()
    if offer.error is not None:
        raise offer.error


def help_shared(finished: Callable[[], bool]) -> None:
    """Run tasks that `run_shared` calls of other threads offer, oldest call first, until finished() holds while
    none is offered (checked again on every `wake_helpers`)."""
    while True:
        with _shared:
            while not _offers:
                if finished():
                    return
                _shared.wait()
            offer = _offers[0]
        _run_next(offer)


def wake_helpers() -> None:
    """Let the threads in `help_shared` check their `finished` again."""
    with _shared:
        _shared.notify_all()


def _run_next(offer: _Offer) -> bool:
    """Take the offer's next task and run it in this thread; False when none is left."""
    with _shared:
        if offer.taken >= len(offer.tasks):
            return False
        task = offer.tasks[offer.taken]
        offer.taken += 1
        offer.running += 1
        if offer.taken == len(offer.tasks):
            _offers.remove(offer)
    try:
        task()
    except BaseException as exc:  # noqa: BLE001 - handed to the caller of run_shared
        with _shared:
            if offer.error is None:
                offer.error = exc
            if offer.taken < len(offer.tasks):
                offer.taken = len(offer.tasks)
                _offers.remove(offer)
    finally:
        with _shared:
            offer.running -= 1
            _shared.notify_all()
    return True


def _reset_pool_after_fork() -> None:
    global _pools
    _pools = threading.local()  # a forked child has none of the parent's worker threads


os.register_at_fork(after_in_child=_reset_pool_after_fork)


def run_over_ranges(kernel: Callable[[int, int], object], n_rows: int, min_rows_per_thread: int = 256) -> None:
    """Calls kernel(first, stop) on contiguous ranges covering range(n_rows), at most one per thread (`threads()`,
    or the caller's torch thread count inside `one_torch_thread`) and each of at least min_rows_per_thread rows, in
    parallel (the calling thread takes the first range); returns when all are done. The kernel must write disjoint
    outputs per range, so results do not depend on the thread count. One pool of worker threads per calling thread
    serves its calls (starting threads per call cost ~1 ms each; the threads of a tile pool, `codec.executor`, each
    have their own share)."""
    n_ranges = max(1, min(_kernel_threads or threads(), n_rows // max(1, min_rows_per_thread)))
    bounds = np.linspace(0, n_rows, n_ranges + 1).astype(np.int64) if n_ranges > 1 else (0, n_rows)  # ~10 us less
    pool, size = getattr(_pools, "pool", None), getattr(_pools, "size", 0)
    if n_ranges - 1 > size:  # more threads than before: a larger pool replaces the old one
        if pool is not None:
            pool.shutdown(wait=False)
        pool = _pools.pool = ThreadPoolExecutor(n_ranges - 1, thread_name_prefix="mapsqueeze-kernel")
        _pools.size = n_ranges - 1
    others = [pool.submit(kernel, int(a), int(b)) for a, b in zip(bounds[1:-1], bounds[2:])] if n_ranges > 1 else []
    kernel(int(bounds[0]), int(bounds[1]))
    for future in others:
        future.result()
