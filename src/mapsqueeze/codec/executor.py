"""Where per-tile jobs run: in this process, in a pool of its threads, or on a Dask cluster, behind one interface.

Every executor maps a module-level `function(context, item)` over items and yields the results in input order,
with at most a few items per worker submitted ahead of the one being yielded (memory: one tile per worker plus the
results waiting for their turn). `context` (e.g. the model) is shared by the threads, sent once to each Dask
worker. Each worker runs its compiled kernels on its share of the cores; results do not depend on where a job ran,
so every executor gives the same bytes.
"""

from __future__ import annotations

import os
import socket
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.geometry.threads import help_shared, kernel_threads, one_blas_thread, set_threads, wake_helpers

TileFunction = Callable[[Any, Any], Any]

ProgressCallback = Callable[[int, int], None]
"""Called with (tiles done, tiles in total) after each tile."""

IN_FLIGHT_PER_WORKER = 2
"""Jobs submitted per worker ahead of the oldest unfinished one (keeps workers busy while results are collected)."""

WORKER_MMAP_THRESHOLD_BYTES = 32 << 20
"""A process running tile jobs allocates blocks up to this size from malloc's heap instead of mapping each one afresh
(glibc's largest; `_keep_freed_memory`)."""

WORKER_TRIM_THRESHOLD_BYTES = 64 << 20
"""Freed heap a process running tile jobs keeps for the next tile instead of returning it to the system (a tile's
arrays)."""

DASK_RETRIES = 3
"""A Dask job whose worker dies is run again on another worker this many times before the whole run fails."""

SCHEDULER_PROBE_S = 5.0
"""Seconds a TCP connection to a Dask scheduler's host and port may take to open (`_probe_scheduler`): a refused
connection or an unknown host fails at once, a host that does not answer after this; the kernel of a reachable
scheduler accepts within a round trip (and two lost SYNs, resent after 1 and 3 s), however busy the scheduler."""

SCHEDULER_TIMEOUT_S = 30
"""Seconds a Dask connection to the scheduler then has for its handshake, which a busy scheduler may answer late
(`_check_handshake`), and the Dask client for its own."""

_PROBED_SCHEMES = ("tcp", "tls", "ws", "wss")
"""Address schemes over TCP (host:port) that `_probe_scheduler` checks; others (e.g. inproc, ucx) go to the client."""


def default_workers() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def check_workers(workers: int) -> int:
    """MapsqueezeError unless workers is an integer >= 1."""
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise MapsqueezeError(f"workers must be an integer of at least 1, got {workers!r}")
    return workers


class SerialExecutor:
    """Runs each job in this process, one after the other; this process keeps freed memory for the next tile from
    then on (`_keep_freed_memory`), as with a pool of threads, and returns it when the jobs are done."""

    workers = 1

    def __init__(self):
        _keep_freed_memory()

    def map(self, function: TileFunction, context: Any, items: Iterable) -> Iterator:
        return (function(context, item) for item in items)

    def close(self, abort: bool = False) -> None:
        _return_freed_memory()


class ThreadExecutor:
    """A pool of `workers` threads of this process. The tile jobs spend their time in numpy's array operations and
    matrix products, the compiled kernels (`geometry.jit.compiled`: nogil) and the k-d tree searches, which all
    release the GIL, so the threads run in parallel with no process to start, no module imported again, the context
    shared instead of copied and the results handed over without pickling. While the pool is open: numpy's matrix
    products stay on one BLAS thread (`one_blas_thread`, held from the opening to the closing of the pool, however
    many other pools of the process open and close meanwhile), so each job's bytes are the serial run's; the
    compiled kernels (`kernel_threads`) and each pool thread's OpenMP k-d tree searches (`_pool_thread_start`) run on
    the workers' share of the cores. This process keeps freed memory for the next tile from then on
    (`_keep_freed_memory`) and returns it when the pool closes. Once every job is handed to the pool, a thread that
    finds no job left helps the running ones with the independent parts they offer (`geometry.threads.run_shared`:
    the decoder's groups of embedding points, the patch planes' blocks), so the last tiles do not run on one core
    while the others idle."""

    def __init__(self, workers: int):
        from concurrent.futures import ThreadPoolExecutor

        self.workers = workers
        _keep_freed_memory()
        share = _threads_per_worker(workers)
        self._blas, self._kernels = one_blas_thread(), kernel_threads(share)
        self._blas.__enter__()
        self._kernels.__enter__()
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="mapsqueeze-tile", initializer=_pool_thread_start,
                                        initargs=(share,))

    def map(self, function: TileFunction, context: Any, items: Iterable) -> Iterator:
        lock, unfinished = threading.Lock(), [0]  # jobs submitted and not done (run, failed or cancelled)

        def done(_future) -> None:
            with lock:
                unfinished[0] -= 1
            wake_helpers()

        def submit(item: Any) -> Any:
            with lock:
                unfinished[0] += 1
            future = self._pool.submit(function, context, item)
            future.add_done_callback(done)
            return future

        def then_help(items: Iterable) -> Iterator:
            yield from items
            for _ in range(self.workers - 1):  # queued after the last job: they start as threads run out of jobs
                self._pool.submit(_help, lambda: unfinished[0] == 0)

        return _ordered(submit, then_help(items), IN_FLIGHT_PER_WORKER * self.workers, lambda future: future.result())

    def close(self, abort: bool = False) -> None:
        """Wait for the running jobs (a thread cannot be stopped) after dropping the queued ones."""
        try:
            self._pool.shutdown(wait=True, cancel_futures=True)
        finally:
            self._kernels.__exit__(None, None, None)
            self._blas.__exit__(None, None, None)
            _return_freed_memory()


