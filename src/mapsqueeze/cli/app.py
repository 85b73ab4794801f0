"""The one typer app; command modules register themselves on it (see cli/__init__.py)."""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

import typer

from mapsqueeze.errors import MapsqueezeError
from mapsqueeze.io import SUPPORTED_FORMATS
from mapsqueeze.version import __version__

if TYPE_CHECKING:
    from rich.console import Console

FORMAT_HELP = f"one of {', '.join(SUPPORTED_FORMATS)} (default: from the extension)"

app = typer.Typer(
    name="mapsqueeze",
    help="Compress dense 3-D point-cloud maps with a learned autoencoder.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # click's plain help: rich's option table cuts flag names short at 80 columns
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


def device_option(runs: str) -> typer.models.OptionInfo:
    """--device: where the network runs (`runs`: what of it the command runs)."""
    return typer.Option("cpu", "--device", metavar="cpu|cuda|cuda:N",
                        help=f"where the network runs ({runs}): cpu (default: numpy without torch, byte-identical "
                             "output on any machine) or a GPU (cuda, cuda:N: torch there, the same results within "
                             "float32 rounding, not the same bytes)")


def max_tile_points_option() -> typer.models.OptionInfo:
    """--max-tile-points: the decoder's guard against crafted files (`codec.decompress.target_counts`)."""
    from mapsqueeze.codec.container import DEFAULT_MAX_TILE_POINTS, MAX_POINTS_PER_TILE

    return typer.Option(DEFAULT_MAX_TILE_POINTS, "--max-tile-points", metavar="N", min=1, max=MAX_POINTS_PER_TILE,
                        help="refuse to decode more points than this in one tile (a guard against crafted files)")


def parse_numbers(text: str, count: int, option: str, meaning: str) -> list[float]:
    """'40,40,15' -> [40.0, 40.0, 15.0]; exactly `count` comma-separated numbers or a MapsqueezeError."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count:
        raise MapsqueezeError(f"{option}: expected {meaning}, got {text!r}")
    return values


def counted(n: int, noun: str) -> str:
    """'1 tile', '2,548,100 points': a count and its noun, plural unless one."""
    return f"{n:,} {noun}{'' if n == 1 else 's'}"


def nan_points_line(count: int, source=None) -> str:
    """The line a command prints when the reader left out `count` points of the file `source` (if named) whose x,
    y or z is NaN."""
    of = "" if source is None else f" of {source}"
    return f"left out {counted(count, 'point')}{of} with NaN coordinates (PCD 'no return' values)"


def make_console(stderr: bool = False) -> Console:
    """The console commands print rich's tables, bars and styled text through: rich on a terminal; piped or
    redirected, plain lines that are never wrapped or coloured (rich would wrap at 80 columns and squeeze wide
    tables)."""
    from rich.console import Console

    if (sys.stderr if stderr else sys.stdout).isatty():
        return Console(stderr=stderr)
    return Console(stderr=stderr, width=10_000, soft_wrap=True, no_color=True, highlight=False, emoji=False)


def print_line(text: str, stderr: bool = False) -> None:
    """One line of plain text on stdout (or stderr), printed as it is (a file name's brackets are no rich markup, its
    ':smile:' no emoji code, a long line is not broken; what the stream's encoding cannot hold, backslash-escaped):
    through rich on a terminal; piped or redirected, without loading rich (~0.05 CPU-s)."""
    stream = sys.stderr if stderr else sys.stdout
    encoding = getattr(stream, "encoding", None) or "utf-8"
    try:
        text.encode(encoding, getattr(stream, "errors", None) or "strict")
    except UnicodeEncodeError:  # e.g. a Chinese file name printed to an ASCII or cp1252 pipe
        text = text.encode(encoding, "backslashreplace").decode(encoding)
    if stream.isatty():
        make_console(stderr).print(text, markup=False, emoji=False, soft_wrap=True)
    else:
        print(text, file=stream)


def print_table(table) -> None:
    """A rich Table on stdout: boxed on a terminal; piped or redirected, plain lines (the title, then the header and
    each row, columns aligned by spaces, no box characters, no trailing spaces)."""
    console = make_console()
    if sys.stdout.isatty():
        console.print(table)
        return
    if table.title:
        print_line(str(table.title))
    table.title, table.box, table.pad_edge = None, None, False
    with console.capture() as captured:
        console.print(table)
    for line in captured.get().splitlines():
        print_line(line.rstrip())


def print_rows(rows: list[tuple[str, str]]) -> None:
    """(name, value) rows on stdout, the values aligned: a rich table on a terminal; piped or redirected, one plain
    line per row (`print_line`) without the trailing spaces a table pads its last column with."""
    if sys.stdout.isatty():
        from rich.table import Table
        from rich.text import Text

        table = Table(show_header=False, box=None)
        for name, value in rows:
            table.add_row(Text(name), Text(value))  # as they are: a model's name '[/b]' is no rich markup
        make_console().print(table)
        return
    width = max((len(name) for name, _ in rows), default=0)
    for name, value in rows:
        print_line(f"{name:<{width}}  {value}".rstrip())
