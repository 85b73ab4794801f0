"""Rotating multi-beam LiDAR models (beam angles, azimuth resolution, mount, noise) of real devices.

A `SensorModel` is the data-sheet description; `SensorModel.instance(rng)` draws one physical unit from it: a
mount height, a rotation resolution, and the small per-laser calibration errors (elevation and range offsets)
that give real multi-beam maps their ring-to-ring inconsistencies. Sensor frame: x forward, y left, z up.
"""

from dataclasses import dataclass

import numpy as np

from mapsqueeze.errors import SimulationError


# Velodyne VLP-32C (Ultra Puck) beam elevations from its data sheet, degrees (denser around the horizon).
_VLP32C_ELEVATIONS_DEG = (
    -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667, -2.333,
    -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333, 3.333, 4.667, 7.0,
    10.333, 15.0,
)


@dataclass(frozen=True)
class SensorModel:
    """A LiDAR's nominal geometry and noise.

    elevations_deg: one elevation angle per laser (degrees, + up); azimuth_step_deg: (min, max) horizontal
    resolution of the device's rotation-rate modes; mount_height_m: (min, max) height of the optical centre
    above the road; range_noise_m: 1-sigma range noise; dropout: probability a return is lost on an ordinary
    surface; divergence_mrad: full beam divergence (beam directions jitter by a quarter of it, 1 sigma);
    elevation_error_deg / range_offset_m: 1-sigma per-laser calibration errors; ego_shadow: the own car's
    roof as an ellipse (centre x, centre y, semi-axis x, semi-axis y, height z) in the sensor frame, metres:
    downward beams that cross the plane z inside it hit the car and give no map point.
    """

    name: str
    description: str
    elevations_deg: tuple[float, ...]
    azimuth_step_deg: tuple[float, float]
    mount_height_m: tuple[float, float]
    max_range_m: float
    range_noise_m: float
    dropout: float
    divergence_mrad: float
    elevation_error_deg: float
    range_offset_m: float
    ego_shadow: tuple[float, float, float, float, float] = (0.0, 0.0, 1.2, 0.7, -0.3)

    @property
    def n_lasers(self) -> int:
        return len(self.elevations_deg)

    def instance(self, rng: np.random.Generator) -> "SensorInstance":
        """One unit of this model: drawn mount height, azimuth step and per-laser calibration errors."""
        n = self.n_lasers
        return SensorInstance(
            model=self,
            mount_height_m=float(rng.uniform(*self.mount_height_m)),
            azimuth_step_deg=float(rng.uniform(*self.azimuth_step_deg)),
            elevations_deg=np.asarray(self.elevations_deg) + rng.normal(0.0, self.elevation_error_deg, n),
            azimuth_offsets_deg=rng.uniform(-0.5, 0.5, n) * self.azimuth_step_deg[1],
            range_offsets_m=rng.normal(0.0, self.range_offset_m, n),
            ego_shadow=np.asarray(self.ego_shadow) * np.r_[1.0, 1.0, rng.uniform(0.9, 1.1, 2), 1.0],
        )


