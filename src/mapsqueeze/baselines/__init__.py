"""Classical point-cloud codecs for the rate-distortion benchmark (paper Fig. 4-5): Draco, the plain binary
octree (raw and arithmetic-coded) and MPEG G-PCC (external `tmc3`). Each is a `BaselineCodec`; `BASELINES`
maps a codec's name to its class."""

from mapsqueeze.baselines.base import BaselineCodec, Setting, setting_label
from mapsqueeze.baselines.draco import DracoCodec
from mapsqueeze.baselines.gpcc import GpccCodec
from mapsqueeze.baselines.octree import OctreeAcCodec, OctreeCodec
from mapsqueeze.baselines.rd import distortion_at, pareto_front
from mapsqueeze.errors import BaselineError

BASELINES: dict[str, type[BaselineCodec]] = {
    codec.name: codec for codec in (DracoCodec, OctreeCodec, OctreeAcCodec, GpccCodec)
}


def get_baseline(name: str) -> BaselineCodec:
    """A new codec instance by name, or BaselineError listing the known names."""
    if name not in BASELINES:
        raise BaselineError(f"unknown baseline codec {name!r}; known: {', '.join(BASELINES)}")
    return BASELINES[name]()


__all__ = [
    "BASELINES",
    "BaselineCodec",
    "DracoCodec",
    "GpccCodec",
    "OctreeAcCodec",
    "OctreeCodec",
    "Setting",
    "distortion_at",
    "get_baseline",
    "pareto_front",
    "setting_label",
]
