"""mapsqueeze against MPEG G-PCC trisoup, side by side on one multi-million-point real-data map, and scaling.

    nice .venv/bin/python benchmarks/bench_vs_gpcc.py --copies 5 -o results/vs_gpcc        # side by side
    nice .venv/bin/python benchmarks/bench_vs_gpcc.py --scaling 1 10 -o results/scaling     # million points

The map is copies x copies mirrored copies of the real KITTI submap (benchmarks/bench_codec.py `build_map`) written
as a binary PLY. mapsqueeze runs as the CLI does (`mapsqueeze compress` / `decompress`, default settings: e1, q,
one worker per core); G-PCC is `tmc3` trisoup (10 cm cells, nodes of 2^3 cells, --partitionMethod=2, the options of
`mapsqueeze.baselines.gpcc`) on the same points, quantised to 1 mm as the wrapper does. Every command runs in a
fresh process tree pinned to the first CORES cores, the four commands in turn --repeats times (so that a drift of
the machine's speed reaches them alike); each figure is the median of a command's runs (`wall_ratios`: the median
over the rounds of mapsqueeze's wall time over G-PCC's): wall seconds, CPU seconds of the whole process tree and
its peak resident memory (RSS, the sum over the tree's processes sampled every 50 ms, which counts the pages
processes share, e.g. torch's libraries, once per process). PSS, which splits shared pages among the processes
sharing them, comes from one more run of each command: reading it parses every process's /proc/PID/smaps (~7 ms
for mapsqueeze's), which at every sample took a tenth of a core from the command measured and so lengthened the
multi-threaded one (mapsqueeze's compress: +0.1-0.3 s wall) more than G-PCC's single thread; the timed runs read
RSS alone (/proc/PID/statm, ~10 us). The side-by-side run also checks that `--workers 1`, the default workers and
`--dask-scheduler local` give byte-identical .msq files and decoded clouds. The machine is shared: the load
average is printed with every row; CPU seconds are the steadier comparison. mapsqueeze's sources are compiled to
bytecode first, as installing the package does (`compile_package`).
"""

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_codec import build_map  # noqa: E402

TMC3 = Path(__file__).resolve().parents[2] / "shared" / "tools" / "tmc3" / "tmc3"
CORES = 2
TRISOUP = {"mode": "trisoup", "cell_m": 0.1, "node_log2": 3}
SAMPLE_S = 0.05


def measure(command: list[str], cores: int = CORES, proportional: bool = False) -> dict:
    """Run a command pinned to `cores` cores; wall s, CPU s and peak RSS (MB) of its process tree, and with
    `proportional` its peak PSS (MB; sampling it slows the command, see the module's docstring).

    CPU: the larger of /usr/bin/time's user + system seconds (exact for the command and the descendants it waits
    for) and the sum over every process of the tree sampled every SAMPLE_S (which also sees descendants that others
    reap). Memory: the larger of /usr/bin/time's maximum RSS and the peak of the sampled sum over the tree."""
    pinned = sorted(os.sched_getaffinity(0))[:cores]
    report = tempfile.NamedTemporaryFile(suffix=".time", delete=False)
    report.close()
    start = time.perf_counter()
    root = psutil.Popen(["/usr/bin/time", "-o", report.name, "-f", "%U %S %M", *command], stdout=subprocess.DEVNULL,
                        stderr=subprocess.PIPE, preexec_fn=lambda: os.sched_setaffinity(0, pinned))
    cpu: dict[int, float] = {}
    peak = peak_proportional = 0
    while root.poll() is None:
        rss = pss = 0
        for process in [root, *_children(root)]:
            try:
                times = process.cpu_times()
                cpu[process.pid] = times.user + times.system
                if proportional:
                    memory = process.memory_full_info()
                    rss, pss = rss + memory.rss, pss + memory.pss
                else:
                    rss += process.memory_info().rss
            except psutil.Error:
                pass
        peak, peak_proportional = max(peak, rss), max(peak_proportional, pss)
        time.sleep(SAMPLE_S)
    wall = time.perf_counter() - start
    if root.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed: {root.stderr.read().decode()[-2000:]}")
    user_s, system_s, max_rss_kb = Path(report.name).read_text().split()[-3:]
    os.unlink(report.name)
    result = {"wall_s": wall, "cpu_s": max(float(user_s) + float(system_s), sum(cpu.values())),
              "peak_rss_mb": max(peak / 2**20, int(max_rss_kb) / 1024)}
    return {**result, "peak_pss_mb": peak_proportional / 2**20} if proportional else result