def _help(finished: Callable[[], bool]) -> None:
    """A pool thread out of jobs: `help_shared` on one BLAS thread, as each decode holds it in its own thread (a
    BLAS library with a thread count per thread, OpenMP or MKL, would otherwise run the tasks it takes on all)."""
    with one_blas_thread():
        help_shared(finished)


class DaskExecutor:
    """Jobs on a Dask distributed cluster at `address` ("local": a LocalCluster of `workers` single-threaded
    processes started here and stopped on close). A job whose worker fails is retried on another (DASK_RETRIES)."""

    def __init__(self, address: str, workers: int):
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise MapsqueezeError('--dask-scheduler needs Dask: pip install "mapsqueeze[dask]"') from None
        self._cluster = None
        if address == "local":
            self._cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                         dashboard_address=":0")
            self._client = Client(self._cluster)
        else:
            try:
                _probe_scheduler(address)
                _check_handshake(address)
                self._client = Client(address, timeout=f"{SCHEDULER_TIMEOUT_S}s")
            except (OSError, ValueError) as exc:
                raise MapsqueezeError(f"cannot reach the Dask scheduler at {address!r}: {exc}") from None
            except Exception as exc:  # another server, e.g. the dashboard's HTTP port: its reply read as a frame
                raise MapsqueezeError(f"cannot reach the Dask scheduler at {address!r}: the server there does not "
                                      f"answer as a Dask scheduler ({type(exc).__name__})") from None
        self.workers = max(1, len(self._client.scheduler_info().get("workers", {})) or workers)

    def map(self, function: TileFunction, context: Any, items: Iterable) -> Iterator:
        shared = self._client.scatter(context, broadcast=True, hash=False)
        threads = _threads_per_worker(self.workers) if self._cluster is not None else None  # remote: their own
        return _ordered(lambda item: self._client.submit(_run_with_context, function, shared, item, threads,
                                                         pure=False, retries=DASK_RETRIES), items,
                        IN_FLIGHT_PER_WORKER * self.workers, lambda future: future.result())

    def close(self, abort: bool = False) -> None:
        self._client.close()
        if self._cluster is not None:
            self._cluster.close()


Executor = SerialExecutor | ThreadExecutor | DaskExecutor


def _probe_scheduler(address: str) -> None:
    """Open and close a TCP connection to the host and port of a Dask scheduler address (tcp://, tls://, ws://,
    wss:// or host:port), or raise OSError (refused, unknown host, no answer within SCHEDULER_PROBE_S) or ValueError
    (no port, or one outside 1-65535). The Dask client retries a refused connection until its timeout (30 s); this fails in a round trip.
    The scheduler logs the connection as closed before its handshake."""
    from distributed.comm.addressing import parse_address, parse_host_port, unparse_host_port

    scheme, location = parse_address(address)
    if scheme not in _PROBED_SCHEMES:
        return
    host, port = parse_host_port(location)
    if not 0 < port < 1 << 16:
        raise ValueError(f"port {port} is outside 1-65535")
    try:
        socket.create_connection((host, port), timeout=SCHEDULER_PROBE_S).close()
    except TimeoutError:
        raise OSError(f"no answer from {unparse_host_port(host, port)} within {SCHEDULER_PROBE_S:g} s") from None
    except OSError as exc:
        raise OSError(f"{exc.strerror or exc} ({unparse_host_port(host, port)})") from None


