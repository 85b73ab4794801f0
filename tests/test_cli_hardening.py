"""The command line in odd environments and in a new user's hands: output paths, read-only homes, signals,
leftovers of killed runs, zero points, --format, piped output, help text, info of a custom model."""

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np
import pytest

import mapsqueeze
from mapsqueeze import api
from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.io import DEFAULT_CHUNK_POINTS, read_point_cloud, read_points, write_points
from mapsqueeze.metrics import EVALUATION_STAGES, evaluate

UTM = np.array([500_000.123, 4_000_000.456, 50.0])


def ground(n: int = 3000, size_m: float = 14.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, size_m, n), rng.uniform(0, size_m / 2, n), rng.normal(0.5, 0.03, n)])


@pytest.fixture
def map_file(tmp_path):
    path = tmp_path / "map.ply"
    write_points(path, ground() + UTM)
    return path


def cli_subprocess(*args, **kwargs) -> subprocess.CompletedProcess:
    """`mapsqueeze ARGS` in a fresh interpreter with this checkout's sources first on the path."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), **kwargs.pop("env", {})}
    return subprocess.run([sys.executable, "-c", "from mapsqueeze.cli import main; main()", *map(str, args)],
                          capture_output=True, text=True, env=env, **kwargs)


# --- output path, checked before any work -----------------------------------------------------------------------

@pytest.mark.parametrize("target", ["missing/x.msq", "a-directory"])
def test_compress_checks_the_output_path_before_compressing(run_cli, map_file, tiny_model_dir, tmp_path,
                                                            monkeypatch, target):
    (tmp_path / "a-directory").mkdir()
    monkeypatch.setattr(api, "compress_chunks", lambda *a, **k: pytest.fail("compressed before the path check"))
    code, out, err = run_cli("compress", str(map_file), "-o", str(tmp_path / target), "--model", str(tiny_model_dir))
    assert code == 2 and out == "" and err.count("\n") == 1 and err.startswith("error: ")
    assert ("does not exist" if "missing" in target else "is a directory") in err


def test_decompress_checks_the_output_path_before_decoding(run_cli, map_file, tiny_model_dir, tmp_path):
    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, str(tiny_model_dir))
    code, _, err = run_cli("decompress", str(msq), "-o", str(tmp_path / "missing" / "x.ply"))
    assert code == 2 and "does not exist" in err and err.count("\n") == 1


@pytest.mark.slow
def test_unwritable_package_home_and_output_folder(tiny_model_dir, map_file, tmp_path):
    """A user who can write neither the package folder, nor ~/.cache, nor NUMBA_CACHE_DIR: the compiled kernels
    still run (numba would refuse with "cannot cache function"), and an unwritable output folder is one error line.
    Unwritable even for root: each `__pycache__` of the copied package, HOME and NUMBA_CACHE_DIR lie under plain
    files, and the output folder is /proc."""
    package = tmp_path / "pkg" / "mapsqueeze"
    shutil.copytree(Path(mapsqueeze.__file__).parent, package, ignore=shutil.ignore_patterns("__pycache__", "*.nb?"))
    for folder in package.rglob("*"):
        if folder.is_dir():
            (folder / "__pycache__").write_text("not a folder")
    (package / "__pycache__").write_text("not a folder")
    (tmp_path / "file").write_text("not a folder")
    (tmp_path / "tmp").mkdir()
    env = {**{k: v for k, v in os.environ.items() if k != "XDG_CACHE_HOME"},
           "HOME": str(tmp_path / "file" / "home"), "NUMBA_CACHE_DIR": str(tmp_path / "file" / "numba"),
           "TMPDIR": str(tmp_path / "tmp"), "PYTHONPATH": str(tmp_path / "pkg"), "PYTHONDONTWRITEBYTECODE": "1"}
    run = [sys.executable, "-c", "from mapsqueeze.cli import main; main()"]
    common = dict(capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    refused = subprocess.run([*run, "compress", str(map_file), "-o", "/proc/x.msq", "--model", str(tiny_model_dir)],
                             **common)
    assert refused.returncode == 2 and refused.stderr.startswith("error: /proc/x.msq: cannot write in folder /proc")
    assert refused.stderr.count("\n") == 1
    done = subprocess.run([*run, "compress", str(map_file), "-o", "x.msq", "--model", str(tiny_model_dir)], **common)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "x.msq").read_bytes() == mapsqueeze.compress(read_points(map_file), str(tiny_model_dir))


# --- signals and leftovers of killed runs -----------------------------------------------------------------------

TILE_JOB_MARKED_CLI = """
import os, pathlib, threading
from mapsqueeze.codec import compress, decompress
for module, name in ((compress, "embed_job"), (compress, "candidates_job"), (decompress, "_decode_job")):
    def marked(*args, job=getattr(module, name)):
        mark = pathlib.Path(os.environ["TILE_JOB_MARK"])
        temp = mark.with_name(f"{mark.name}.{threading.get_ident()}")
        temp.write_text(threading.current_thread().name)
        os.replace(temp, mark)
        return job(*args)
    setattr(module, name, marked)
from mapsqueeze.cli import main
main()
"""
"""`mapsqueeze ARGS` that writes the name of the thread running a tile job to $TILE_JOB_MARK as each job starts."""


def _signals_as_in_a_terminal():
    """Default SIGINT and SIGTERM in the child: a shell that starts the test run in the background (as CI may) leaves
    SIGINT ignored, and the command line rightly keeps an ignored signal ignored."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


@pytest.mark.slow
@pytest.mark.parametrize("command, signum, workers", [("compress", signal.SIGINT, 2), ("compress", signal.SIGTERM, 1),
                                                      ("decompress", signal.SIGINT, 2)],
                         ids=["compress-SIGINT-2-workers", "compress-SIGTERM-1-worker", "decompress-SIGINT-2-workers"])
def test_a_signal_while_tiles_are_coded_gives_one_line_and_removes_temporary_files(tiny_model_dir, tmp_path, command,
                                                                                   signum, workers):
    """Ctrl-C or SIGTERM while tiles are coded (in the pool's threads with --workers 2): one error line, exit code
    128 + the signal, the pool's threads ended, no spill folder, output or temporary file left, the input as it was."""
    spill, work = tmp_path / "tmp", tmp_path / "work"
    spill.mkdir()
    work.mkdir()
    if command == "compress":  # 120 tiles of 500 points, each refined 200 steps: minutes to the end
        source = work / "big.ply"
        write_points(source, np.concatenate([ground(30_000, 120.0, seed) for seed in range(2)]) + UTM)
        args = [source, "-o", work / "big.msq", "--model", tiny_model_dir, "--refine", 200]
    else:  # 4,000,000 points decoded from 8 tiles, through spill files (a PCD is written from them)
        source = work / "big.msq"
        mapsqueeze.compress_file(map_file_of(work / "small.ply", ground(4000, 30.0)), source, str(tiny_model_dir))
        (work / "small.ply").unlink()
        args = [source, "-o", work / "big.pcd", "--model", tiny_model_dir, "--points", 4_000_000]
    before = source.read_bytes()
    mark = tmp_path / "mark"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "TMPDIR": str(spill), "TILE_JOB_MARK": str(mark)}
    process = subprocess.Popen([sys.executable, "-c", TILE_JOB_MARKED_CLI, command, *map(str, args),
                                "--workers", str(workers)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                               preexec_fn=_signals_as_in_a_terminal)
    deadline = time.monotonic() + 300
    while not mark.exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.05)
    assert mark.exists() and process.poll() is None, f"no tile job started: {process.communicate()}"
    if workers > 1:
        assert mark.read_text().startswith("mapsqueeze-tile")
    assert list(spill.glob("mapsqueeze-*")), "no spill folder while tiles are coded"
    process.send_signal(signum)
    try:
        out, err = process.communicate(timeout=120)  # the pool's threads finish their running tiles and end
    finally:
        process.kill()
    assert (process.returncode, out, err) == (128 + signum, "", f"error: {SIGNAL_WORDS[signum]}\n")
    assert list(spill.iterdir()) == [] and [p.name for p in work.iterdir()] == [source.name]
    assert source.read_bytes() == before


