"""Command-line entry point: `mapsqueeze COMMAND ...`.

Each module imported below adds its commands to the single typer app in `cli.app`; every command is a thin
call into the library. Library errors (MapsqueezeError) and wrong flags become one `error: ...` line and exit
code 2. Ctrl-C (SIGINT) and SIGTERM unwind every `with` block (the tile threads finish their running tiles, temporary
folders and partial outputs are removed) and end with one line, `error: interrupted` (exit code 130) or
`error: terminated` (143).
"""

import signal
import sys
import threading

import typer

from mapsqueeze.cli.app import app
from mapsqueeze.cli import (  # noqa: F401  (registers commands)
    bench_cmds, codec_cmds, data_cmds, demo_cmds, eval_cmds, io_cmds, model_cmds, sim_cmds, view_cmds,
)
from mapsqueeze.errors import MapsqueezeError


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


def main() -> None:
    replaced = _install_signal_handlers()
    try:
        _run()
    finally:
        for signum, handler in replaced.items():
            signal.signal(signum, handler)


def _run() -> None:
    try:
        result = app(standalone_mode=False)
    except MapsqueezeError as exc:
        _fail(str(exc))
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # usage errors: unknown option, bad value, missing argument
        _fail(f"{exc.format_message()} (see --help)", getattr(exc, "exit_code", 2))
    except (KeyboardInterrupt, typer.Abort):
        _fail("interrupted", 128 + signal.SIGINT)
    except _Signalled as exc:
        _fail(_SIGNAL_MESSAGES[exc.signum], 128 + exc.signum)
    sys.exit(result if isinstance(result, int) else 0)