def _children(process: psutil.Process) -> list:
    try:
        return process.children(recursive=True)
    except psutil.Error:
        return []


def median_of(runs: list[dict]) -> dict:
    return {key: statistics.median(run[key] for run in runs) for key in runs[0]}


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def mapsqueeze_commands(source: Path, msq: Path, decoded: Path, *options: str) -> tuple[list[str], list[str]]:
    cli = [sys.executable, "-m", "mapsqueeze"]
    return ([*cli, "compress", str(source), "-o", str(msq), *options],
            [*cli, "decompress", str(msq), "-o", str(decoded), *options])


def gpcc_commands(points: np.ndarray, folder: Path) -> tuple[list[str], list[str], Path]:
    """tmc3 encoder and decoder commands for the trisoup setting, with the quantised input PLY written."""
    from mapsqueeze.baselines.gpcc import GRID_STEP_M, GpccCodec, _write_grid_ply

    codec = GpccCodec(str(TMC3))
    grid = np.rint((points - points.min(axis=0)) / GRID_STEP_M)
    source, stream, decoded = folder / "gpcc_in.ply", folder / "gpcc.bin", folder / "gpcc_out.ply"
    _write_grid_ply(source, grid)
    encode = [str(TMC3), *codec.encoder_arguments(TRISOUP, source, stream), "--partitionMethod=2"]
    decode = [str(TMC3), *codec.decoder_arguments(stream, decoded)]
    return encode, decode, stream


def compile_package() -> None:
    """Compile mapsqueeze's sources to bytecode, as installing a wheel does: an editable install run under
    PYTHONDONTWRITEBYTECODE=1 compiles every module afresh at each start of the CLI (~0.1-0.15 CPU-s, BENCHMARKS.md
    "Throughput"). The bytecode goes to the package's __pycache__ folders (ignored by git); Python checks it against
    each source's modification time, so a later edit is never run stale."""
    import compileall

    import mapsqueeze

    compileall.compile_dir(Path(mapsqueeze.__file__).parent, quiet=1)


def load() -> str:
    return "{:.1f} / {:.1f} / {:.1f}".format(*os.getloadavg())


def side_by_side(copies: int, repeats: int, out: Path) -> dict:
    from mapsqueeze.io import write_points

    points = build_map(copies, (0.0, 0.0))
    results = {"points": len(points), "copies": copies, "cores": CORES, "repeats": repeats}
    with tempfile.TemporaryDirectory(prefix="bench-vs-gpcc-") as temp:
        folder = Path(temp)
        source = folder / "map.ply"
        write_points(source, points)
        compress, decompress = mapsqueeze_commands(source, folder / "map.msq", folder / "decoded.ply")
        gpcc_encode, gpcc_decode, stream = gpcc_commands(points, folder)
        commands = {"mapsqueeze compress": compress, "mapsqueeze decompress": decompress,
                    "G-PCC trisoup encode": gpcc_encode, "G-PCC trisoup decode": gpcc_decode}
        runs = {name: [] for name in commands}
        for _ in range(repeats):  # round-robin, so that a drift of the machine's speed reaches every command alike
            for name, command in commands.items():
                runs[name].append({**measure(command), "load_1min": os.getloadavg()[0]})
                print(f"{name}: {runs[name][-1]} (load {load()})", flush=True)
        rows = {}
        for name, command in commands.items():
            memory = measure(command, proportional=True)
            print(f"{name}, memory run: {memory} (load {load()})", flush=True)
            rows[name] = {**median_of(runs[name]), "peak_pss_mb": memory["peak_pss_mb"]}
        results["rows"] = rows
        results["wall_ratios"] = {  # per round, mapsqueeze's run over G-PCC's of the same round: the median
            f"{ours} / {theirs}": statistics.median(a["wall_s"] / b["wall_s"] for a, b in zip(runs[ours], runs[theirs]))
            for ours, theirs in (("mapsqueeze compress", "G-PCC trisoup encode"),
                                 ("mapsqueeze decompress", "G-PCC trisoup decode"))}
        results["bytes"] = {"mapsqueeze": (folder / "map.msq").stat().st_size, "G-PCC trisoup": stream.stat().st_size}
        results["identity"] = identical_bytes(source, folder)
    return results


