"""Surface reflectivity and the intensity of a return: what a LiDAR's intensity / reflectance channel measures.

Every face gets a diffuse reflectivity at the laser's 905 nm wavelength from its semantic class (asphalt ~0.12,
lane paint ~0.6, concrete ~0.3, grass and leaves ~0.4-0.5, retro-reflective sign sheeting ~3), varied per object
by a log-normal factor (cars of every colour, buildings of every facade), lowered on glass. A return's intensity
follows the lidar equation for an extended Lambertian target, received power ~ reflectivity x cos(incidence) / range^2, with
speckle noise, compressed to 0..1 like KITTI's reflectance channel (`intensity`).
"""

import numpy as np

from mapsqueeze.data.simulator.shapes import Material, Semantic

# class -> (median reflectivity, 1-sigma of the per-object log-normal factor)
REFLECTIVITY: dict[Semantic, tuple[float, float]] = {
    Semantic.UNLABELED: (0.25, 0.3),
    Semantic.CAR: (0.3, 0.6),  # paint of every colour
    Semantic.BICYCLE: (0.25, 0.3),
    Semantic.TRUCK: (0.35, 0.4),
    Semantic.PERSON: (0.3, 0.3),
    Semantic.ROAD: (0.12, 0.2),  # asphalt
    Semantic.PARKING: (0.14, 0.2),
    Semantic.SIDEWALK: (0.3, 0.2),  # concrete, paving
    Semantic.BUILDING: (0.35, 0.35),
    Semantic.FENCE: (0.3, 0.35),
    Semantic.OTHER_STRUCTURE: (0.3, 0.3),
    Semantic.LANE_MARKING: (0.6, 0.0),  # white road paint with glass beads
    Semantic.VEGETATION: (0.5, 0.2),  # leaves reflect strongly in the near infrared
    Semantic.TRUNK: (0.3, 0.2),
    Semantic.TERRAIN: (0.4, 0.2),
    Semantic.POLE: (0.35, 0.3),
    Semantic.TRAFFIC_SIGN: (3.0, 0.2),  # retro-reflective sheeting
    Semantic.OTHER_OBJECT: (0.3, 0.4),
}
MATERIAL_FACTOR = {Material.GLASS: 0.15}
"""Reflectivity factor of materials other than their class's usual surface (default 1)."""

REFERENCE_RANGE_M = 10.0
"""Range at which a head-on Lambertian target of reflectivity 1 gives the compressed signal 1 (before saturation)."""
SPECKLE_SIGMA = 0.1
"""1-sigma of the log-normal speckle noise on the received power."""


def face_reflectivity(labels: np.ndarray, objects: np.ndarray, materials: np.ndarray,
                      rng: np.random.Generator | None) -> np.ndarray:
    """(F,) float64 reflectivity of each face: its class's median x exp(sigma_class x z_object) x material factor.

    z is one standard normal draw per object id (in ascending id order; faces of no object, id 0, get z = 0),
    so every face of one object shares its factor; rng None: z = 0 (the class medians).
    """
    median = np.ones(len(labels))
    sigma = np.zeros(len(labels))
    for semantic, (value, spread) in REFLECTIVITY.items():
        mine = labels == semantic
        median[mine], sigma[mine] = value, spread
    ids, index = np.unique(objects, return_inverse=True)
    z = np.zeros(len(ids)) if rng is None else rng.normal(0.0, 1.0, len(ids))
    z[ids == 0] = 0.0
    factor = np.ones(len(labels))
    for material, value in MATERIAL_FACTOR.items():
        factor[materials == material] = value
    return median * np.exp(sigma * z[index.reshape(-1)]) * factor


def intensity(reflectivity: np.ndarray, cosine: np.ndarray, range_m: np.ndarray,
              rng: np.random.Generator) -> np.ndarray:
    """(N,) float32 intensity in [0, 1) of returns from surfaces of `reflectivity` at incidence cosine `cosine`
    and distance `range_m` (metres).

    signal = reflectivity x cos(incidence) x (REFERENCE_RANGE_M / range)^2 x speckle (log-normal); intensity =
    1 - exp(-sqrt(signal)): square-root range compression and soft saturation like a sensor's automatic gain,
    so intensity falls with range and incidence angle and bright targets saturate near 1.
    """
    signal = (np.asarray(reflectivity) * np.clip(cosine, 0.0, 1.0) * (REFERENCE_RANGE_M / np.maximum(range_m, 0.1)) ** 2
              * np.exp(rng.normal(0.0, SPECKLE_SIGMA, len(reflectivity))))
    return (1.0 - np.exp(-np.sqrt(signal))).astype(np.float32)