SIGNAL_WORDS = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated"}


def test_the_entry_point_runs_in_another_thread_and_leaves_the_signal_handlers_as_it_found_them(monkeypatch, capsys):
    """main() called from a thread other than the main one (an application running the CLI in a worker thread),
    where Python refuses to set signal handlers, runs the command and leaves SIGINT and SIGTERM to the main thread's
    handlers; in the main thread the handlers it replaced are restored."""
    import threading

    from mapsqueeze.cli import main

    monkeypatch.setattr(sys, "argv", ["mapsqueeze", "models"])
    before = {signum: signal.getsignal(signum) for signum in SIGNAL_WORDS}
    ended = []

    def run() -> None:
        try:
            main()
        except BaseException as exc:  # noqa: BLE001  (SystemExit is the expected end)
            ended.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert len(ended) == 1 and isinstance(ended[0], SystemExit) and ended[0].code == 0, ended
    assert "shipped models" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        main()
    assert exit_info.value.code == 0
    assert {signum: signal.getsignal(signum) for signum in SIGNAL_WORDS} == before


def map_file_of(path: Path, points: np.ndarray) -> Path:
    write_points(path, points + UTM)
    return path


def dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_leftovers_of_dead_processes_are_removed_by_the_next_run(map_file, tiny_model_dir, tmp_path, monkeypatch):
    spill = tmp_path / "tmp"
    spill.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spill))
    pid = dead_pid()
    stale = [spill / f"mapsqueeze-tiles-{pid}-abc_1", spill / f"mapsqueeze-decoded-{pid}-x9",
             tmp_path / f".out.ply.{pid}-0a1b2c3d.tmp"]
    alive = [spill / f"mapsqueeze-tiles-{os.getpid()}-live", spill / "mapsqueeze-tiles-nopid"]
    for path in stale[:2] + alive:
        path.mkdir()
        (path / "tile_0_0_0.f64").write_bytes(b"x" * 24)
    stale[2].write_bytes(b"partial")
    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, str(tiny_model_dir))
    assert stale[0].exists() is False and stale[1].exists()  # compress cleans its own prefix
    mapsqueeze.decompress_file(msq, tmp_path / "out.ply", model=str(tiny_model_dir))
    assert not any(path.exists() for path in stale) and all(path.exists() for path in alive)


# --- a new user's first hour ------------------------------------------------------------------------------------

def test_points_at_the_origin_are_dropped_by_default(run_cli, tiny_model_dir, tmp_path):
    points = np.concatenate([ground(), np.zeros((70, 3))])
    source = tmp_path / "scan.ply"
    write_points(source, points)
    code, out, _ = run_cli("compress", str(source), "-o", str(tmp_path / "a.msq"), "--model", str(tiny_model_dir))
    assert code == 0 and "left out 70 points at exactly (0, 0, 0)" in out
    assert mapsqueeze.info(tmp_path / "a.msq").n_points == 3000
    code, out, _ = run_cli("compress", str(source), "-o", str(tmp_path / "b.msq"), "--model", str(tiny_model_dir),
                           "--keep-zero-points")
    assert code == 0 and "left out" not in out and mapsqueeze.info(tmp_path / "b.msq").n_points == 3070
    # The API: the same default and flag, in memory and file to file.
    points = read_points(source)
    assert mapsqueeze.compress(points, model=str(tiny_model_dir)) == (tmp_path / "a.msq").read_bytes()
    kept = mapsqueeze.compress(points, model=str(tiny_model_dir), keep_zero_points=True)
    assert kept == (tmp_path / "b.msq").read_bytes()
    write_points(source, np.zeros((5, 3)))
    code, _, err = run_cli("compress", str(source), "-o", str(tmp_path / "c.msq"), "--model", str(tiny_model_dir))
    assert code == 2 and "all 5 points lie at (0, 0, 0)" in err and "--keep-zero-points" in err


def organised_records(points: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """x, y, z and intensity as float32 PCD point records."""
    records = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    records["x"], records["y"], records["z"] = points.T
    records["intensity"] = intensity
    return records


def organised_pcd(path: Path, points: np.ndarray, intensity: np.ndarray) -> Path:
    """x, y, z and intensity as a binary PCD of 2 rows (an organised cloud), NaN rows as they are."""
    records = organised_records(points, intensity)
    header = ("VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
              f"WIDTH {len(points) // 2}\nHEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA binary\n")
    path.write_bytes(header.encode() + records.tobytes())
    return path


def test_pcd_points_with_nan_coordinates_are_left_out_by_every_command(run_cli, tiny_model_dir, tmp_path):
    """compress, convert, eval and view read an organised PCD without its NaN ("no return") points and their
    attributes, each saying how many; the .msq is the one of the same PCD without those rows."""
    points = ground().astype(np.float32)
    intensity = np.random.default_rng(3).uniform(0, 100, 3000).astype(np.float32)
    missing = np.zeros(3000, bool)
    missing[::9] = True  # 334
    points[missing] = np.nan
    source = organised_pcd(tmp_path / "org.pcd", points, intensity)
    write_points(tmp_path / "dense.pcd", points[~missing], attributes={"intensity": intensity[~missing]})
    code, out, err = run_cli("compress", str(source), "-o", str(tmp_path / "org.msq"), "--model", str(tiny_model_dir))
    assert code == 0 and err == "" and out.startswith("left out 334 points with NaN coordinates (PCD 'no return' "
                                                      "values)\nwrote ") and out.count("\n") == 2
    assert mapsqueeze.info(tmp_path / "org.msq").n_points == 2666
    mapsqueeze.compress_file(tmp_path / "dense.pcd", tmp_path / "dense.msq", str(tiny_model_dir))
    assert (tmp_path / "org.msq").read_bytes() == (tmp_path / "dense.msq").read_bytes()
    code, out, _ = run_cli("convert", str(source), str(tmp_path / "org.ply"))
    assert (code, out) == (0, f"left out 334 points with NaN coordinates (PCD 'no return' values)\n"
                              f"wrote 2,666 points to {tmp_path / 'org.ply'}\n")
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "org.ply").attributes["intensity"],
                                  intensity[~missing])
    code, out, err = run_cli("eval", str(source), str(tmp_path / "org.ply"), "--json")
    assert code == 0 and err == f"left out 334 points of {source} with NaN coordinates (PCD 'no return' values)\n"
    assert json.loads(out)["n_gt"] == 2666 and json.loads(out)["d_e"] == 0.0
    code, out, _ = run_cli("view", str(tmp_path / "org.msq"), "--original", str(source), "-o",
                           str(tmp_path / "v.html"), "--max-points", "500")
    assert code == 0 and out.startswith(f"left out 334 points of {source} with NaN coordinates") and \
        "original 500 of 2,666" in out
    # one of each: singular
    points, intensity = ground(), np.ones(3000)
    points[7], points[8] = np.nan, 0.0
    code, out, _ = run_cli("compress", str(organised_pcd(tmp_path / "one.pcd", points, intensity)), "-o",
                           str(tmp_path / "one.msq"), "--model", str(tiny_model_dir))
    assert code == 0 and out.startswith("left out 1 point with NaN coordinates (PCD 'no return' values)\n"
                                        "left out 1 point at exactly (0, 0, 0) (sensor 'no return' values; ")


