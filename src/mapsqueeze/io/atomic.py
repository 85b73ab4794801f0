"""Atomic file output: write a temporary file beside the target, then `os.replace` it into place; temporary
work folders that a killed process leaves behind are removed by the next run.

A reader never sees a half-written file, and a failed write leaves the target as it was (absent or the old
version) with no temporary file behind. OSError (missing directory, no permission, disk full) propagates. A target
that is a symbolic link is written through it (the link stays, the file it names is replaced); one that exists and is
not a regular file (a device such as /dev/null, a named pipe, a socket) is refused, since replacing it would remove
it.
Temporary files and folders carry the writing process's id (`.NAME.PID-RANDOM.tmp`, `PREFIXPID-RANDOM`), so
those of dead processes (killed by SIGKILL, a crash, a power cut) are recognised and removed.
"""

import os
import re
import secrets
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from mapsqueeze.errors import OutputError


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _remove_dead_processes_leftovers(folder: Path, pattern: re.Pattern) -> None:
    """Remove the entries of `folder` owned by this user whose name matches `pattern` (group 1: a pid) and whose
    process is gone."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for entry in entries:
        match = pattern.fullmatch(entry.name)
        try:
            if not match or entry.stat(follow_symlinks=False).st_uid != os.getuid() or _process_alive(int(match[1])):
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path, ignore_errors=True)
            else:
                os.unlink(entry.path)
        except OSError:
            continue


def work_dir(prefix: str, dir: str | os.PathLike | None = None) -> tempfile.TemporaryDirectory:
    """A temporary folder `PREFIX<pid>-<random>` in `dir` (default: the system's temporary directory), removed
    on exit; folders of the same prefix left by dead processes are removed first (`remove_dead_work_dirs`)."""
    parent = remove_dead_work_dirs(prefix, dir)
    return tempfile.TemporaryDirectory(prefix=f"{prefix}{os.getpid()}-", dir=parent)


def remove_dead_work_dirs(prefix: str, dir: str | os.PathLike | None = None) -> Path:
    """Remove the `work_dir` folders of this prefix in `dir` (default: the system's temporary directory) whose
    process is gone; returns that folder."""
    parent = Path(dir if dir is not None else tempfile.gettempdir())
    _remove_dead_processes_leftovers(parent, re.compile(re.escape(prefix) + r"(\d+)-[A-Za-z0-9_]+"))
    return parent


def _same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # either is missing or unreadable
        return False


def _replaceable(path: str | os.PathLike) -> Path:
    """The file an atomic write to `path` replaces: `path`, or the file a symbolic link there names (the link is
    kept); OutputError if that exists and is not a regular file (replacing a device or a pipe would remove it)."""
    shown = target = Path(path)
    if target.is_symlink():
        target = Path(os.path.realpath(target))
    if target.is_dir():
        raise OutputError(f"{shown}: is a directory; give a file name")
    if target.exists() and not target.is_file():
        raise OutputError(f"{shown}: is not a regular file (a device, pipe or socket); give a file name")
    return target


def check_output_path(path: str | os.PathLike, inputs: tuple[str | os.PathLike, ...] = ()) -> None:
    """OutputError unless a file can be written atomically at `path`: its folder exists and is writable (a
    temporary file is created there and removed), no directory, device or pipe has its name and it is none of
    `inputs` (the files the command reads: writing one would destroy it). Call it before long work."""
    shown, target = Path(path), _replaceable(path)
    for source in inputs:
        if _same_file(target, source):
            raise OutputError(f"{shown}: is the input file {source}; give another output path")
    folder = target.parent
    if not folder.is_dir():
        raise OutputError(f"{shown}: folder {folder} does not exist")
    try:
        _create_temp_file(target).unlink()
    except OSError as exc:
        raise OutputError(f"{shown}: cannot write in folder {folder} ({exc.strerror or exc})") from None


def _new_file_mode() -> int:
    """0o666 minus the process's umask: the mode `open` gives a new file."""
    try:
        with open("/proc/self/status") as status:  # Linux: read without changing it
            mask = next(int(line.split()[1], 8) for line in status if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError):
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o666 & ~mask


def _create_temp_file(target: Path) -> Path:
    """Create an empty, uniquely named file in the target's directory (mode 0o666 minus the umask); temporary
    files of this target left by dead processes are removed first."""
    leftover = re.compile(re.escape(f".{target.name}.") + r"(\d+)-[0-9a-f]+\.tmp")
    _remove_dead_processes_leftovers(target.parent, leftover)
    while True:
        temp = target.with_name(f".{target.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
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
    target = _replaceable(path)
    temp = _create_temp_file(target)
    try:
        yield temp
        _fsync(temp)
        os.chmod(temp, _new_file_mode())  # a library may have replaced the file with a private one (safetensors)
        os.replace(temp, target)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` atomically (see `atomic_output`)."""
    with atomic_output(path) as temp:
        temp.write_bytes(data)
