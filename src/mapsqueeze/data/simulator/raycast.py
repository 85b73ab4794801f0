"""Ray casting of LiDAR sweeps against a scene mesh (Embree through trimesh), with per-material returns.

Each beam is traced to its first surface. What happens there depends on the surface's material: it returns,
passes on (gaps between leaves, window glass, wire mesh: the ray is traced further from just behind the hit),
or is lost. Returned ranges get the sensor's range noise, the laser's calibration offset and the material's
own scatter; beams also jitter within their divergence and drop out at random and at grazing incidence.
Beams that hit nothing give no return (no sky points). `sweep` also gives each return its intensity
(`reflectance.intensity`), the semantic class and the instance id of the face it came from.
"""

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from mapsqueeze.data.simulator.reflectance import REFLECTIVITY, face_reflectivity, intensity
from mapsqueeze.data.simulator.sensors import SensorInstance
from mapsqueeze.data.simulator.shapes import Material, Semantic
from mapsqueeze.errors import SimulationError


@dataclass(frozen=True)
class MaterialResponse:
    """Probabilities that a beam returns from / passes through a surface (the rest is lost), and range scatter."""

    returns: float
    passes: float
    scatter_m: float  # extra 1-sigma range noise
    early_m: float = 0.0  # mean of an extra one-sided shortening (returns from blades above the ground)


MATERIAL_RESPONSE: dict[Material, MaterialResponse] = {
    Material.SOLID: MaterialResponse(returns=1.0, passes=0.0, scatter_m=0.0),
    Material.VEGETATION: MaterialResponse(returns=0.6, passes=0.35, scatter_m=0.05),
    Material.GLASS: MaterialResponse(returns=0.2, passes=0.45, scatter_m=0.01),
    Material.GRASS: MaterialResponse(returns=1.0, passes=0.0, scatter_m=0.015, early_m=0.05),
    Material.MESH: MaterialResponse(returns=0.25, passes=0.7, scatter_m=0.01),
}

MAX_PASSES = 4
"""A beam is traced through at most this many porous surfaces."""

_STEP_PAST_M = 0.01  # a passing beam continues this far behind the surface it went through


@dataclass(frozen=True)
class Sweep:
    """The returns of one sweep: points (N, 3) float64 metres in the sensor frame, intensity (N,) float32 in
    [0, 1), semantic label (N,) uint16 (`shapes.Semantic` ids) and instance id (N,) uint16 (0: not a countable
    object)."""

    points: np.ndarray
    intensity: np.ndarray
    label: np.ndarray
    instance: np.ndarray

    def attributes(self) -> dict[str, np.ndarray]:
        """The per-point attributes by the names the io layer uses (`label` and `instance` as it reads a
        SemanticKITTI .label file)."""
        return {"intensity": self.intensity, "label": self.label, "instance": self.instance}


