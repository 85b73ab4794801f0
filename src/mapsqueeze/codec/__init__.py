"""The .msq codec: container format, embedding coders (f32 / f16 / entropy-coded q), whole-map compression."""

from mapsqueeze.codec.compress import compress_map
from mapsqueeze.codec.container import ContainerReader, TileCoding, TileEntry, open_container
from mapsqueeze.codec.decompress import iter_decoded_tiles
from mapsqueeze.codec.embedding import Precision
from mapsqueeze.codec.header import Header

__all__ = [
    "ContainerReader", "Header", "Precision", "TileCoding", "TileEntry", "compress_map", "iter_decoded_tiles",
    "open_container",
]
