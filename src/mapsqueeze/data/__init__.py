"""Map building from scan sequences (poses, labels, range and voxel filters), submaps and grid tiling.

`sequences` reads scan sequences, `mapping` builds maps and submap datasets the paper's way, `tiling` cuts any
map into grid tiles for the codec. The simulator (`data.simulator`) and the training dataset (`data.training`)
build on these.
"""

from mapsqueeze.data.mapping import (
    Submap,
    SubmapDataset,
    SubmapRecord,
    aggregate_map,
    build_submaps,
    crop_submap,
    preprocess_scan,
    read_dataset,
    submap_bounds,
    submap_centers,
    transform,
    write_dataset,
)
from mapsqueeze.data.sequences import DataError, ScanSequence, estimate_poses, open_sequences
from mapsqueeze.data.tiling import TILE_SIZE_M, Tile, tile_map, to_local

__all__ = [
    "TILE_SIZE_M",
    "DataError",
    "ScanSequence",
    "Submap",
    "SubmapDataset",
    "SubmapRecord",
    "Tile",
    "aggregate_map",
    "build_submaps",
    "crop_submap",
    "estimate_poses",
    "open_sequences",
    "preprocess_scan",
    "read_dataset",
    "submap_bounds",
    "submap_centers",
    "tile_map",
    "to_local",
    "transform",
    "write_dataset",
]