def test_binary_compressed_pcd_compresses_to_the_bytes_of_the_same_binary_pcd(run_cli, tiny_model_dir, tmp_path,
                                                                              binary_compressed_pcd):
    """PCL's DATA binary_compressed (LZF, each field for every point in turn) holds the cloud DATA binary holds:
    the same NaN points left out and said, the same .msq bytes."""
    points = ground().astype(np.float32)
    intensity = np.random.default_rng(4).uniform(0, 100, 3000).astype(np.float32)
    points[::9] = np.nan
    organised_pcd(tmp_path / "binary.pcd", points, intensity)
    binary_compressed_pcd(tmp_path / "lzf.pcd", organised_records(points, intensity), height=2)
    assert b"DATA binary_compressed\n" in (tmp_path / "lzf.pcd").read_bytes()
    outputs = {}
    for name in ("binary", "lzf"):
        code, out, err = run_cli("compress", str(tmp_path / f"{name}.pcd"), "-o", str(tmp_path / f"{name}.msq"),
                                 "--model", str(tiny_model_dir))
        assert code == 0 and err == "" and out.startswith("left out 334 points with NaN coordinates (PCD 'no return' "
                                                          "values)\nwrote ")
        outputs[name] = (tmp_path / f"{name}.msq").read_bytes()
    assert outputs["lzf"] == outputs["binary"]
    summary = mapsqueeze.info(outputs["lzf"])
    assert summary.n_points == 2666 and "intensity" in summary.attributes


@pytest.mark.parametrize("case", ["all NaN", "infinite"])
def test_pcd_with_only_nan_or_infinite_coordinates_is_one_error_line(run_cli, tiny_model_dir, tmp_path, case):
    points = np.full((8, 3), np.nan) if case == "all NaN" else ground()
    points[-1, 0] = np.nan if case == "all NaN" else np.inf
    source = organised_pcd(tmp_path / "bad.pcd", points, np.ones(len(points)))
    expected = ("no points: all 8 points have NaN coordinates" if case == "all NaN"
                else "1 of 3,000 points has infinite coordinates (the first: point 2,999")
    for args in (["compress", source, "-o", tmp_path / "bad.msq", "--model", tiny_model_dir],
                 ["convert", source, tmp_path / "bad.ply"], ["eval", source, source]):
        code, out, err = run_cli(*map(str, args))
        assert (code, out) == (2, "") and err.startswith(f"error: {source}: {expected}") and err.count("\n") == 1
    assert sorted(path.name for path in tmp_path.iterdir()) == ["bad.pcd"]


def test_a_pcd_of_only_nan_and_zero_points_counts_both_in_its_error_line(run_cli, tiny_model_dir, tmp_path):
    """Points left out by the reader (NaN) and by compress (at (0, 0, 0)) leave nothing to code: the one error line
    names both counts, as the two lines of a run with points left do; --keep-zero-points keeps the zero ones."""
    points = np.zeros((12, 3))
    points[1::3] = np.nan  # 4 NaN, 8 at the origin
    source = organised_pcd(tmp_path / "empty.pcd", points, np.ones(len(points)))
    code, out, err = run_cli("compress", str(source), "-o", str(tmp_path / "empty.msq"), "--model",
                             str(tiny_model_dir))
    assert (code, out) == (2, "") and err == (
        f"error: {source}: no points: 4 of 12 points have NaN coordinates (PCD 'no return' values) and the other 8 "
        "lie at (0, 0, 0) (sensor 'no return' values); keep those with --keep-zero-points\n")
    code, out, _ = run_cli("compress", str(source), "-o", str(tmp_path / "kept.msq"), "--model", str(tiny_model_dir),
                           "--keep-zero-points")
    assert code == 0 and out.startswith("left out 4 points with NaN coordinates (PCD 'no return' values)\nwrote ")
    assert mapsqueeze.info(tmp_path / "kept.msq").n_points == 8
    assert sorted(path.name for path in tmp_path.iterdir()) == ["empty.pcd", "kept.msq"]


def test_an_integer_npy_is_refused_with_how_to_convert_it(run_cli, tiny_model_dir, tmp_path):
    """Integer x, y, z (millimetres? centimetres? voxel indices?) have no unit to read them in: one error line
    saying to save float metres, for compress and convert alike; the same values as floats are read as metres."""
    centimetres = np.round(ground() * 100).astype(np.int32)
    source = tmp_path / "cm.npy"
    np.save(source, centimetres)
    for args in (["compress", source, "-o", tmp_path / "cm.msq", "--model", tiny_model_dir],
                 ["convert", source, tmp_path / "cm.ply"]):
        code, out, err = run_cli(*map(str, args))
        assert (code, out) == (2, "") and err.count("\n") == 1
        assert err.startswith(f"error: {source}: .npy holds int32 integers, whose unit is unknown; x, y, z must be "
                              "floats in metres") and "* 0.01" in err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["cm.npy"]
    np.save(source, centimetres * 0.01)
    code, out, _ = run_cli("convert", str(source), str(tmp_path / "m.ply"))
    assert code == 0 and out == f"wrote 3,000 points to {tmp_path / 'm.ply'}\n"
    np.testing.assert_allclose(read_points(tmp_path / "m.ply"), centimetres * 0.01, atol=1e-3)


