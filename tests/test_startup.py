"""Start-up and end of the command line: loading it imports neither torch nor scipy nor trimesh (~0.5 CPU-s instead
of ~1.5; `mapsqueeze --help` and `mapsqueeze info` stay under a CPU-second), a command loads only its own module,
and neither typer's pydantic coercion nor rich where its output is piped; the program ends without the interpreter's
teardown once its command is done (`cli.entry`)."""

import subprocess
import sys

HEAVY = ("torch", "scipy", "trimesh", "numba", "matplotlib")


def test_loading_the_command_line_imports_no_heavy_library():
    probe = ("import sys\nfrom mapsqueeze.cli.commands import load_commands\nload_commands()\n"
             "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))")
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.split()
    assert "mapsqueeze" in loaded and not set(HEAVY) & set(loaded)


def test_every_command_is_loaded_by_its_name_alone():
    """COMMAND_MODULES names the module registering each command, and every command is in it (a missing one would
    only be found through the full load of a misspelt name)."""
    probe = ("import sys, typer.main\nfrom mapsqueeze.cli.commands import COMMAND_MODULES, load_commands\n"
             "for name, module in COMMAND_MODULES.items():\n"
             "    commands = typer.main.get_command(load_commands([name, '--help'])).commands\n"
             "    assert commands[name].callback.__module__ == f'mapsqueeze.cli.{module}', name\n"
             "every = typer.main.get_command(load_commands()).commands\n"
             "print(' '.join(sorted(every)), '|', ' '.join(sorted(COMMAND_MODULES)))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    every, named = result.stdout.split("|")
    assert every.split() == named.split() and "compress" in named.split()


_PIPED_COMPRESS_PROBE = """
import sys
import numpy as np
from mapsqueeze.cli import main
from mapsqueeze.io import write_points
rng = np.random.default_rng(0)
write_points(sys.argv[1], np.c_[rng.random((3000, 2)) * 30, rng.normal(1, 0.05, 3000)])
sys.argv = ["mapsqueeze", "compress", sys.argv[1], "-o", sys.argv[2], "--model", "e0", "--workers", "1",
            "--device", "cpu"]
try:
    main()
except SystemExit as exit:
    assert not exit.code, exit.code
print(" ".join(sorted(sys.modules)))
"""


def test_the_typer_range_in_pyproject_is_the_versions_the_command_line_runs_on():
    """`cli.commands.run` turns usage errors into one line by catching `typer.TyperException`, which typer has from
    0.27.2 on (with 0.12 to 0.27.1 an unknown option was an AttributeError traceback); typer 0.29 imports pydantic
    (the test below). pyproject's range must be that window, and hold the typer installed."""
    import re
    from importlib.metadata import version
    from pathlib import Path

    import typer
    from packaging.requirements import Requirement

    pyproject = (Path(__file__).parents[1] / "pyproject.toml").read_text()
    typer_requirement = Requirement(re.search(r'"(typer[<>=!~ ].*?)"', pyproject).group(1))
    allowed = typer_requirement.specifier
    assert "0.27.1" not in allowed and "0.27.2" in allowed and "0.29.0" not in allowed, allowed
    assert version("typer") in allowed and issubclass(typer.TyperException, Exception)


def test_a_piped_compress_loads_neither_pydantic_nor_rich_nor_other_commands(tmp_path):
    """`mapsqueeze compress --device cpu` with its output piped (as a script runs it): no torch, only the compress
    command's modules, no pydantic (typer >= 0.29 coerces every parameter through it: ~0.1 CPU-s), no rich (~0.05 CPU-s: its lines are
    plain text), and none of the simulator, the viewer or the data tools' modules the other commands use."""
    result = subprocess.run([sys.executable, "-c", _PIPED_COMPRESS_PROBE, str(tmp_path / "map.ply"),
                             str(tmp_path / "map.msq")], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    *printed, loaded = result.stdout.splitlines()
    assert printed[-1].startswith(f"wrote {tmp_path / 'map.msq'}: 3,000 points in 1 tile")
    loaded = set(loaded.split())
    assert "mapsqueeze.cli.codec_cmds" in loaded and (tmp_path / "map.msq").stat().st_size
    assert not {name for name in loaded if name.split(".")[0] in ("pydantic", "rich", "torch")}
    assert not {"mapsqueeze.cli.sim_cmds", "mapsqueeze.cli.view_cmds", "mapsqueeze.cli.data_cmds",
                "mapsqueeze.cli.eval_cmds", "mapsqueeze.data", "mapsqueeze.view"} & loaded


def test_info_imports_no_heavy_library(tmp_path):
    import numpy as np

    import mapsqueeze

    rng = np.random.default_rng(0)
    points = np.c_[rng.random((3000, 2)) * 30, rng.normal(1, 0.05, 3000)]
    (tmp_path / "map.msq").write_bytes(mapsqueeze.compress(points, model="e0", workers=1))
    probe = ("import sys\nfrom mapsqueeze.cli import main\nsys.argv = ['mapsqueeze', 'info', sys.argv[1]]\n"
             "try:\n    main()\nexcept SystemExit as exit:\n    assert not exit.code, exit.code\n"
             "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))")
    result = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "map.msq")], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    loaded = result.stdout.split()
    assert "mapsqueeze" in loaded and not set(HEAVY) & set(loaded)


