"""Atomic file output: write a temporary file beside the target, then `os.replace` it into place.

A reader never sees a half-written file, and a failed write leaves the target as it was (absent or the old
version) with no temporary file behind. OSError (missing directory, no permission, disk full) propagates.
"""

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def _create_temp_file(target: Path) -> Path:
    """Create an empty, uniquely named file in the target's directory (mode 0o666 minus the umask)."""
    while True:
        temp = target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")
        try:
            os.close(os.open(temp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
        except FileExistsError:
            continue
        return temp


def _fsync(path: Path) -> None:
    with open(path, "rb") as stream:
        os.fsync(stream.fileno())


@contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in `path`'s directory; on normal exit, move it onto `path` atomically.

    The body writes the complete file to the yielded path (by path: libraries may reopen it). If the body
    raises, the temporary file is removed and the exception propagates; `path` is left untouched.
    """
    target = Path(path)
    temp = _create_temp_file(target)
    try:
        yield temp
        _fsync(temp)
        os.replace(temp, target)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` atomically (see `atomic_output`)."""
    with atomic_output(path) as temp:
        temp.write_bytes(data)
