"""Tile jobs in pool threads and on a Dask cluster give the bytes and points of the serial run."""

import platform
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from threadpoolctl import ThreadpoolController

import mapsqueeze
from mapsqueeze.codec import executor as executor_module
from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.io import read_points, write_points
from mapsqueeze.model import load_model

UTM = np.array([500_000.123, 4_000_000.456, 50.0])


@pytest.fixture(scope="module")
def model_dir(tiny_model_dir):
    return tiny_model_dir


@pytest.fixture(scope="module")
def model(model_dir):
    return load_model(model_dir)


@pytest.fixture(scope="module")
def map_points():
    """A 20 x 14 m ground and a wall at UTM coordinates: 6 occupied tiles of 8 x 8 x 4 m."""
    rng = np.random.default_rng(7)
    ground = np.column_stack([rng.uniform(0, 20, 6000), rng.uniform(0, 14, 6000), rng.normal(0.5, 0.03, 6000)])
    wall = np.column_stack([rng.uniform(2, 18, 2000), rng.normal(10.0, 0.02, 2000), rng.uniform(0.5, 6.0, 2000)])
    return np.concatenate([ground, wall]) + UTM


@pytest.fixture(scope="module")
def serial(map_points, model):
    data = mapsqueeze.compress(map_points, model=model, workers=1)
    return data, mapsqueeze.decompress(data, model=model, workers=1)


def test_pool_threads_give_the_serial_bytes_and_points(model, map_points, serial):
    data = mapsqueeze.compress(map_points, model=model, workers=3)
    assert data == serial[0]
    assert np.array_equal(mapsqueeze.decompress(data, model=model, workers=3), serial[1])


def test_attributes_coded_by_pool_threads_give_the_serial_bytes_and_values(map_points, model):
    from mapsqueeze.api import decompress_cloud

    attributes = {"intensity": np.random.default_rng(1).uniform(0, 1, len(map_points)).astype(np.float32)}
    data = mapsqueeze.compress(map_points, model=model, attributes=attributes, workers=1)
    assert mapsqueeze.compress(map_points, model=model, attributes=attributes, workers=2) == data
    serial, parallel = (decompress_cloud(data, model=model, workers=n) for n in (1, 2))
    assert np.array_equal(serial.points, parallel.points)
    assert np.array_equal(serial.attributes["intensity"], parallel.attributes["intensity"])


def test_file_to_file_with_workers_gives_the_serial_files(map_points, model_dir, serial, tmp_path):
    source = tmp_path / "map.ply"
    write_points(source, map_points)
    mapsqueeze.compress_file(source, tmp_path / "two.msq", model=model_dir, workers=2)
    assert (tmp_path / "two.msq").read_bytes() == serial[0]
    mapsqueeze.decompress_file(tmp_path / "two.msq", tmp_path / "two.npy", model=model_dir, workers=2)
    assert np.array_equal(read_points(tmp_path / "two.npy"), serial[1])


