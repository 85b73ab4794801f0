"""Compiled kernels whose machine code is cached on disk wherever the user can write.

numba caches beside the package (`__pycache__`), in NUMBA_CACHE_DIR or in ~/.cache/numba, and refuses to
decorate ("cannot cache function") when none is writable, e.g. an installed package run by a user whose home is
read-only. `compiled` then caches in a per-user folder of the temporary directory, or compiles at each start.
"""

from __future__ import annotations

import os
import tempfile

import numba


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