def test_compress_loads_no_scipy_linalg_and_kernels_with_a_blas_still_compile():
    probe = ("import sys\nimport numpy as np\nimport mapsqueeze\nrng = np.random.default_rng(0)\n"
             "import mapsqueeze.codec.compress\nmapsqueeze.codec.compress.NUMPY_KERNEL_POINTS = 0\n"  # numba's kernels
             "points = np.c_[rng.random((3000, 2)) * 30, rng.normal(1, 0.05, 3000)]\n"
             "assert len(mapsqueeze.compress(points, model='e0', workers=1)) > 0\n"
             "print('scipy.linalg' in sys.modules)\n"
             "import numba\n"
             "print(numba.njit(lambda a, b: np.dot(a, b))(np.ones(3), np.full(3, 2.0)), 'scipy.linalg' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["False", "6.0", "True"]


def test_holding_scipy_linalg_back_from_numba_leaves_other_threads_importing_it():
    """The compiled kernels' module is imported by a thread while compress reads the map: scipy.linalg is held back
    from that thread's import of numba's array functions only, not from what the other threads import meanwhile."""
    probe = (
        "import sys, threading\n"
        "started, done = threading.Event(), threading.Event()\n"
        "class Pause:\n"  # stops the loading thread as it imports numba's array functions
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'numba.np.arraymath':\n"
        "            started.set()\n"
        "            done.wait(60)\n"
        "        return None\n"
        "sys.meta_path.insert(0, Pause())\n"
        "loading = threading.Thread(target=__import__, args=('mapsqueeze.geometry.jit',))\n"
        "loading.start()\n"
        "assert started.wait(60)\n"
        "try:\n"
        "    import scipy.linalg\n"
        "finally:\n"
        "    done.set()\n"
        "loading.join()\n"
        "import numba.np.arraymath\n"
        "print(scipy.linalg.__name__, numba.np.arraymath._HAVE_BLAS)")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["scipy.linalg", "True"]


def test_compress_loads_the_kernels_in_a_thread_once():
    """A thread imports the encoder's kernel modules (not scipy.linalg) while compress reads the map: not for a Dask
    cluster, nor once they are loaded."""
    probe = ("import sys\nimport mapsqueeze.codec.compress as compress\ncompress.default_workers = lambda: 2\n"
             "assert compress._load_kernels_meanwhile('tcp://127.0.0.1:8786') is None\n"
             "assert not set(compress.ENCODER_KERNEL_MODULES) & set(sys.modules)\n"
             "compress._load_kernels_meanwhile(None).join()\n"
             "assert set(compress.ENCODER_KERNEL_MODULES) <= set(sys.modules)\n"
             "print(compress._load_kernels_meanwhile(None), 'scipy.linalg' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["None", "False"]


_ENDING_PROBE = """
import atexit, sys, threading, time

class Late:
    def __del__(self):
        print("teardown ran", flush=True)

late = Late()
atexit.register(lambda: print("atexit ran"))
how, thread = sys.argv[1:3]
if thread == "thread":
    threading.Thread(target=lambda: (time.sleep(0.5), print("thread done", flush=True))).start()
sys.argv = ["mapsqueeze", *sys.argv[3:]]
from mapsqueeze.cli import entry, main
entry() if how == "entry" else main()
"""


def _ending(how: str, thread: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _ENDING_PROBE, how, thread, *args], capture_output=True, text=True)


def test_the_program_ends_without_the_interpreter_teardown_after_its_output_and_atexit_handlers():
    """`entry` (the `mapsqueeze` script and `python -m mapsqueeze`) flushes the piped output, runs the atexit
    handlers and ends at once; `main` (for callers that keep their process) leaves the ending to the interpreter,
    whose teardown finalises the objects left (the probe's control)."""
    ended = _ending("entry", "none", "models")
    assert ended.returncode == 0, ended.stderr
    assert "e1" in ended.stdout and ended.stdout.rstrip().endswith("atexit ran")
    assert "teardown ran" not in ended.stdout
    usual = _ending("main", "none", "models")
    assert usual.returncode == 0 and "teardown ran" in usual.stdout


def test_the_program_keeps_its_exit_code_and_error_line_and_waits_for_running_threads(tmp_path):
    failed = _ending("entry", "none", "compress", str(tmp_path / "missing.ply"), "-o", str(tmp_path / "m.msq"))
    assert failed.returncode == 2
    assert failed.stderr.count("error:") == 1 and "teardown ran" not in failed.stdout
    assert not (tmp_path / "m.msq").exists()
    waited = _ending("entry", "thread", "models")  # a thread still running: the usual exit, which joins it
    assert waited.returncode == 0 and "thread done" in waited.stdout
    script = subprocess.run([sys.executable, "-m", "mapsqueeze", "models"], capture_output=True, text=True)
    assert script.returncode == 0 and "e1" in script.stdout


def test_output_a_full_device_refuses_is_one_error_line_and_a_closed_stdout_is_no_error(tmp_path):
    """`> /dev/full`: one `error:` line and exit code 2, not a traceback; started with stdout closed (`>&-`), the
    command runs and writes its files."""
    import os
    from pathlib import Path

    if Path("/dev/full").exists():
        with open("/dev/full", "w") as full:
            result = subprocess.run([sys.executable, "-m", "mapsqueeze", "models"], stdout=full, stderr=subprocess.PIPE,
                                    text=True)
        assert result.returncode == 2
        assert result.stderr.splitlines() == ["error: cannot write the output (No space left on device)"]
    result = subprocess.run([sys.executable, "-m", "mapsqueeze", "convert", str(_small_map(tmp_path)),
                             str(tmp_path / "out.pcd")], stdin=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: os.close(1))
    assert result.returncode == 0 and "Traceback" not in result.stderr and (tmp_path / "out.pcd").stat().st_size


def _small_map(folder):
    import numpy as np

    from mapsqueeze.io import write_points

    path = folder / "map.ply"
    write_points(path, np.random.default_rng(0).random((200, 3)) * 10)
    return path
