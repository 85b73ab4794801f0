"""Command-line entry point: `mapsqueeze COMMAND ...`.

`main` sets its SIGINT and SIGTERM handlers first and only then loads typer and the module of the command run
(`cli.commands`, where each module adds its commands to the single typer app in `cli.app`; every command is a thin
call into the library). Library errors (MapsqueezeError) and wrong flags become one `error: ...` line and exit
code 2. Ctrl-C (SIGINT) and SIGTERM, from the moment `main` starts (while the command line still loads, too), unwind
every `with` block (the tile threads finish their running tiles, temporary folders and partial outputs are removed)
and end with one line, `error: interrupted` (exit code 130) or `error: terminated` (143). This module imports
nothing beyond the standard library, so that the handlers are set within milliseconds of the start.

`entry` is the program (the `mapsqueeze` script, `python -m mapsqueeze`): `main`, then the process ends without the
interpreter's teardown (`_end_process`).
"""

import atexit
import errno
import os
import signal
import sys
import threading


def _fail(message: str, code: int = 2) -> None:
    print(f"error: {' '.join(message.split())}", file=sys.stderr)
    sys.exit(code)


_SIGNAL_MESSAGES = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated"}


class _Signalled(BaseException):
    """Raised in the main thread on SIGINT or SIGTERM, so that every `with` block cleans up on the way out. Not a
    KeyboardInterrupt: typer turns one into a silent exit code 130."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _on_signal(signum, frame) -> None:
    raise _Signalled(signum)


def _install_signal_handlers() -> dict:
    """Route SIGINT and SIGTERM to `_on_signal`, except a signal the parent set to be ignored (e.g. SIGINT of a
    command started in the background); returns the handlers replaced. None outside the main thread (an
    application running the CLI in a worker thread), where Python delivers no signal and sets no handler."""
    replaced = {}
    if threading.current_thread() is not threading.main_thread():
        return replaced
    for signum in _SIGNAL_MESSAGES:
        if signal.getsignal(signum) is not signal.SIG_IGN:
            replaced[signum] = signal.signal(signum, _on_signal)
    return replaced


def _open_closed_streams() -> None:
    """A standard stream the command was started without (`>&-`: Python's sys.stdout is None) writes to os.devnull,
    so that the command runs and its output files are written."""
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w"))  # noqa: SIM115 - the process's stream from now on


_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
"""Errors only a write raises, which no retry mends: the device or the quota is full, the file too large."""


def main() -> None:
    replaced = _install_signal_handlers()
    _open_closed_streams()
    try:
        from mapsqueeze.cli.commands import run  # typer and the command's module, once the handlers are set

        run()
    except OSError as exc:  # e.g. the output printed to a full device (`> /dev/full`)
        if exc.errno not in _WRITE_ERRNOS:
            raise
        _fail(f"cannot write {exc.filename or 'the output'} ({exc.strerror})")
    except KeyboardInterrupt:
        _fail("interrupted", 128 + signal.SIGINT)
    except _Signalled as exc:
        _fail(_SIGNAL_MESSAGES[exc.signum], 128 + exc.signum)
    finally:
        for signum, handler in replaced.items():
            signal.signal(signum, handler)


def entry() -> None:
    """The `mapsqueeze` program: `main`, then `_end_process` with its exit code. (`main` itself ends with SystemExit,
    for callers that run the command line in their own process.)"""
    try:
        main()
    except SystemExit as exc:
        _end_process(exc.code)
    _end_process(0)


def _end_process(code) -> None:
    """End the process with exit code `code` (as SystemExit takes it) once the command is done: run the atexit
    handlers, flush stdout and stderr, then os._exit, skipping the interpreter's teardown (destroying every module
    and object: 0.3 s after numba's compiled kernels are loaded, 0.1 s otherwise), which the outputs, closed by
    now, do not need. Output stdout cannot take (a full device) ends a run that had succeeded with one error line
    and exit code 2; a reader that closed the pipe, silently. Where a thread other than daemons is still running,
    the usual exit instead (it waits for the threads)."""
    if any(thread is not threading.main_thread() and not thread.daemon and thread.is_alive()
           for thread in threading.enumerate()):
        raise SystemExit(code)
    if code is None:
        status = 0
    elif isinstance(code, int):
        status = code & 0xFF
    else:  # SystemExit("message"): printed, status 1
        print(code, file=sys.stderr)
        status = 1
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError) as exc:
            if stream is sys.stdout and status == 0 and not isinstance(exc, BrokenPipeError):
                status = 2
                try:
                    print(f"error: cannot write to standard output ({getattr(exc, 'strerror', None) or exc})",
                          file=sys.stderr, flush=True)
                except (OSError, ValueError):
                    pass
    os._exit(status)
