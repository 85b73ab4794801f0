"""Command-line entry point: `mapsqueeze COMMAND ...`.

Each module imported below adds its commands to the single typer app in `cli.app`; every command is a thin
call into the library. Library errors (MapsqueezeError) become one `error: ...` line and exit code 2.
"""

import sys

from mapsqueeze.cli.app import app
from mapsqueeze.cli import data_cmds, eval_cmds, io_cmds, model_cmds  # noqa: F401  (registers commands)
from mapsqueeze.errors import MapsqueezeError


def main() -> None:
    try:
        app(standalone_mode=True)
    except MapsqueezeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        sys.exit(130)
