"""mapsqueeze: learned compression of dense 3-D LiDAR point-cloud maps."""

from mapsqueeze.version import __version__  # noqa: F401

_API = ("compress", "decompress", "compress_file", "decompress_file", "info", "tiles")


def __getattr__(name: str):
    """Lazy `mapsqueeze.compress` / `decompress` / ...: the codec (and torch) load on first use."""
    if name in _API:
        from mapsqueeze import api

        return getattr(api, name)
    raise AttributeError(f"module 'mapsqueeze' has no attribute {name!r}")
