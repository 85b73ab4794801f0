"""The one typer app; command modules register themselves on it (see cli/__init__.py)."""

import typer

app = typer.Typer(
    name="mapsqueeze",
    help="Compress dense 3-D point-cloud maps with a learned autoencoder.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