def test_non_finite_points_beyond_the_first_chunk_are_numbered_in_the_map(run_cli, tiny_model_dir, tmp_path):
    """A map is read in chunks of DEFAULT_CHUNK_POINTS: the error names points of the map, not of the chunk."""
    points = ground(DEFAULT_CHUNK_POINTS + 40_000) + UTM
    bad = [DEFAULT_CHUNK_POINTS + 1000, DEFAULT_CHUNK_POINTS + 30_000]
    points[bad, 2] = np.nan
    source = tmp_path / "map.npy"
    np.save(source, points)
    code, out, err = run_cli("compress", str(source), "-o", str(tmp_path / "map.msq"), "--model", str(tiny_model_dir))
    assert (code, out) == (2, "")
    assert err == (f"error: {source}: 2 of points {DEFAULT_CHUNK_POINTS:,} to {len(points) - 1:,} (of {len(points):,}) "
                   f"have NaN or infinite coordinates (the first: point {bad[0]:,}, counting from 0)\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.npy"]


def test_format_option_overrides_the_extension(run_cli, map_file, tiny_model_dir, tmp_path):
    odd_input = tmp_path / "map.data"
    shutil.copy(map_file, odd_input)
    msq = tmp_path / "map.msq"
    code, _, err = run_cli("compress", str(odd_input), "-o", str(msq), "--model", str(tiny_model_dir))
    assert code == 2 and "unknown point-cloud extension" in err
    code, out, _ = run_cli("compress", str(odd_input), "-o", str(msq), "--model", str(tiny_model_dir), "--format",
                           "ply")
    assert code == 0 and msq.stat().st_size > 0
    code, _, _ = run_cli("decompress", str(msq), "-o", str(tmp_path / "out.xyz"), "--model", str(tiny_model_dir),
                         "--format", "npy", "--points", "3000")
    assert code == 0 and len(np.load(tmp_path / "out.xyz")) == 3000
    code, _, err = run_cli("decompress", str(msq), "-o", str(tmp_path / "o.ply"), "--format", "xyz")
    assert code == 2 and "unknown point-cloud format 'xyz'" in err


def test_piped_output_is_not_wrapped(run_cli, map_file, tiny_model_dir, tmp_path):
    deep = tmp_path / ("a-rather-long-folder-name-" * 4)
    deep.mkdir()
    code, out, _ = run_cli("compress", str(map_file), "-o", str(deep / "map.msq"), "--model", str(tiny_model_dir))
    assert code == 0 and len(out.splitlines()) == 1 and out.rstrip().endswith("bits per point")
    assert " tiles (" in out  # the tiles per mode


def test_help_shows_flags_without_a_value():
    result = cli_subprocess("eval", "--help", timeout=120)
    assert result.returncode == 0 and "--json" in result.stdout and "<bool>" not in result.stdout


def test_info_names_a_custom_model_as_custom(run_cli, map_file, tiny_model_dir, tmp_path):
    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, str(tiny_model_dir))
    code, out, _ = run_cli("info", str(msq))
    assert code == 0 and "custom, named 'e1'" in out and "--model PATH" in out
    lines = out.splitlines()  # piped: one aligned line per row, no padding after the value
    assert lines[0].startswith("model ") and all(line == line.rstrip() for line in lines)
    assert len({len(line) - len(line[line.index("  "):].lstrip()) for line in lines}) == 1


def test_compress_reports_raw_tiles(run_cli, tiny_model_dir, tmp_path):
    sparse = tmp_path / "sparse.ply"
    write_points(sparse, np.concatenate([ground(3000), ground(5, seed=1) + [0, 0, 5]]) + UTM)
    code, out, _ = run_cli("compress", str(sparse), "-o", str(tmp_path / "s.msq"), "--model", str(tiny_model_dir))
    info = mapsqueeze.info(tmp_path / "s.msq")
    assert code == 0 and info.n_raw_tiles >= 1 and f"{info.n_raw_tiles} raw" in out



def test_eval_warns_when_the_clouds_do_not_overlap(run_cli, tmp_path):
    cloud = ground()
    write_points(tmp_path / "gt.ply", cloud)
    write_points(tmp_path / "near.ply", cloud + 0.01)
    write_points(tmp_path / "far.ply", cloud + [1000.0, 0.0, 0.0])
    write_points(tmp_path / "offset.ply", cloud + [12.0, 0.0, 0.0])  # 2 of 14 m overlap
    code, _, err = run_cli("eval", str(tmp_path / "gt.ply"), str(tmp_path / "near.ply"))
    assert code == 0 and err == ""
    code, out, err = run_cli("eval", str(tmp_path / "gt.ply"), str(tmp_path / "far.ply"), "--json")
    assert code == 0 and err.startswith("warning: the clouds do not overlap") and err.count("\n") == 1
    assert json.loads(out)["d_e"] > 900
    code, _, err = run_cli("eval", str(tmp_path / "gt.ply"), str(tmp_path / "offset.ply"))
    assert code == 0 and "barely overlap" in err


def test_evaluate_reports_its_stages():
    cloud = ground()
    stages = []
    evaluate(cloud, cloud + 0.01, progress=stages.append)
    assert stages == list(EVALUATION_STAGES)


@pytest.mark.parametrize("name, content", [
    ("objects.npy", None),
    ("short.bin", b"\x00" * 10),
    ("bad.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n2\n"),
    ("empty.pcd", b""),
    ("garbage.las", b"LASF" + b"\x00" * 50),
    ("folder.ply", "dir"),
])
def test_file_errors_name_the_file_and_never_suggest_pickles(tmp_path, name, content):
    path = tmp_path / name
    if content is None:
        np.save(path, np.array([{"x": 1}], dtype=object), allow_pickle=True)
    elif content == "dir":
        path.mkdir()
    else:
        path.write_bytes(content)
    with pytest.raises(MapsqueezeError) as error:
        read_points(path)
    assert str(error.value).startswith(f"{path}: ") and "pickle" not in str(error.value)


def test_density_counts_the_box_of_each_tiles_points(tiny_model_dir):
    cloud = ground()  # one 8 x 8 x 4 m tile of the tiny model holds x 0..8, y 0..7, z ~0.5 (a thin box: 1 m high)
    data = mapsqueeze.compress(cloud[(cloud[:, 0] < 7.9)], model=str(tiny_model_dir), precision="f16")
    info = mapsqueeze.info(data)
    box_m3 = np.prod(np.maximum(info.bounds[1] - info.bounds[0], 1.0))
    decoded = mapsqueeze.decompress(data, model=str(tiny_model_dir), density=20.0)
    assert info.n_tiles == 1 and abs(len(decoded) - 20.0 * box_m3) <= 20.0 * 0.01 * box_m3
    help_text = cli_subprocess("decompress", "--help", timeout=120).stdout
    assert "bounding box of each" in " ".join(help_text.replace("│", " ").split())


# --- a demanding new user's error paths: one line naming the problem, exit code 2, nothing written ---------------

def truncated(path: Path, fraction: float) -> Path:
    """A copy of `path` cut to `fraction` of its length, beside it."""
    data = path.read_bytes()
    cut = path.with_name(f"cut-{fraction:g}-{path.name}")
    cut.write_bytes(data[:int(len(data) * fraction)])
    return cut


