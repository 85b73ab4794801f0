"""Command-line entry point: `mapsqueeze COMMAND ...`.

Each module imported below adds its commands to the single typer app in `cli.app`; every command is a thin
call into the library. Library errors (MapsqueezeError) and wrong flags become one `error: ...` line and exit
code 2. SIGTERM is handled like Ctrl-C: temporary folders and partial outputs are removed, exit code 143.
"""

import signal
import sys

import typer

from mapsqueeze.cli.app import app
from mapsqueeze.cli import (  # noqa: F401  (registers commands)
    bench_cmds, codec_cmds, data_cmds, demo_cmds, eval_cmds, io_cmds, model_cmds, sim_cmds, view_cmds,
)
from mapsqueeze.errors import MapsqueezeError


def _fail(message: str, code: int = 2) -> None:
    print(f"error: {' '.join(message.split())}", file=sys.stderr)
    sys.exit(code)


class _Terminated(BaseException):
    """Raised in the main thread on SIGTERM, so that every `with` block cleans up on the way out."""


def _on_sigterm(signum, frame) -> None:
    raise _Terminated()


def main() -> None:
    signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        result = app(standalone_mode=False)
    except MapsqueezeError as exc:
        _fail(str(exc))
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # usage errors: unknown option, bad value, missing argument
        _fail(f"{exc.format_message()} (see --help)", getattr(exc, "exit_code", 2))
    except (KeyboardInterrupt, typer.Abort):
        _fail("interrupted", 130)
    except _Terminated:
        _fail("terminated", 128 + signal.SIGTERM)
    sys.exit(result if isinstance(result, int) else 0)