def test_compress_and_decompress_with_workers_import_no_torch_and_start_no_process(map_points, model_dir, serial,
                                                                                  tmp_path):
    """A compress and a decompress with 2 workers: the process loads no torch and starts no child process (the
    tiles run in its threads), and the bytes are the serial run's."""
    source, msq, decoded = tmp_path / "map.ply", tmp_path / "map.msq", tmp_path / "decoded.npy"
    write_points(source, map_points)
    probe = (f"import sys, multiprocessing, psutil, mapsqueeze; "
             f"mapsqueeze.compress_file({str(source)!r}, {str(msq)!r}, model={str(model_dir)!r}, workers=2); "
             f"mapsqueeze.decompress_file({str(msq)!r}, {str(decoded)!r}, model={str(model_dir)!r}, workers=2); "
             f"print('torch' in sys.modules, 'multiprocessing.forkserver' in sys.modules, "
             f"len(psutil.Process().children(recursive=True)))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert done.stdout.split() == ["False", "False", "0"]
    assert msq.read_bytes() == serial[0]
    assert np.array_equal(read_points(decoded), serial[1])


def test_decoding_imports_no_numba(model_dir, serial, tmp_path):
    """Decoding a file loads neither numba nor torch nor scipy: the decoder runs on numpy alone."""
    msq = tmp_path / "map.msq"
    msq.write_bytes(serial[0])
    probe = (f"import sys, mapsqueeze; "
             f"mapsqueeze.decompress_file({str(msq)!r}, {str(tmp_path / 'decoded.npy')!r}, "
             f"model={str(model_dir)!r}, workers=2); "
             f"print(sorted({{'numba', 'torch', 'scipy'}} & set(sys.modules)))")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"
    assert np.array_equal(read_points(tmp_path / "decoded.npy"), serial[1])


@pytest.mark.slow
def test_dask_cluster_gives_the_serial_bytes_and_points(map_points, model, serial):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster:
        data = mapsqueeze.compress(map_points, model=model, dask_scheduler=cluster.scheduler_address)
        assert data == serial[0]
        decoded = mapsqueeze.decompress(data, model=model, dask_scheduler=cluster.scheduler_address)
    assert np.array_equal(decoded, serial[1])


def test_results_come_in_input_order_with_a_bounded_number_in_flight():
    pending, most = [], 0

    class Job:
        def __init__(self, item):
            self.item = item

        def cancel(self):
            pass

    def submit(item):
        nonlocal most
        pending.append(item)
        most = max(most, len(pending))
        return Job(item)

    def result(job):
        pending.remove(job.item)
        return job.item * 10

    assert list(executor_module._ordered(submit, range(20), 4, result)) == [i * 10 for i in range(20)]
    assert most == 4


def _page_faults_of_a_second_round(context, sizes_mb):
    """Minor page faults of filling and freeing arrays of sizes_mb (MB) after one round of the same."""
    import resource

    def one_round():
        for size in sizes_mb:
            np.ones(size << 18, dtype=np.float32)

    one_round()
    who = resource.RUSAGE_THREAD  # the calling thread alone (a pool worker runs its jobs in its main thread)
    before = resource.getrusage(who).ru_minflt
    one_round()
    return resource.getrusage(who).ru_minflt - before


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_pool_threads_reuse_freed_memory_for_the_next_tile():
    pool = executor_module.ThreadExecutor(2)
    try:
        faults = list(pool.map(_page_faults_of_a_second_round, None, [[2, 4, 8, 16]] * 2))
    finally:
        pool.close()
    assert max(faults) < 500


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_serial_decoding_reuses_freed_memory_for_the_next_tile():
    """In a fresh process (malloc's settings are the process's): once a serial executor is opened, arrays of a few
    MB are taken from the freed ones (with glibc's defaults a second round maps and faults in ~2,000 pages)."""
    probe = ("import resource, numpy as np\nfrom mapsqueeze.codec.executor import SerialExecutor\nSerialExecutor()\n"
             "def one_round():\n    for size in (2, 4, 8, 16):\n        np.ones(size << 18, dtype=np.float32)\n"
             "one_round()\nbefore = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\none_round()\n"
             "print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert int(done.stdout) < 100


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's malloc_trim")
def test_a_closed_executor_returns_the_freed_memory_it_kept():
    """In a fresh process: the 48 MB of arrays freed while a serial executor is open stay resident (kept for the
    next tile) until it closes, which returns them to the system (what one of compress's stages frees does not add
    to the next one's memory)."""
    probe = ("import os, numpy as np\nfrom mapsqueeze.codec.executor import SerialExecutor\n"
             "def rss_mb():\n    pages = int(open('/proc/self/statm').read().split()[1])\n"
             "    return pages * os.sysconf('SC_PAGESIZE') >> 20\n"
             "executor = SerialExecutor()\narrays = [np.ones(1 << 17) for _ in range(48)]\nheld = rss_mb()\n"
             "del arrays\nkept = rss_mb()\nexecutor.close()\nprint(held - kept, kept - rss_mb())")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    returned_on_free, returned_on_close = map(int, done.stdout.split())
    assert returned_on_free < 8 and returned_on_close >= 40


@pytest.mark.parametrize("bad", [0, -1, True, 2.5])
def test_bad_worker_counts_are_refused(map_points, model, bad):
    with pytest.raises(MapsqueezeError, match="workers"):
        mapsqueeze.compress(map_points, model=model, workers=bad)


def test_cli_refuses_zero_workers(tmp_path):
    done = subprocess.run([sys.executable, "-m", "mapsqueeze", "compress", str(tmp_path / "map.ply"), "-o",
                           str(tmp_path / "map.msq"), "--workers", "0"], capture_output=True, text=True)
    assert done.returncode == 2 and done.stderr.startswith("error:") and "Traceback" not in done.stderr


@pytest.mark.parametrize("direction", ["compress", "decompress"])
def test_tiles_run_in_threads_on_their_share_of_the_cores(map_points, model, serial, monkeypatch, direction):
    """Several workers run the tile jobs in a pool of threads (`ThreadExecutor`): no child process, the serial
    run's bytes or points; in every job numpy's BLAS at one thread, the compiled kernels and the job thread's
    OpenMP searches at the workers' share of the cores (here 4 cores for 2 workers: 2 each, so two jobs run
    `run_over_ranges` at once); the caller's settings back afterwards."""
    import multiprocessing

    from mapsqueeze.geometry import threads as threads_module

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(executor_module, "default_workers", lambda: 4)
    opened, seen = [], []
    real = executor_module.ThreadExecutor

    class Spy(real):
        def __init__(self, workers):
            opened.append(workers)
            super().__init__(workers)

        def map(self, function, context, items):
            def job(context, item):
                seen.append((library_threads("blas", "numpy"), threads_module.threads(),
                             library_threads("openmp", "pykdtree")))
                return function(context, item)
            return super().map(job, context, items)

    monkeypatch.setattr(executor_module, "ThreadExecutor", Spy)
    import pykdtree.kdtree  # noqa: F401  (its OpenMP library, loaded for the controller to see)

    def library_threads(api, package):
        """The thread counts, as the calling thread sees them, of the loaded `api` libraries `package` ships."""
        return {library["num_threads"] for library in ThreadpoolController().select(user_api=api).info()
                if package in library["filepath"]}

    blas = ThreadpoolController().select(user_api="blas")
    kernels = threads_module.threads()
    with blas.limit(limits=2):
        if direction == "compress":
            assert mapsqueeze.compress(map_points, model=model, workers=2) == serial[0]
        else:
            assert np.array_equal(mapsqueeze.decompress(serial[0], model=model, workers=2), serial[1])
        assert library_threads("blas", "numpy") == {2}
    assert threads_module.threads() == kernels
    n_tiles = mapsqueeze.info(serial[0]).n_tiles
    jobs = 2 * n_tiles if direction == "compress" else n_tiles  # compress: embed, then candidates
    assert opened == [2] * (jobs // n_tiles) and seen == [({1}, 2, {2})] * jobs
    assert multiprocessing.active_children() == []


def test_thread_pool_gives_results_in_order_and_passes_errors_on():
    pool = executor_module.ThreadExecutor(3)
    try:
        assert list(pool.map(lambda context, item: context + item, 100, range(12))) == list(range(100, 112))
        with pytest.raises(MapsqueezeError, match="tile 4"):
            list(pool.map(_fail_on_four, None, range(8)))
    finally:
        pool.close(abort=True)


def _fail_on_four(context, item):
    if item == 4:
        raise MapsqueezeError("tile 4 is broken")
    return item


def test_a_thread_out_of_jobs_helps_the_running_ones_with_their_shared_tasks():
    """Once every job is handed out, an idle thread of the pool takes tasks that a running job offers
    (`run_shared`); the tasks write their own outputs, so the job's result is the serial one."""
    import threading
    import time

    from mapsqueeze.geometry.threads import run_shared

    def job(context, item):
        out, ran_in = np.zeros(40), [None] * 40

        def task(i):
            time.sleep(0.005)
            out[i], ran_in[i] = item * 100 + i, threading.get_ident()

        run_shared([lambda i=i: task(i) for i in range(40)])
        return out, set(ran_in)

    pool = executor_module.ThreadExecutor(2)
    try:
        results = list(pool.map(job, None, [7]))
    finally:
        pool.close()
    out, threads = results[0]
    assert np.array_equal(out, 700 + np.arange(40)) and len(threads) == 2


def test_a_shared_task_that_fails_fails_its_job_once_the_others_are_done():
    import time

    from mapsqueeze.geometry.threads import run_shared

    finished = []

    def task(i):
        time.sleep(0.002)
        if i == 5:
            raise MapsqueezeError("task 5 is broken")
        finished.append(i)

    def job(context, item):
        run_shared([lambda i=i: task(i) for i in range(30)])

    pool = executor_module.ThreadExecutor(2)
    try:
        with pytest.raises(MapsqueezeError, match="task 5"):
            list(pool.map(job, None, [0]))
        assert 5 not in finished and len(finished) < 29  # the tasks not yet taken were dropped
        assert list(pool.map(lambda context, item: item, None, range(5))) == list(range(5))  # the pool still works
    finally:
        pool.close()


def test_overlapping_thread_pools_keep_blas_at_one_thread_until_the_last_closes():
    """Two decoding pools opened and closed by two threads, overlapping: the second pool's jobs still run on one
    BLAS thread after the first pool closed, and the caller's count comes back once both are closed (threadpoolctl
    alone ignores the limits of all but one thread)."""
    import threading

    blas = ThreadpoolController().select(user_api="blas")
    numpy_blas_threads = lambda: {library["num_threads"] for library in blas.info()  # noqa: E731
                                  if "numpy" in library["filepath"]}
    first_open, second_open, first_closed = threading.Event(), threading.Event(), threading.Event()
    seen = []

    def first():
        pool = executor_module.ThreadExecutor(2)
        first_open.set()
        second_open.wait(10)
        pool.close()
        first_closed.set()

    def second():
        first_open.wait(10)
        pool = executor_module.ThreadExecutor(2)
        second_open.set()
        first_closed.wait(10)
        try:
            seen.extend(pool.map(lambda context, item: numpy_blas_threads(), None, range(4)))
        finally:
            pool.close()

    with blas.limit(limits=2):
        threads = [threading.Thread(target=first), threading.Thread(target=second)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(30)
        assert seen == [{1}] * 4
        assert numpy_blas_threads() == {2}


def _closed_port() -> int:
    """A local TCP port nothing listens on (bound, then released)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _http_server() -> socket.socket:
    """A listening socket answering every connection as an HTTP server answers a bad request (e.g. the Dask
    dashboard's port given as the scheduler's)."""
    server = socket.create_server(("127.0.0.1", 0))

    def serve():
        while True:
            try:
                connection, _ = server.accept()
            except OSError:  # closed
                return
            with connection:
                connection.recv(65536)
                connection.sendall(b"HTTP/1.1 400 Bad Request\r\nconnection: close\r\ncontent-length: 0\r\n\r\n")

    threading.Thread(target=serve, daemon=True).start()
    return server


@pytest.mark.parametrize("case", ["refused", "http server", "silent server"])
def test_an_unreachable_dask_scheduler_is_one_error_line_within_seconds(run_cli, map_points, model_dir, tmp_path,
                                                                         monkeypatch, case):
    """A refused connection fails in a round trip (the Dask client alone retries it for its 30 s timeout); a
    server that answers but not as a scheduler is one line too, not a traceback; so is one that accepts connections
    and never answers (a listening socket nobody reads: the kernel accepts for it), after SCHEDULER_TIMEOUT_S
    (here 1 s) instead of never (the Dask client waits for the handshake without a time limit)."""
    pytest.importorskip("distributed")
    monkeypatch.setattr(executor_module, "SCHEDULER_TIMEOUT_S", 1)
    write_points(tmp_path / "map.ply", map_points)
    server = {"http server": _http_server, "silent server": lambda: socket.create_server(("127.0.0.1", 0)),
              "refused": lambda: None}[case]()
    address = f"tcp://127.0.0.1:{server.getsockname()[1] if server else _closed_port()}"
    started = time.monotonic()
    try:
        code, out, err = run_cli("compress", str(tmp_path / "map.ply"), "-o", str(tmp_path / "map.msq"), "--model",
                                 str(model_dir), "--dask-scheduler", address)
    finally:
        if server:
            server.close()
    elapsed = time.monotonic() - started
    reason = {"refused": "Connection refused", "http server": "the server there does not answer as a Dask scheduler",
              "silent server": "the server there accepts connections but sends no Dask handshake within 1 s"}[case]
    assert (code, out) == (2, "") and err.startswith(f"error: cannot reach the Dask scheduler at {address!r}: {reason}")
    assert err.count("\n") == 1 and elapsed < 15.0 and sorted(path.name for path in tmp_path.iterdir()) == ["map.ply"]


_INTERRUPTED_HANDSHAKE_PROBE = """
import signal, sys, time
from mapsqueeze.codec import executor
import distributed.comm  # loaded before the alarm is set

def interrupt(signum, frame):
    raise KeyboardInterrupt
executor.SCHEDULER_TIMEOUT_S = 20
signal.signal(signal.SIGALRM, interrupt)
signal.alarm(1)
started = time.monotonic()
try:
    executor._check_handshake(sys.argv[1])
except KeyboardInterrupt:
    print(round(time.monotonic() - started, 1))
"""


def test_ctrl_c_ends_a_wait_for_the_dask_handshake_at_once():
    """Ctrl-C while a silent server is waited on for its handshake (SCHEDULER_TIMEOUT_S, here 20 s) ends the wait
    at once, as it did the Dask client's, and the process with it (the connection's thread is a daemon)."""
    pytest.importorskip("distributed")
    with socket.create_server(("127.0.0.1", 0)) as server:
        started = time.monotonic()
        done = subprocess.run([sys.executable, "-c", _INTERRUPTED_HANDSHAKE_PROBE,
                               f"tcp://127.0.0.1:{server.getsockname()[1]}"], capture_output=True, text=True,
                              timeout=60)
        ended = time.monotonic() - started
    assert done.returncode == 0, done.stderr
    assert float(done.stdout) < 5.0 and ended < 15.0, (done.stdout, ended)


def test_the_scheduler_probe_passes_a_listening_port_and_leaves_other_schemes_to_dask():
    pytest.importorskip("distributed")
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        for address in (f"tcp://127.0.0.1:{port}", f"127.0.0.1:{port}", f"tls://127.0.0.1:{port}"):
            executor_module._probe_scheduler(address)
    executor_module._probe_scheduler("inproc://192.168.1.1/1234/1")
    with pytest.raises(ValueError, match="port"):
        executor_module._probe_scheduler("tcp://127.0.0.1")
    for port in (0, 65536, 99999):  # getaddrinfo would wrap 99999 onto another port
        with pytest.raises(ValueError, match="outside 1-65535"):
            executor_module._probe_scheduler(f"tcp://127.0.0.1:{port}")