@pytest.mark.parametrize("case", ["directory as input", "directory as decompress output", "directory as convert output",
                                  "convert into a missing folder", "truncated LAS", "truncated LAZ",
                                  "truncated ascii PCD", "truncated binary_compressed PCD",
                                  "corrupt binary_compressed PCD", "LAS declaring fewer points than it holds",
                                  "LAS point outside the header's bounds", "LAZ with a NaN GPS time"])
def test_bad_paths_and_truncated_files_name_the_problem(run_cli, tiny_model_dir, map_file, tmp_path, case,
                                                        binary_compressed_pcd):
    folder = tmp_path / "folder"
    folder.mkdir()
    points = ground(2000) + UTM
    if case == "directory as input":
        args, expected = ["compress", folder, "-o", tmp_path / "x.msq"], f"{folder}: is a directory, not a point-cloud"
    elif case == "directory as decompress output":
        mapsqueeze.compress_file(map_file, tmp_path / "map.msq", str(tiny_model_dir))
        args, expected = ["decompress", tmp_path / "map.msq", "-o", folder], f"{folder}: is a directory"
    elif case == "directory as convert output":
        args, expected = ["convert", map_file, folder], f"{folder}: is a directory"
    elif case == "convert into a missing folder":  # refused before the input is read: a truncated input says nothing
        write_points(tmp_path / "in.las", points)
        args = ["convert", truncated(tmp_path / "in.las", 0.5), tmp_path / "missing" / "out.ply"]
        expected = "missing/out.ply: folder"
    elif case == "truncated LAS":  # cut inside the point records: the header's count and record size tell
        write_points(tmp_path / "in.las", points)
        args, expected = ["convert", truncated(tmp_path / "in.las", 0.5), tmp_path / "out.ply"], "(truncated?)"
    elif case == "truncated LAZ":
        write_points(tmp_path / "in.laz", points)
        args = ["convert", truncated(tmp_path / "in.laz", 0.5), tmp_path / "out.ply"]
        expected = "corrupt or truncated LAZ point data"
    elif case == "LAS declaring fewer points than it holds":  # the rest would be left out unsaid
        write_points(tmp_path / "in.las", points)
        data = bytearray((tmp_path / "in.las").read_bytes())
        struct.pack_into("<I", data, 107, 100)  # legacy point count
        struct.pack_into("<Q", data, 247, 100)  # LAS 1.4 point count
        (tmp_path / "in.las").write_bytes(bytes(data))
        args, expected = ["convert", tmp_path / "in.las", tmp_path / "out.ply"], \
            "LAS header declares 100 points, the file holds 2,000 point records"
    elif case == "LAS point outside the header's bounds":  # corrupt coordinates, or a header that lies
        write_points(tmp_path / "in.las", points)
        data = bytearray((tmp_path / "in.las").read_bytes())
        struct.pack_into("<d", data, 179, points[:, 0].min() + 1.0)  # max x
        (tmp_path / "in.las").write_bytes(bytes(data))
        args, expected = ["compress", tmp_path / "in.las", "-o", tmp_path / "out.msq"], "lies outside the header's bounds"
    elif case == "LAZ with a NaN GPS time":  # what lazrs makes of damaged bytes, without an error
        header = laspy.LasHeader(version="1.2", point_format=1)
        header.offsets, header.scales = UTM, np.full(3, 0.001)
        las = laspy.LasData(header)
        las.x, las.y, las.z = points.T
        las.gps_time = np.where(np.arange(len(points)) == 1234, np.nan, 1e5)
        las.write(str(tmp_path / "in.laz"))
        args, expected = ["convert", tmp_path / "in.laz", tmp_path / "out.ply"], \
            "point 1,234 has a GPS time of nan: corrupt point data"
    elif case == "truncated ascii PCD":
        write_points(tmp_path / "in.pcd", points, format="pcd-ascii")
        args = ["convert", truncated(tmp_path / "in.pcd", 0.5), tmp_path / "out.ply"]
        expected = "corrupt PCD ascii data (the number of columns changed"
    else:
        records = np.empty(len(points), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
        records["x"], records["y"], records["z"] = points.T
        source = binary_compressed_pcd(tmp_path / "in.pcd", records)
        if case == "truncated binary_compressed PCD":
            args, expected = ["compress", truncated(source, 0.5), "-o", tmp_path / "out.msq"], "(truncated?)"
        else:  # the LZF stream's first token made a back-reference (LZF has no checksum: a flipped literal passes)
            data = bytearray(source.read_bytes())
            data[data.index(b"DATA binary_compressed\n") + 23 + 8] = 0x20
            source.write_bytes(bytes(data))
            args, expected = ["convert", source, tmp_path / "out.ply"], "corrupt PCD binary_compressed data (LZF: "
    before = sorted(tmp_path.rglob("*"))
    code, out, err = run_cli(*map(str, args))
    assert (code, out) == (2, "") and err.startswith("error: ") and err.count("\n") == 1, err
    assert expected in err and "usecols" not in err
    assert sorted(tmp_path.rglob("*")) == before  # no output, no temporary file


@pytest.mark.parametrize("config", [[1, 2], {"tile_size": "abc"}, {"subsampling_dist": "x"}, {"map_size": 0},
                                    {"max_input_points": -5}, {"tile_size": [8, 8, float("inf")]}, {"name": 7},
                                    None])
def test_a_model_folder_with_a_bad_config_is_one_line_naming_it(run_cli, tiny_model_dir, map_file, tmp_path, config):
    model = tmp_path / "model"
    shutil.copytree(tiny_model_dir, model)
    if config is None:
        (model / "config.json").unlink()
    elif isinstance(config, dict):
        (model / "config.json").write_text(json.dumps({**json.loads((model / "config.json").read_text()), **config}))
    else:
        (model / "config.json").write_text(json.dumps(config))
    code, out, err = run_cli("compress", str(map_file), "-o", str(tmp_path / "x.msq"), "--model", str(model))
    assert (code, out) == (2, "") and err.startswith(f"error: {model / 'config.json'}: ") and err.count("\n") == 1
    assert not (tmp_path / "x.msq").exists()


def test_a_msq_cut_anywhere_is_one_line_for_info_and_decompress(run_cli, tiny_model_dir, tmp_path):
    """Cut at every tenth of its length and one byte short: header, tile table, payloads, attribute streams."""
    source = tmp_path / "map.ply"
    points = np.concatenate([ground(3000, 14.0, seed) + [9.0 * seed, 0, 0] for seed in range(3)]) + UTM
    write_points(source, points, attributes={"intensity": np.arange(len(points), dtype=np.uint16) % 200})
    whole = tmp_path / "map.msq"
    mapsqueeze.compress_file(source, whole, str(tiny_model_dir))
    assert mapsqueeze.info(whole).n_tiles > 1 and mapsqueeze.info(whole).attributes == ("intensity",)
    size = whole.stat().st_size
    for length in sorted({size * tenth // 10 for tenth in range(10)} | {size - 1}):
        cut = tmp_path / "cut.msq"
        cut.write_bytes(whole.read_bytes()[:length])
        for args in (["info", cut], ["decompress", cut, "-o", tmp_path / "out.las", "--model", tiny_model_dir]):
            code, out, err = run_cli(*map(str, args))
            assert (code, out) == (2, "") and err.startswith(f"error: {cut}: ") and err.count("\n") == 1, (length, err)
            assert "truncated" in err or "too short" in err, (length, err)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.msq", "map.msq", "map.ply"]


# --- output paths that would destroy data, and a Ctrl-C while the command line loads -----------------------------

@pytest.mark.parametrize("name", ["map.ply", "map.las", "map", "map.msq.tmp"])
def test_compress_refuses_an_output_name_that_decompress_would_read_as_a_point_cloud(run_cli, map_file, tmp_path,
                                                                                       monkeypatch, name):
    """`compress MAP -o out.ply` would write a .msq container under a point-cloud name (decompress picks its output's
    format by the extension): one line, nothing written, before any work; `.MSQ` is a .msq name."""
    monkeypatch.setattr(api, "compress_chunks", lambda *a, **k: pytest.fail("compressed before the name check"))
    code, out, err = run_cli("compress", str(map_file), "-o", str(tmp_path / name))
    assert (code, out) == (2, "") and err == (f"error: {tmp_path / name}: compress writes a .msq container; give an "
                                              "output name ending in .msq\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.ply"]


def test_compress_accepts_an_upper_case_msq_name(run_cli, map_file, tiny_model_dir, tmp_path):
    code, _, err = run_cli("compress", str(map_file), "-o", str(tmp_path / "MAP.MSQ"), "--model", str(tiny_model_dir))
    assert code == 0, err
    assert mapsqueeze.info(tmp_path / "MAP.MSQ").n_points == 3000


def _same_file_cases(tmp_path: Path, map_file: Path, tiny_model_dir: Path) -> dict:
    """command line -> the input it must leave untouched, for each way an output can be an input."""
    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, str(tiny_model_dir))
    os.link(map_file, tmp_path / "hard-link.msq")
    (tmp_path / "sym-link.msq").symlink_to(map_file.name)
    return {
        "compress onto a hard link": (["compress", map_file, "-o", tmp_path / "hard-link.msq"], map_file),
        "compress onto a symbolic link": (["compress", map_file, "-o", tmp_path / "sym-link.msq"], map_file),
        "compress --format onto itself": (["compress", msq, "--format", "ply", "-o", tmp_path / "." / "map.msq"], msq),
        "decompress --format onto itself": (["decompress", msq, "--format", "ply", "-o", msq], msq),
        "convert onto itself": (["convert", map_file, tmp_path / "." / "map.ply"], map_file),
        "view onto the original": (["view", msq, "--original", map_file, "-o", map_file], map_file),
    }


@pytest.mark.parametrize("case", ["compress onto a hard link", "compress onto a symbolic link",
                                  "compress --format onto itself", "decompress --format onto itself",
                                  "convert onto itself", "view onto the original"])
def test_an_output_path_that_is_the_input_is_refused_and_the_input_kept(run_cli, map_file, tiny_model_dir, tmp_path,
                                                                         case):
    args, source = _same_file_cases(tmp_path, map_file, tiny_model_dir)[case]
    if args[0] in ("compress", "decompress", "view"):
        args += ["--model", tiny_model_dir]
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in tmp_path.iterdir()}
    code, out, err = run_cli(*map(str, args))
    assert (code, out) == (2, "") and err.startswith("error: ") and err.count("\n") == 1, err
    assert f"is the input file {source}; give another output path" in err
    assert {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in tmp_path.iterdir()} == before
    assert (tmp_path / "sym-link.msq").is_symlink()


def test_the_api_refuses_to_write_its_input(map_file, tiny_model_dir, tmp_path):
    from mapsqueeze.errors import OutputError

    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, str(tiny_model_dir))
    before = map_file.read_bytes(), msq.read_bytes()
    with pytest.raises(OutputError, match="is the input file"):
        mapsqueeze.compress_file(map_file, map_file, str(tiny_model_dir))
    with pytest.raises(OutputError, match="is the input file"):
        mapsqueeze.decompress_file(msq, msq, model=str(tiny_model_dir), format="ply")
    assert (map_file.read_bytes(), msq.read_bytes()) == before


