"""mapsqueeze: learned compression of dense 3-D LiDAR point-cloud maps."""

from mapsqueeze.version import __version__  # noqa: F401

_API = ("compress", "decompress", "decompress_cloud", "compress_file", "decompress_file", "info", "tiles",
        "AttributeOptions")


def __getattr__(name: str):
    """Lazy `mapsqueeze.compress` / `decompress` / ...: the codec (and torch) load on first use."""
    if name in _API:
        from mapsqueeze import api

        return getattr(api, name)
    raise AttributeError(f"module 'mapsqueeze' has no attribute {name!r}")
