"""Map building from scan sequences (poses, labels, range and voxel filters), submaps and grid tiling.

`sequences` reads scan sequences, `mapping` builds maps and submap datasets the paper's way, `tiling` cuts any
map into grid tiles for the codec. The simulator (`data.simulator`) and the training dataset (`data.training`)
build on these.
"""

import importlib

_EXPORTS = {
    "mapping": ("Submap", "SubmapDataset", "SubmapRecord", "aggregate_map", "build_submaps", "crop_submap",
                "preprocess_scan", "read_dataset", "submap_bounds", "submap_centers", "transform", "write_dataset"),
    "sequences": ("DataError", "ScanSequence", "estimate_poses", "open_sequences"),
    "tiling": ("TILE_SIZE_M", "Tile", "tile_map", "to_local"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_MODULE_OF)


def __getattr__(name: str):
    """Lazy re-exports: the codec imports `data.tiling` without the map builder's scipy and pose estimation."""
    if name in _MODULE_OF:
        return getattr(importlib.import_module(f"mapsqueeze.data.{_MODULE_OF[name]}"), name)
    raise AttributeError(f"module 'mapsqueeze.data' has no attribute {name!r}")