@pytest.mark.parametrize("command", ["compress", "decompress", "convert", "write_points"])
def test_an_output_that_is_a_named_pipe_is_refused_not_replaced(run_cli, map_file, tiny_model_dir, tmp_path, command):
    """An atomic write replaces its target: a named pipe (or a device such as /dev/null, which root could replace)
    would be removed and a regular file left in its place."""
    from mapsqueeze.errors import OutputError

    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, str(tiny_model_dir))
    pipe = tmp_path / ("pipe.msq" if command == "compress" else "pipe.ply")
    os.mkfifo(pipe)
    expected = f"{pipe}: is not a regular file (a device, pipe or socket); give a file name"
    if command == "write_points":
        with pytest.raises(OutputError, match="is not a regular file"):
            write_points(pipe, ground())
    else:
        args = {"compress": ["compress", map_file, "-o", pipe, "--model", tiny_model_dir],
                "decompress": ["decompress", msq, "-o", pipe, "--model", tiny_model_dir],
                "convert": ["convert", map_file, pipe]}[command]
        code, out, err = run_cli(*map(str, args))
        assert (code, out, err) == (2, "", f"error: {expected}\n")
    assert pipe.is_fifo() and sorted(p.name for p in tmp_path.iterdir()) == ["map.msq", "map.ply", pipe.name]


def test_an_output_through_a_symbolic_link_keeps_the_link(run_cli, map_file, tiny_model_dir, tmp_path):
    """The file the link names is replaced (atomically, beside it); the link stays a link."""
    (tmp_path / "store").mkdir()
    (tmp_path / "store" / "v1.msq").write_bytes(b"old")
    link = tmp_path / "latest.msq"
    link.symlink_to(Path("store") / "v1.msq")
    code, _, err = run_cli("compress", str(map_file), "-o", str(link), "--model", str(tiny_model_dir))
    assert code == 0, err
    assert link.is_symlink() and os.readlink(link) == str(Path("store") / "v1.msq")
    assert (tmp_path / "store" / "v1.msq").read_bytes() == mapsqueeze.compress(read_points(map_file),
                                                                                 str(tiny_model_dir))
    assert sorted(p.name for p in (tmp_path / "store").iterdir()) == ["v1.msq"]