def identical_bytes(source: Path, folder: Path) -> dict:
    """SHA-256 of the .msq and the decoded PLY for --workers 1, the default workers and a local Dask cluster."""
    digests = {}
    for label, options in (("--workers 1", ["--workers", "1"]), ("default workers", []),
                           ("--dask-scheduler local", ["--dask-scheduler", "local"])):
        msq, decoded = folder / f"identity_{len(digests)}.msq", folder / f"identity_{len(digests)}.ply"
        for command in mapsqueeze_commands(source, msq, decoded, *options):
            subprocess.run(command, check=True, capture_output=True)
        digests[label] = {"msq": sha256(msq), "decoded": sha256(decoded)}
        print(f"{label}: {digests[label]}", flush=True)
    return digests


def scaling(millions: list[float], out: Path) -> dict:
    """Compress and decompress maps of about each size (KITTI copies on a square grid), one run each."""
    from mapsqueeze.io import write_points

    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-scaling-") as temp:
        folder = Path(temp)
        for size in millions:
            copies = max(1, int(round(np.sqrt(size * 1e6 / 101_924))))  # points of one KITTI submap
            points = build_map(copies, (0.0, 0.0))
            source = folder / "map.ply"
            write_points(source, points)
            row = {"points": len(points), "copies": copies}
            del points
            compress, decompress = mapsqueeze_commands(source, folder / "map.msq", folder / "decoded.ply")
            for name, command in (("compress", compress), ("decompress", decompress)):
                row[name] = {**measure(command), "load_1min": os.getloadavg()[0]}
            print(json.dumps(row), flush=True)
            rows.append(row)
    plot_scaling(rows, out / "scaling.png")
    return {"rows": rows, "cores": CORES}


def plot_scaling(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = [row["points"] / 1e6 for row in rows]
    figure, (time_axis, memory_axis) = plt.subplots(1, 2, figsize=(9, 3.6))
    for stage, marker in (("compress", "o"), ("decompress", "s")):
        time_axis.plot(points, [row[stage]["wall_s"] for row in rows], marker=marker, label=f"{stage} wall")
        time_axis.plot(points, [row[stage]["cpu_s"] for row in rows], marker=marker, linestyle="--",
                       label=f"{stage} CPU")
        memory_axis.plot(points, [row[stage]["peak_rss_mb"] for row in rows], marker=marker, label=stage)
    time_axis.set(xlabel="map points (millions)", ylabel="seconds", title=f"time ({CORES} cores)")
    memory_axis.set(xlabel="map points (millions)", ylabel="MB", title="peak resident memory (process tree)",
                    ylim=(0, None))
    for axis in (time_axis, memory_axis):
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=5, help="side by side: a copies x copies map (5: 2.5M points)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scaling", type=float, nargs="+", metavar="MILLIONS",
                        help="instead: one compress and decompress per map size (millions of points)")
    parser.add_argument("-o", "--out", type=Path, required=True, help="folder for results.json (and scaling.png)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).parent).stdout.strip()
    header = {"date": time.strftime("%Y-%m-%d"), "commit": commit, "load_at_start": load(),
              "machine": f"{os.cpu_count()} CPUs, {CORES} used"}
    print(header, flush=True)
    compile_package()
    results = scaling(args.scaling, args.out) if args.scaling else side_by_side(args.copies, args.repeats, args.out)
    (args.out / "results.json").write_text(json.dumps({**header, **results, "load_at_end": load()}, indent=2))
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
