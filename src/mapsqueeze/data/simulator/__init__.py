"""LiDAR map simulator: procedural driving scenes, ray-cast sweeps of real sensor models, and submap datasets
built with the same map-building code as real data (`mapsqueeze.data.mapping`).

    from mapsqueeze.data.simulator import SimulationConfig, simulate_dataset
    simulate_dataset("datasets/sim", SimulationConfig(n_submaps=200, sensors=("hdl64",), presets=("urban",)))

Modules: `sensors` (beam geometry and noise of HDL-64E, HDL-32E, VLP-32C, OS1-128, OS2-128), `shapes` (mesh
primitives), `buildings`, `objects` (vehicles, vegetation, fences, poles, clutter), `streets` (roads and terrain),
`presets` (kinds of environment), `layout` (placing objects along streets), `lots` (what fills a street side),
`scene` (assembly of a scene), `raycast` (Embree ray casting with material responses), `simulate` (driving,
aggregation, datasets). See docs/simulator.md.
"""

from mapsqueeze.data.simulator.presets import PRESETS, Preset, get_preset
from mapsqueeze.data.simulator.raycast import Raycaster
from mapsqueeze.data.simulator.scene import Scene, build_scene
from mapsqueeze.data.simulator.sensors import SENSORS, SensorInstance, SensorModel, get_sensor
from mapsqueeze.data.simulator.simulate import (
    SceneResult,
    SimulationConfig,
    drive,
    iter_scenes,
    simulate_dataset,
    simulate_scene,
)

__all__ = [
    "PRESETS",
    "SENSORS",
    "Preset",
    "Raycaster",
    "Scene",
    "SceneResult",
    "SensorInstance",
    "SensorModel",
    "SimulationConfig",
    "build_scene",
    "drive",
    "get_preset",
    "get_sensor",
    "iter_scenes",
    "simulate_dataset",
    "simulate_scene",
]
