"""LiDAR map simulator: procedural driving scenes, ray-cast sweeps of real sensor models, and submap datasets
built with the same map-building code as real data (`mapsqueeze.data.mapping`).

    from mapsqueeze.data.simulator import SimulationConfig, simulate_dataset
    simulate_dataset("datasets/sim", SimulationConfig(n_submaps=200, sensors=("hdl64",), presets=("urban",)))

Modules: `sensors` (beam geometry and noise of HDL-64E, HDL-32E, VLP-32C, OS1-128, OS2-128), `shapes` (mesh
primitives), `buildings`, `objects` (vehicles, vegetation, fences, poles, clutter), `streets` (roads and terrain),
`presets` (kinds of environment), `layout` (placing objects along streets), `lots` (what fills a street side),
`scene` (assembly of a scene), `raycast` (Embree ray casting with material responses), `reflectance`
(reflectivity per class and the intensity model), `aggregate` (voxel aggregation of points with their intensity,
label and instance), `simulate` (driving, aggregation, datasets). See docs/simulator.md.
"""

import importlib

_EXPORTS = {
    "presets": ("PRESETS", "Preset", "get_preset"),
    "raycast": ("Raycaster", "Sweep"),
    "scene": ("Scene", "build_scene"),
    "sensors": ("SENSORS", "SensorInstance", "SensorModel", "get_sensor"),
    "shapes": ("Semantic",),
    "simulate": ("SceneResult", "SimulationConfig", "drive", "iter_scenes", "simulate_dataset", "simulate_scene"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_MODULE_OF)


def __getattr__(name: str):
    """Lazy re-exports: the command line lists the sensors and presets without importing trimesh and Embree."""
    if name in _MODULE_OF:
        return getattr(importlib.import_module(f"mapsqueeze.data.simulator.{_MODULE_OF[name]}"), name)
    raise AttributeError(f"module 'mapsqueeze.data.simulator' has no attribute {name!r}")
