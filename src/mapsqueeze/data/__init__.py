"""Map building from scan sequences (poses, labels, range and voxel filters) and submap datasets.

`sequences` reads scan sequences, `mapping` builds maps and submap datasets the paper's way; the simulator
(`data.simulator`) builds simulated datasets with the same code. Grid tiling for the codec is `geometry.tiling`.
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
from mapsqueeze.data.sequences import ScanSequence, estimate_poses, open_sequences

__all__ = [
    "ScanSequence",
    "Submap",
    "SubmapDataset",
    "SubmapRecord",
    "aggregate_map",
    "build_submaps",
    "crop_submap",
    "estimate_poses",
    "open_sequences",
    "preprocess_scan",
    "read_dataset",
    "submap_bounds",
    "submap_centers",
    "transform",
    "write_dataset",
]