@dataclass(frozen=True)
class SensorInstance:
    """One physical sensor drawn from a `SensorModel` (see `SensorModel.instance`)."""

    model: SensorModel
    mount_height_m: float
    azimuth_step_deg: float
    elevations_deg: np.ndarray  # (L,) per laser, calibration error included
    azimuth_offsets_deg: np.ndarray  # (L,) per-laser firing offsets
    range_offsets_m: np.ndarray  # (L,) per-laser range bias
    ego_shadow: np.ndarray  # (5,) see SensorModel.ego_shadow

    def beams(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """One sweep: (unit directions (R, 3) in the sensor frame, laser index (R,)) of the firings that leave
        the car (beams into the own roof are left out).

        The sweep starts at a random azimuth phase, so successive scans sample the scene at different angles.
        """
        azimuths = np.deg2rad(np.arange(0.0, 360.0, self.azimuth_step_deg) + rng.uniform(0, self.azimuth_step_deg))
        n_lasers = len(self.elevations_deg)
        azimuth = azimuths[None, :] + np.deg2rad(self.azimuth_offsets_deg)[:, None]
        elevation = np.broadcast_to(np.deg2rad(self.elevations_deg)[:, None], azimuth.shape)
        cos_el = np.cos(elevation)
        directions = np.stack([cos_el * np.cos(azimuth), cos_el * np.sin(azimuth), np.sin(elevation)], -1)
        lasers = np.broadcast_to(np.arange(n_lasers)[:, None], azimuth.shape)
        directions, lasers = directions.reshape(-1, 3), lasers.ravel()
        cx, cy, ax, ay, z = self.ego_shadow
        down = directions[:, 2] < -1e-6
        scale = np.where(down, z / np.where(down, directions[:, 2], -1.0), np.inf)
        at_roof = directions[:, :2] * np.minimum(scale, 1e6)[:, None]
        blocked = down & (((at_roof[:, 0] - cx) / ax) ** 2 + ((at_roof[:, 1] - cy) / ay) ** 2 < 1.0)
        return directions[~blocked], lasers[~blocked]


SENSORS: dict[str, SensorModel] = {
    "hdl64": SensorModel(
        name="hdl64",
        description="Velodyne HDL-64E S2 as on the KITTI car (64 lasers, +2.0 to -24.9 deg, 10 Hz)",
        elevations_deg=tuple(np.r_[np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.9, 32)].round(3)),
        azimuth_step_deg=(0.15, 0.18),
        mount_height_m=(1.68, 1.78),
        max_range_m=120.0,
        range_noise_m=0.02,
        dropout=0.02,
        divergence_mrad=2.0,
        elevation_error_deg=0.04,
        range_offset_m=0.02,
        ego_shadow=(-1.25, 0.0, 0.35, 0.6, -0.5),  # KITTI: the lowest beams are blocked behind the car
    ),
    "hdl32": SensorModel(
        name="hdl32",
        description="Velodyne HDL-32E as on the nuScenes car (32 lasers, +10.67 to -30.67 deg, 20 Hz: 0.33 deg)",
        elevations_deg=tuple(np.linspace(10.67, -30.67, 32).round(3)),
        azimuth_step_deg=(0.31, 0.35),
        mount_height_m=(1.75, 1.95),
        max_range_m=100.0,
        range_noise_m=0.012,
        dropout=0.03,
        divergence_mrad=2.8,
        elevation_error_deg=0.05,
        range_offset_m=0.012,
        ego_shadow=(0.0, 0.0, 1.0, 0.55, -0.33),  # nuScenes: the lower eight beams partly hit the roof
    ),
    "vlp32c": SensorModel(
        name="vlp32c",
        description="Velodyne VLP-32C Ultra Puck (32 lasers, +15 to -25 deg, denser at the horizon)",
        elevations_deg=_VLP32C_ELEVATIONS_DEG,
        azimuth_step_deg=(0.1, 0.2),
        mount_height_m=(1.6, 2.0),
        max_range_m=200.0,
        range_noise_m=0.03,
        dropout=0.03,
        divergence_mrad=3.0,
        elevation_error_deg=0.05,
        range_offset_m=0.01,
    ),
    "os1_128": SensorModel(
        name="os1_128",
        description="Ouster OS1-128 (128 lasers, +22.5 to -22.5 deg, 1024 or 2048 columns)",
        elevations_deg=tuple(np.linspace(22.5, -22.5, 128).round(3)),
        azimuth_step_deg=(0.176, 0.352),
        mount_height_m=(1.6, 2.0),
        max_range_m=120.0,
        range_noise_m=0.03,
        dropout=0.03,
        divergence_mrad=1.5,
        elevation_error_deg=0.02,
        range_offset_m=0.008,
    ),
    "os2_128": SensorModel(
        name="os2_128",
        description="Ouster OS2-128 long range (128 lasers, +11.25 to -11.25 deg, 1024 or 2048 columns)",
        elevations_deg=tuple(np.linspace(11.25, -11.25, 128).round(3)),
        azimuth_step_deg=(0.176, 0.352),
        mount_height_m=(1.7, 2.3),
        max_range_m=240.0,
        range_noise_m=0.025,
        dropout=0.03,
        divergence_mrad=0.9,
        elevation_error_deg=0.02,
        range_offset_m=0.008,
    ),
}
"""Sensor models by CLI name."""


def get_sensor(name: str) -> SensorModel:
    """The sensor model called `name` (a key of SENSORS)."""
    try:
        return SENSORS[name]
    except KeyError:
        raise SimulationError(f"unknown sensor {name!r}; choose from {', '.join(SENSORS)}") from None
