"""Start-up of the command line: loading it imports neither torch nor scipy nor trimesh (~0.5 CPU-s instead of
~1.5; `mapsqueeze --help` and `mapsqueeze info` stay under a CPU-second)."""

import subprocess
import sys

HEAVY = ("torch", "scipy", "trimesh", "numba", "matplotlib")


def test_loading_the_command_line_imports_no_heavy_library():
    probe = "import sys, mapsqueeze.cli; print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))"
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.split()
    assert not set(HEAVY) & set(loaded)