PAUSED_IMPORT_CLI = """
import os, pathlib, sys, time
class Pause:  # holds the import of typer (the command line's first heavy import) for a minute
    def find_spec(self, name, path=None, target=None):
        if name == "typer":
            pathlib.Path(os.environ["IMPORT_MARK"]).write_text("importing")
            time.sleep(60)
        return None
sys.meta_path.insert(0, Pause())
from mapsqueeze.cli import main
main()
"""


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_while_the_command_line_loads_gives_one_line(tmp_path, signum):
    """Ctrl-C in the first half second of `mapsqueeze ...`, while typer and the command modules load: the same one
    line and exit code as later, not a traceback of the import."""
    mark = tmp_path / "mark"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "IMPORT_MARK": str(mark)}
    process = subprocess.Popen([sys.executable, "-c", PAUSED_IMPORT_CLI, "models"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, env=env, preexec_fn=_signals_as_in_a_terminal)
    deadline = time.monotonic() + 60
    while not mark.exists() and time.monotonic() < deadline and process.poll() is None:
        time.sleep(0.02)
    assert mark.exists() and process.poll() is None, process.communicate()
    process.send_signal(signum)
    try:
        out, err = process.communicate(timeout=60)
    finally:
        process.kill()
    assert (process.returncode, out, err) == (128 + signum, "", f"error: {SIGNAL_WORDS[signum]}\n")


def test_bbox_and_point_count_errors_are_one_plain_line(run_cli, map_file, tiny_model_dir, tmp_path):
    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, str(tiny_model_dir))
    code, _, err = run_cli("decompress", str(msq), "-o", str(tmp_path / "x.ply"), "--bbox", "10,10,10,0,0,1e3")
    assert code == 2 and err == ("error: bbox must be six finite numbers x0,y0,z0,x1,y1,z1 with x0<=x1, y0<=y1, "
                                 "z0<=z1, got 10,10,10,0,0,1000\n")
    code, _, err = run_cli("decompress", str(msq), "-o", str(tmp_path / "x.ply"), "--bbox",
                           "500005.25,5600005.1234,249,500015,5600004.5,262")  # UTM: every digit shown
    assert code == 2 and err.endswith("got 500005.25,5600005.1234,249,500015,5600004.5,262\n")
    data = msq.read_bytes()
    with pytest.raises(MapsqueezeError, match=r"got \('a', 1, 2, 3, 4, 5\)"):
        mapsqueeze.decompress(data, model=str(tiny_model_dir), bbox=("a", 1, 2, 3, 4, 5))
    for count in (10.5, True, 0):
        with pytest.raises(MapsqueezeError, match=f"point count must be an integer of at least 1, got {count}"):
            mapsqueeze.decompress(data, model=str(tiny_model_dir), n_points=count)
    assert len(mapsqueeze.decompress(data, model=str(tiny_model_dir), n_points=np.int64(7))) == 7


def test_help_shows_every_option_whole_in_80_columns(run_cli, monkeypatch):
    """`mapsqueeze COMMAND --help` in an 80-column terminal or piped: every option's full name (rich's option table
    cut --keep-zero-points and --attribute-voxel to '--keep-zero-poi…' there) and each paragraph wrapped to the
    width, not at the docstring's line breaks."""
    import typer.main

    from mapsqueeze.cli.commands import load_commands

    monkeypatch.setenv("COLUMNS", "80")
    commands = typer.main.get_command(load_commands()).commands
    assert {"compress", "decompress", "convert", "eval", "simulate"} <= set(commands)
    for name, command in commands.items():
        code, out, _ = run_cli(name, "--help")
        assert code == 0 and max(map(len, out.splitlines())) <= 80, name
        for param in (param for param in command.params if param.param_type_name == "option"):
            for option in param.opts + param.secondary_opts:
                assert any(f"{option}{after}" in out for after in " ,\n"), (name, option)
    _, out, _ = run_cli("convert", "--help")
    assert "keeping every attribute and the LAS header's metadata\n  the output format can hold;" in out



def test_no_command_prints_the_help_as_help_does(run_cli):
    """`mapsqueeze` alone prints what `mapsqueeze --help` does (click 8.2 and typer 0.27 raise a usage error for an
    empty command line, which printed the whole help squeezed into one 'error: Usage: ...' line, exit code 2)."""
    code, out, err = run_cli()
    assert (code, err) == (0, "") and out == run_cli("--help")[1]
    assert out.startswith("Usage: ") and "\n  compress " in out


def test_printed_file_names_keep_their_brackets(run_cli, map_file, tiny_model_dir, tmp_path):
    """File names are printed as they are: rich's markup read '[bold]' in one as a style (left out of the line) and
    '[/b]' as a closing tag it refused with a traceback after the file was written."""
    (tmp_path / "a[").mkdir()
    msq, ply, las = tmp_path / "a[" / "b].msq", tmp_path / "[bold]back.ply", tmp_path / "a[" / "[red]c].las"
    code, out, err = run_cli("compress", str(map_file), "-o", str(msq), "--model", str(tiny_model_dir))
    assert code == 0 and out.startswith(f"wrote {msq}: ") and "[/b]" in out, err
    code, out, err = run_cli("decompress", str(msq), "-o", str(ply), "--model", str(tiny_model_dir))
    assert code == 0 and out.startswith("wrote ") and out.endswith(f" points to {ply}\n"), err
    code, out, err = run_cli("convert", str(ply), str(las))
    assert code == 0 and out.endswith(f" points to {las}\n"), err


@pytest.mark.parametrize("stderr", [False, True])
def test_a_printed_line_on_a_terminal_is_the_text_as_it_is(monkeypatch, stderr):
    """On a terminal too (rich), a printed line is its text whole: a file name's ':smile:' stays (no emoji code),
    and a line longer than the terminal is not broken into several (copied from the terminal, a path stays whole)."""
    import io
    import re

    from mapsqueeze.cli.app import print_line

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr" if stderr else "stdout", terminal)
    monkeypatch.setenv("COLUMNS", "80")
    text = "wrote /maps/:smile:/[bold]" + "long_folder_name/" * 8 + "map.msq: 1,234 points"
    print_line(text, stderr=stderr)
    assert re.sub(r"\x1b\[[0-9;]*m", "", terminal.getvalue()) == text + "\n"


def test_a_file_name_the_output_encoding_cannot_hold_is_printed_escaped(tmp_path, monkeypatch):
    """A name stdout's encoding cannot hold (an ASCII or cp1252 pipe, a Chinese file name) is printed with
    backslash escapes: the command that wrote the file succeeds, where it ended in a UnicodeEncodeError traceback."""
    import io

    source = map_file_of(tmp_path / "in.ply", ground(100))
    output = tmp_path / "地图.pcd"
    stdout = io.TextIOWrapper(io.BytesIO(), encoding="ascii", write_through=True)
    monkeypatch.setattr(sys, "stdout", stdout)
    monkeypatch.setattr(sys, "argv", ["mapsqueeze", "convert", str(source), str(output)])
    from mapsqueeze.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main()
    assert exit_info.value.code == 0 and output.exists()
    assert stdout.buffer.getvalue().decode("ascii") == f"wrote 100 points to {tmp_path}/\\u5730\\u56fe.pcd\n"


