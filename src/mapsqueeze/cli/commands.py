"""The command line with every command registered on the typer app (`cli.app`), and `run`, which runs the command
sys.argv names; `cli.main` loads this module once its signal handlers are set."""

import signal
import sys

import typer

from mapsqueeze.cli import _fail
from mapsqueeze.cli.app import app
from mapsqueeze.cli import (  # noqa: F401  (registers commands)
    bench_cmds, codec_cmds, data_cmds, demo_cmds, eval_cmds, io_cmds, model_cmds, sim_cmds, view_cmds,
)
from mapsqueeze.errors import MapsqueezeError


def run() -> None:
    """Run the command of sys.argv: library errors and usage errors become one `error: ...` line and exit code 2
    (SIGINT and SIGTERM propagate to `cli.main`)."""
    try:
        result = app(standalone_mode=False)
    except MapsqueezeError as exc:
        _fail(str(exc))
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # usage errors: unknown option, bad value, missing argument
        _fail(f"{exc.format_message()} (see --help)", getattr(exc, "exit_code", 2))
    except typer.Abort:  # click's form of a KeyboardInterrupt
        _fail("interrupted", 128 + signal.SIGINT)
    sys.exit(result if isinstance(result, int) else 0)
