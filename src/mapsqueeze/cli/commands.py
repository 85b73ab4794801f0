"""The command line: `load_commands`, which registers commands on the single typer app (`cli.app`), and `run`, which
runs the command sys.argv names; `cli.main` loads this module once its signal handlers are set.

Each command module adds its commands to the app as it is imported. `run` imports only the module of the command
it runs (COMMAND_MODULES): a compress loads neither the simulator's presets, the viewer nor rich's tables (~0.03
CPU-s of the start). Anything else (`--help`, `--version`, no command, a misspelt one) loads every module, so that
the help lists every command and click suggests the name meant."""

import importlib
import signal
import sys
import warnings

import typer

from mapsqueeze.cli import _fail
from mapsqueeze.cli.app import app, print_line
from mapsqueeze.errors import MapsqueezeError, MapsqueezeWarning

COMMAND_MODULES = {
    "compress": "codec_cmds", "decompress": "codec_cmds", "info": "codec_cmds", "convert": "io_cmds",
    "eval": "eval_cmds", "bench": "bench_cmds", "demo": "demo_cmds", "view": "view_cmds", "simulate": "sim_cmds",
    "build-map": "data_cmds", "tile": "data_cmds", "import-depoco": "model_cmds", "fit-density": "model_cmds",
    "train": "model_cmds", "models": "model_cmds",
}
"""Each command's name -> the module of `mapsqueeze.cli` that registers it."""


def load_commands(args: list[str] | None = None) -> typer.Typer:
    """The app with the command that `args` (the command line after the program's name) starts with registered, or
    every command (args None, or not starting with a command's name)."""
    named = COMMAND_MODULES.get(args[0]) if args else None
    for module in [named] if named else sorted(set(COMMAND_MODULES.values())):
        importlib.import_module(f"mapsqueeze.cli.{module}")
    return app


_python_show_warning = warnings.showwarning


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A MapsqueezeWarning as one `warning: ...` line on stderr; any other warning as Python shows it."""
    if issubclass(category, MapsqueezeWarning):
        print_line(f"warning: {' '.join(str(message).split())}", stderr=True)
    else:
        _python_show_warning(message, category, filename, lineno, file, line)


def run() -> None:
    """Run the command of sys.argv (none: `--help`, which click 8.2 would make a usage error holding the help):
    library errors and usage errors become one `error: ...` line and exit code 2 (SIGINT and SIGTERM propagate to
    `cli.main`)."""
    args = sys.argv[1:] or ["--help"]
    load_commands(args)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            result = app(args=args, standalone_mode=False)
    except MapsqueezeError as exc:
        _fail(str(exc))
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.TyperException as exc:  # usage errors: unknown option, bad value, missing argument
        _fail(f"{exc.format_message()} (see --help)", getattr(exc, "exit_code", 2))
    except typer.Abort:  # click's form of a KeyboardInterrupt
        _fail("interrupted", 128 + signal.SIGINT)
    sys.exit(result if isinstance(result, int) else 0)