def test_info_rows_the_output_encoding_cannot_hold_are_printed_escaped(monkeypatch):
    """`info`'s rows (a custom model's name is any UTF-8 text) on an ASCII pipe: escaped, as print_line's lines."""
    import io

    from mapsqueeze.cli.app import print_rows

    stdout = io.TextIOWrapper(io.BytesIO(), encoding="ascii", write_through=True)
    monkeypatch.setattr(sys, "stdout", stdout)
    print_rows([("model", "custom, named '模型'"), ("points", "1,000")])
    assert stdout.buffer.getvalue().decode("ascii") == "model   custom, named '\\u6a21\\u578b'\npoints  1,000\n"


def test_info_rows_on_a_terminal_are_their_text(monkeypatch):
    """`info`'s table on a terminal (rich) shows its values as they are: a custom model's name '[/b]x' is no
    closing markup tag (rich refused it with a traceback) and '[bold]' no style."""
    import io
    import re

    from mapsqueeze.cli.app import print_rows

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    terminal = Terminal()
    monkeypatch.setattr(sys, "stdout", terminal)
    print_rows([("model", "custom, named '[/b]x[bold]y'"), ("points", "1,000")])
    lines = [line.rstrip() for line in re.sub(r"\x1b\[[0-9;]*m", "", terminal.getvalue()).splitlines()]
    assert lines == [" model   custom, named '[/b]x[bold]y'", " points  1,000"]


def test_a_count_of_one_is_singular(run_cli, tiny_model_dir, tmp_path):
    source = map_file_of(tmp_path / "one.ply", ground(1))
    code, out, _ = run_cli("compress", str(source), "-o", str(tmp_path / "one.msq"), "--model", str(tiny_model_dir))
    assert code == 0 and out.startswith(f"wrote {tmp_path / 'one.msq'}: 1 point in 1 tile (1 raw), ")
    code, out, _ = run_cli("decompress", str(tmp_path / "one.msq"), "-o", str(tmp_path / "back.ply"))
    assert (code, out) == (0, f"wrote 1 point to {tmp_path / 'back.ply'}\n")
    code, out, _ = run_cli("convert", str(source), str(tmp_path / "one.las"))
    assert (code, out) == (0, f"wrote 1 point to {tmp_path / 'one.las'}\n")


def test_compress_says_when_no_coding_fits_the_bpp_budget(run_cli, map_file, tiny_model_dir, tmp_path):
    """A --bpp budget no choice of codings meets (here below the header's own bits) is one warning line naming the
    rate written; a budget that is met, none."""
    code, out, err = run_cli("compress", str(map_file), "-o", str(tmp_path / "tight.msq"), "--model",
                             str(tiny_model_dir), "--bpp", "0.001")
    rate = mapsqueeze.info(tmp_path / "tight.msq").bits_per_point
    assert code == 0 and out.startswith("wrote") and rate > 0.001
    assert err == (f"warning: {tmp_path / 'tight.msq'} takes {rate:.4f} bits per point, more than --bpp 0.001: no "
                   "choice of codings fits, so the smallest found was written\n")
    code, _, err = run_cli("compress", str(map_file), "-o", str(tmp_path / "loose.msq"), "--model",
                           str(tiny_model_dir), "--bpp", "100")
    assert code == 0 and err == ""


@pytest.mark.parametrize("command", ["decompress-output", "eval", "view-original", "convert"])
def test_a_msq_where_a_point_cloud_is_expected_is_named_as_such(run_cli, map_file, tiny_model_dir, tmp_path,
                                                                 command):
    """A .msq given as a point cloud (input or output) is one error line saying what a .msq is, not advice to set a
    format that eval and view have no option for."""
    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, model=tiny_model_dir)
    args = {"decompress-output": ["decompress", msq, "-o", tmp_path / "out.msq", "--model", tiny_model_dir],
            "eval": ["eval", msq, map_file],
            "view-original": ["view", msq, "--original", msq, "-o", tmp_path / "v.html", "--model", tiny_model_dir],
            "convert": ["convert", msq, tmp_path / "out.ply"]}[command]
    code, out, err = run_cli(*map(str, args))
    assert code == 2 and out == "" and err.count("\n") == 1
    assert err.startswith("error: ") and "is a mapsqueeze container, not a point cloud" in err, err
    assert "set the format" not in err


def test_eval_of_flat_clouds_a_millimetre_apart_gives_no_overlap_warning(run_cli, tmp_path):
    """A flat ground truth (z = 50 exactly) and a decoding a millimetre above it have disjoint boxes but overlap:
    no warning (before: "the clouds do not overlap")."""
    plane = np.column_stack([np.random.default_rng(2).uniform(0, 20, (500, 2)), np.full(500, 50.0)]) + UTM
    write_points(tmp_path / "gt.ply", plane)
    write_points(tmp_path / "rec.ply", plane + [0.0, 0.0, 0.001])
    code, out, err = run_cli("eval", str(tmp_path / "gt.ply"), str(tmp_path / "rec.ply"), "--json")
    assert code == 0 and err == "" and json.loads(out)["d_e"] == pytest.approx(0.001, abs=1e-4)


def test_eval_of_a_ground_truth_without_extent_gives_no_overlap_warning(run_cli, tmp_path):
    """Every ground-truth point in one place: D_e of a tenth of a millimetre is no sign of another frame."""
    write_points(tmp_path / "gt.ply", np.tile([[1.0, 2.0, 3.0]], (50, 1)))
    write_points(tmp_path / "rec.ply", np.tile([[1.0, 2.0, 3.0001], [1.0, 2.0, 2.9999]], (35, 1)))
    code, out, err = run_cli("eval", str(tmp_path / "gt.ply"), str(tmp_path / "rec.ply"), "--json")
    assert code == 0 and err == "" and json.loads(out)["d_e"] > 0


@pytest.mark.parametrize("output", ["out.ply", "out.las"])
def test_a_density_that_gives_no_points_is_named_not_a_bbox(run_cli, map_file, tiny_model_dir, tmp_path, output):
    """decompress --density so low that every tile decodes to no point says so; the message of an empty --bbox
    stays for a bbox."""
    msq = tmp_path / "map.msq"
    mapsqueeze.compress_file(map_file, msq, model=tiny_model_dir)
    code, out, err = run_cli("decompress", str(msq), "-o", str(tmp_path / output), "--model", str(tiny_model_dir),
                             "--density", "1e-9")
    assert (code, out) == (2, "") and err.count("\n") == 1 and "bbox" not in err and "a density of 1e-09 points per m^3" in err, err
    far = ",".join(str(v) for v in [0, 0, 0, 1, 1, 1])
    code, _, err = run_cli("decompress", str(msq), "-o", str(tmp_path / output), "--model", str(tiny_model_dir),
                           "--bbox", far)
    assert code == 2 and "the bbox holds no decoded points" in err
    whole = ",".join(str(v) for v in [-1e6, -1e6, -1e6, 1e6, 1e6, 1e6])  # every tile, none at that density
    code, _, err = run_cli("decompress", str(msq), "-o", str(tmp_path / output), "--model", str(tiny_model_dir),
                           "--bbox", whole, "--density", "1e-9")
    assert code == 2 and "the bbox holds no decoded points at a density of 1e-09 points per m^3" in err, err
    assert not (tmp_path / output).exists()
