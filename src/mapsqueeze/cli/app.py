"""The one typer app; command modules register themselves on it (see cli/__init__.py)."""

import typer

from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.version import __version__

app = typer.Typer(
    name="mapsqueeze",
    help="Compress dense 3-D point-cloud maps with a learned autoencoder.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _print_version(requested: bool) -> None:
    if requested:
        typer.echo(f"mapsqueeze {__version__}")
        raise typer.Exit()


@app.callback()
def _options(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """Compress dense 3-D point-cloud maps with a learned autoencoder."""


def parse_numbers(text: str, count: int, option: str, meaning: str) -> list[float]:
    """'40,40,15' -> [40.0, 40.0, 15.0]; exactly `count` comma-separated numbers or a MapsqueezeError."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count:
        raise MapsqueezeError(f"{option}: expected {meaning}, got {text!r}")
    return values