class Raycaster:
    """First-hit queries on one triangle mesh; Embree (embreex) when available, trimesh's numpy caster else.

    Per face: `materials` (`shapes.Material`), and optionally `labels` (`shapes.Semantic`, default unlabeled),
    object ids (> 0 countable objects) and `reflectivity` (default: each class's median reflectivity).
    `markings(world points, faces) -> bool mask` picks returns on road paint (`Scene.lane_markings`).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, materials: np.ndarray,
                 labels: np.ndarray | None = None, objects: np.ndarray | None = None,
                 reflectivity: np.ndarray | None = None,
                 markings: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None):
        if len(faces) == 0:
            raise SimulationError("the scene has no triangles")
        self.mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False, validate=False)
        self._corners = vertices[faces[:, 0]]  # plain copies: indexing the mesh's tracked arrays re-hashes it
        normals = np.cross(vertices[faces[:, 1]] - self._corners, vertices[faces[:, 2]] - self._corners)
        self.normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        self.materials = np.asarray(materials, dtype=np.int8)
        self.labels = np.zeros(len(faces), np.uint16) if labels is None else np.asarray(labels, dtype=np.uint16)
        objects = np.zeros(len(faces), np.int32) if objects is None else np.asarray(objects)
        self.instances = np.maximum(objects, 0).astype(np.uint16)
        self.reflectivity = (face_reflectivity(self.labels, objects, self.materials, None) if reflectivity is None
                             else np.asarray(reflectivity, dtype=np.float64))
        self.markings = markings
        responses = [MATERIAL_RESPONSE[Material(code)] for code in range(len(Material))]
        self._returns = np.array([r.returns for r in responses])
        self._passes = np.array([r.passes for r in responses])
        self._scatter = np.array([r.scatter_m for r in responses])
        self._early = np.array([r.early_m for r in responses])
        try:
            from trimesh.ray.ray_pyembree import RayMeshIntersector

            self._intersector = RayMeshIntersector(self.mesh)
            self.engine = "embree"
        except ImportError:
            warnings.warn("embreex is not installed: ray casting falls back to trimesh's slow numpy intersector "
                          "(pip install 'mapsqueeze[sim]' for Embree)", RuntimeWarning, stacklevel=2)
            from trimesh.ray.ray_triangle import RayMeshIntersector

            self._intersector = RayMeshIntersector(self.mesh)
            self.engine = "numpy"

    def first_hits(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance to the first surface (N,) metres, face index (N,)); inf and -1 where a ray hits nothing.

        `directions` must be unit vectors. The distance is that to the hit face's plane along the ray.
        """
        distance = np.full(len(origins), np.inf)
        if len(origins) == 0:
            return distance, np.full(0, -1, dtype=np.int64)
        face = np.asarray(self._intersector.intersects_first(origins, directions), dtype=np.int64)
        hit = np.flatnonzero(face >= 0)
        normal = self.normals[face[hit]]
        corner = self._corners[face[hit]]
        along = np.einsum("ij,ij->i", directions[hit], normal)
        along = np.where(np.abs(along) < 1e-9, 1e-9, along)
        distance[hit] = np.maximum(np.einsum("ij,ij->i", corner - origins[hit], normal) / along, 0.0)
        return distance, face

    def scan(self, sensor: SensorInstance, pose: np.ndarray, rng: np.random.Generator,
             max_range_m: float | None = None) -> np.ndarray:
        """One sweep from the sensor at `pose` (4 x 4, sensor to world): (N, 3) float64 points in the sensor frame.

        Returns beyond `max_range_m` (default the sensor's maximum range) are dropped.
        """
        return self._trace(sensor, pose, rng, max_range_m)[0]

    def sweep(self, sensor: SensorInstance, pose: np.ndarray, rng: np.random.Generator,
              attribute_rng: np.random.Generator, max_range_m: float | None = None) -> Sweep:
        """`scan`'s points (the same for the same `rng`) with their intensity, label and instance id; the
        intensity noise comes from `attribute_rng` alone."""
        points, face, cosine, distance = self._trace(sensor, pose, rng, max_range_m)
        labels, reflectivity = self.labels[face], self.reflectivity[face]
        if self.markings is not None:
            paint = self.markings(points @ pose[:3, :3].T + pose[:3, 3], face)
            labels = np.where(paint, np.uint16(Semantic.LANE_MARKING), labels)
            reflectivity = np.where(paint, REFLECTIVITY[Semantic.LANE_MARKING][0], reflectivity)
        return Sweep(points, intensity(reflectivity, cosine, distance, attribute_rng), labels, self.instances[face])

    def _trace(self, sensor: SensorInstance, pose: np.ndarray, rng: np.random.Generator,
               max_range_m: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(points (N, 3) sensor frame, face index (N,), |cos incidence| (N,), distance travelled (N,) metres)."""
        model = sensor.model
        max_range = model.max_range_m if max_range_m is None else min(max_range_m, model.max_range_m)
        directions, lasers = sensor.beams(rng)
        sigma = model.divergence_mrad * 1e-3 / 4
        physical = directions + rng.normal(0.0, sigma, directions.shape)
        physical /= np.linalg.norm(physical, axis=1, keepdims=True)
        rotation, origin = pose[:3, :3], pose[:3, 3]
        world = physical @ rotation.T
        origins = np.broadcast_to(origin, world.shape).copy()
        travelled = np.zeros(len(world))
        measured = np.full(len(world), np.nan)
        last_face = np.full(len(world), -1, dtype=np.int64)
        active = np.arange(len(world))
        for _ in range(MAX_PASSES + 1):
            distance, face = self.first_hits(origins[active], world[active])
            total = travelled[active] + distance
            hit = np.isfinite(distance) & (total <= max_range)
            active, face, total = active[hit], face[hit], total[hit]
            material = self.materials[face]
            draw = rng.random(len(active))
            returned = draw < self._returns[material]
            passed = ~returned & (draw < self._returns[material] + self._passes[material])
            measured[active[returned]] = total[returned]
            last_face[active[returned]] = face[returned]
            active = active[passed]
            travelled[active] = total[passed] + _STEP_PAST_M
            origins[active] = origin + world[active] * travelled[active, None]
            if len(active) == 0:
                break
        hit = np.flatnonzero(np.isfinite(measured))
        face = last_face[hit]
        material = self.materials[face]
        cosine = np.abs(np.einsum("ij,ij->i", self.normals[face], world[hit]))
        lost = rng.random(len(hit)) < model.dropout + 0.5 * np.clip(1.0 - cosine / 0.1, 0.0, 1.0)
        hit, material, face, cosine = hit[~lost], material[~lost], face[~lost], cosine[~lost]
        ranges = (measured[hit] + rng.normal(0.0, model.range_noise_m, len(hit)) + sensor.range_offsets_m[lasers[hit]]
                  + rng.normal(0.0, 1.0, len(hit)) * self._scatter[material]
                  - np.abs(rng.normal(0.0, 1.0, len(hit))) * self._early[material])
        return directions[hit] * ranges[:, None], face, cosine, measured[hit]
