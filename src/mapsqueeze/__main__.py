"""`python -m mapsqueeze ...` (e.g. under `torchrun`): the command-line interface."""

from mapsqueeze.cli import entry

if __name__ == "__main__":
    entry()
