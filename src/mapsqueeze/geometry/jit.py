"""Compiled kernels whose machine code is cached on disk wherever the user can write.

numba caches beside the package (`__pycache__`), in NUMBA_CACHE_DIR or in ~/.cache/numba, and refuses to
decorate ("cannot cache function") when none is writable, e.g. an installed package run by a user whose home is
read-only. `compiled` then caches in a per-user folder of the temporary directory, or compiles at each start.

numba's array functions (`numba.np.arraymath`, loaded with its other registries before the first kernel runs)
import scipy.linalg to learn whether a BLAS is there (~27 MB resident, 0.17-0.22 CPU-s); none of these kernels
calls one, so that module is loaded here with scipy.linalg held back (`_load_array_functions`).
"""

from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
import threading

import numba


class _HoldBack:
    """A finder that refuses scipy.linalg to the thread that made it and to no other (`_load_array_functions`
    runs in a thread while compress reads the map, `codec.compress._load_kernels_meanwhile`)."""

    def __init__(self):
        self.thread = threading.get_ident()

    def find_spec(self, name, path=None, target=None):
        if name == "scipy.linalg" and threading.get_ident() == self.thread:
            raise ModuleNotFoundError("scipy.linalg is held back while numba's array functions load", name=name)
        return None


def _load_array_functions() -> None:
    """Import `numba.np.arraymath` with scipy.linalg held back from this thread (`_HoldBack`), then set its
    import-time BLAS probe to whether scipy is installed (what numba would have found): a kernel that needs a BLAS
    (np.dot, np.linalg, np.correlate of floats) still imports scipy.linalg, as it is compiled (numba's
    `ensure_blas`). Nothing changes once either module is loaded."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    finder = _HoldBack()
    sys.meta_path.insert(0, finder)
    try:
        import numba.np.arraymath
    finally:
        sys.meta_path.remove(finder)
    numba.np.arraymath._HAVE_BLAS = importlib.util.find_spec("scipy") is not None


_load_array_functions()


def fallback_cache_dir() -> str:
    """The per-user numba cache folder in the temporary directory, used when no usual location is writable."""
    return os.path.join(tempfile.gettempdir(), f"mapsqueeze-numba-cache-{os.getuid()}")


def compiled(function):
    """`numba.njit(cache=True, nogil=True)` that never fails for want of a writable cache folder."""
    try:
        return numba.njit(cache=True, nogil=True)(function)
    except RuntimeError:  # no writable cache location
        pass
    configured = numba.config.CACHE_DIR
    numba.config.CACHE_DIR = fallback_cache_dir()
    try:
        return numba.njit(cache=True, nogil=True)(function)
    except RuntimeError:
        return numba.njit(nogil=True)(function)
    finally:
        numba.config.CACHE_DIR = configured
