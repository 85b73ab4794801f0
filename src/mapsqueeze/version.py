"""The package version (read by pyproject.toml, printed by `mapsqueeze --version`)."""

__version__ = "0.1.0"