def _check_handshake(address: str) -> None:
    """Open a Dask connection to the scheduler at a tcp://, tls://, ws://, wss:// or host:port address, handshake
    included, and close it, or raise OSError (no handshake within SCHEDULER_TIMEOUT_S). The Dask client waits for
    the handshake without a time limit (`distributed.comm.connect`), so a server that accepts connections and never
    answers (e.g. a port forward to a stopped scheduler) would hang it. The connection runs on an event loop of its
    own, in a daemon thread of its own (this thread may be running a loop, as in Jupyter), so that Ctrl-C ends the
    wait, and the process, at once."""
    import asyncio

    from distributed.comm import connect
    from distributed.comm.addressing import parse_address
    from distributed.security import Security

    if parse_address(address)[0] not in _PROBED_SCHEMES:
        return

    async def handshake() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=SCHEDULER_TIMEOUT_S,
                                              **Security().get_connection_args("client")), SCHEDULER_TIMEOUT_S)
        await comm.close()

    failed: list[BaseException] = []

    def check() -> None:
        try:
            asyncio.run(handshake())
        except BaseException as exc:  # noqa: BLE001 - raised in the calling thread
            failed.append(exc)

    thread = threading.Thread(target=check, name="mapsqueeze-dask-handshake", daemon=True)
    thread.start()
    thread.join()
    if failed and isinstance(failed[0], asyncio.TimeoutError):
        raise OSError("the server there accepts connections but sends no Dask handshake within "
                      f"{SCHEDULER_TIMEOUT_S:g} s") from None
    if failed:
        raise failed[0]


def open_executor(workers: int | None, dask_scheduler: str | None, n_jobs: int) -> Executor:
    """The executor for a run of n_jobs tile jobs: Dask when a scheduler address is given, for several workers and
    jobs a pool of threads, else this process. workers None: one per core."""
    workers = default_workers() if workers is None else check_workers(workers)
    if dask_scheduler:
        return DaskExecutor(dask_scheduler, workers)
    if workers > 1 and n_jobs > 1:
        return ThreadExecutor(min(workers, n_jobs))
    return SerialExecutor()


def _ordered(submit: Callable[[Any], Any], items: Iterable, in_flight: int, result: Callable[[Any], Any]) -> Iterator:
    """Submit items, keeping at most in_flight pending, and yield their results in input order."""
    pending: deque = deque()
    try:
        for item in items:
            pending.append(submit(item))
            if len(pending) >= in_flight:
                yield result(pending.popleft())
        while pending:
            yield result(pending.popleft())
    finally:
        for future in pending:
            future.cancel()


def _threads_per_worker(workers: int) -> int:
    return max(1, default_workers() // workers)


def _pool_thread_start(count: int) -> None:
    """A pool thread's first act: its OpenMP k-d tree searches (pykdtree's) run on `count` threads, unless the
    user set OMP_NUM_THREADS (OpenMP's thread count is each thread's own: without this a pool thread would start
    one OpenMP thread per core for every search). pykdtree is loaded first, so that its OpenMP library is there to
    be set."""
    if "OMP_NUM_THREADS" in os.environ:
        return
    import pykdtree.kdtree  # noqa: F401
    from threadpoolctl import ThreadpoolController

    ThreadpoolController().select(user_api="openmp").limit(limits=count)


def _keep_freed_memory() -> None:
    """Let glibc's malloc reuse a tile's freed arrays for the next tile (WORKER_MMAP_THRESHOLD_BYTES,
    WORKER_TRIM_THRESHOLD_BYTES): with its defaults, a pool maps and zero-fills every tile's arrays afresh (~20,000
    page faults a tile, ~2 of 6 CPU-s decoding 25 tiles in worker processes), and so does one thread decoding the
    tiles in turn (~171,000 page faults for those 25 tiles, BENCHMARKS.md "Throughput"). What earlier work freed
    and malloc kept (the previous run's tiles, compress's latent fit) is returned first (`_return_freed_memory`).
    Nothing changes where the C library has no mallopt."""
    _return_freed_memory()
    mallopt = _libc_function("mallopt")
    if mallopt is not None:
        mallopt(_M_MMAP_THRESHOLD, WORKER_MMAP_THRESHOLD_BYTES)
        mallopt(_M_TRIM_THRESHOLD, WORKER_TRIM_THRESHOLD_BYTES)


def _return_freed_memory() -> None:
    """Return the freed memory malloc keeps (every thread's heap: up to WORKER_TRIM_THRESHOLD_BYTES at its top and
    the free pages within it) to the system (glibc's malloc_trim), so that what one run of tile jobs, or the work
    between runs, freed does not add to the next run's memory (kept across compress's stages, it grew the peak RSS
    with the map's tile count). Nothing happens where the C library has no malloc_trim."""
    malloc_trim = _libc_function("malloc_trim")
    if malloc_trim is not None:
        malloc_trim(0)


def _libc_function(name: str):
    """The C library's function `name`, or None where it has none (or where the process's own symbols cannot be
    opened, as on Windows)."""
    import ctypes

    try:
        return getattr(ctypes.CDLL(None), name)
    except (OSError, AttributeError, TypeError):
        return None


_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
"""mallopt's parameter numbers (glibc's malloc.h)."""


def _run_with_context(function: TileFunction, context: Any, item: Any, threads: int | None) -> Any:
    if threads is not None:
        set_threads(threads)
    return function(context, item)
