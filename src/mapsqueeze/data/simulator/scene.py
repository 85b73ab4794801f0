"""Procedural driving scenes: a main street with junctions, lots along it (building rows, houses with gardens,
parks, parking, industry, fields, forest, noise walls), parked cars, street furniture and terrain.

`build_scene(preset, drive_length_m, rng)` returns a `Scene`: one triangle mesh with a material, a semantic class
and an object id per face, the street the car drives along and the lane it keeps. Only what a sensor on the driven
stretch can see within the 20 m mapping range is built (objects up to REACH_M from the route).
"""

from dataclasses import dataclass

import numpy as np

from mapsqueeze.data.simulator import objects
from mapsqueeze.data.simulator.layout import REACH_M, Layout
from mapsqueeze.data.simulator.lots import fill_side, furnish, open_spans, utility_wires
from mapsqueeze.data.simulator.presets import Preset, get_preset
from mapsqueeze.data.simulator.shapes import Semantic
from mapsqueeze.data.simulator.streets import STEP_M, Ground, SideProfile, Street, random_bumps
from mapsqueeze.errors import SimulationError

LEAD_M = 30.0
"""Street built before the start and after the end of the driven stretch."""

MAX_INSTANCE = 0xFFFF
"""Instance ids are stored in 16 bits, as in SemanticKITTI label files."""


@dataclass
class Scene:
    """A built scene: the mesh, the main street and the driven stretch (metres along it) and lane (offset)."""

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    materials: np.ndarray  # (F,) int8, `shapes.Material` codes
    labels: np.ndarray  # (F,) uint16, `shapes.Semantic` ids
    objects: np.ndarray  # (F,) int32 object ids: > 0 countable objects (instances), < 0 other objects
    street: Street
    drive_start_m: float
    drive_end_m: float
    lane_offset_m: float  # lateral offset of the driven lane (negative: right of the centre line)
    preset: str
    lanes: int = 1  # driving lanes per direction of the main street
    lane_width_m: float = 3.0
    median_m: float = 0.0  # width of the median barrier (0: none)
    street_object: int = 0  # object id of the main street's mesh

    def lane_markings(self, points: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """(N,) bool: which returns (world points (N, 3) metres, on faces (N,)) lie on the main street's paint.

        Lines are 15 cm wide: dashed lane dividers (3 m line, 9 m gap) between the lanes of one direction, the
        centre line (solid with 2+ lanes, dashed else) where there is no median, a solid line at the parking
        lane's edge or 25 cm inside the road edge.
        """
        marked = np.zeros(len(points), dtype=bool)
        road = np.flatnonzero((self.objects[faces] == self.street_object) & (self.labels[faces] == Semantic.ROAD))
        if len(road) == 0:
            return marked
        s, t, _ = self.street.project(points[road, :2])
        across = np.abs(t) - self.median_m / 2  # metres from the centre line or the median's edge
        parked = self.street.parking[(t > 0).astype(int)] > 0
        dashed = np.fmod(s, 12.0) < 3.0
        edge = self.lanes * self.lane_width_m - np.where(parked, 0.0, 0.25)
        on_line = np.abs(across - edge) < 0.075
        for k in range(1, self.lanes):
            on_line |= (np.abs(across - k * self.lane_width_m) < 0.075) & dashed
        if self.median_m == 0:
            on_line |= (across < 0.075) & (dashed | (self.lanes > 1))
        marked[road] = on_line
        return marked

    @property
    def top_z(self) -> float:
        """Highest point of the scene (metres): no return can come from above it."""
        return float(self.vertices[:, 2].max())


def build_scene(preset: Preset | str, drive_length_m: float, rng: np.random.Generator) -> Scene:
    """A random scene around a drive of `drive_length_m` metres along its main street."""
    preset = get_preset(preset) if isinstance(preset, str) else preset
    if not drive_length_m > 0:
        raise SimulationError(f"drive length must be positive, got {drive_length_m}")
    length = drive_length_m + 2 * LEAD_M
    xy = _centre_line(rng, length, preset)
    s = np.arange(len(xy)) * STEP_M
    lanes = int(rng.integers(preset.lanes[0], preset.lanes[1] + 1))
    lane_width = rng.uniform(*preset.lane_width)
    parking = np.array([rng.uniform(2.0, 2.5) if rng.random() < preset.parking else 0.0 for _ in range(2)])
    median = 0.6 if preset.median else 0.0
    half_width = lanes * lane_width + parking + median / 2
    main = Street(xy, _elevation(rng, s, preset.grade), half_width, float(rng.uniform(*preset.kerb)),
                  np.array([rng.uniform(*preset.sidewalk) for _ in range(2)]), parking=parking,
                  bumps=random_bumps(rng, rng.uniform(0.005, 0.02)))
    streets = [main]
    drive_start, drive_end = LEAD_M, LEAD_M + drive_length_m
    if preset.junction_spacing is not None:
        junction = drive_start + rng.uniform(0, preset.junction_spacing[1])
        while junction < drive_end + 10:
            straight = abs(np.angle(np.exp(1j * (main.at(junction + 25)[1] - main.at(junction - 25)[1])))) < 0.2
            sides = [0, 1] if rng.random() < 0.4 else [int(rng.integers(2))]
            if straight:
                for side in sides:
                    streets.append(_cross_street(rng, main, preset, junction, side))
            junction += rng.uniform(*preset.junction_spacing)
    route = main.xy[int(drive_start / STEP_M): int(drive_end / STEP_M) + 1]
    profiles = [(_side_profile(rng, preset), _side_profile(rng, preset)) for _ in streets]
    ground = Ground(streets, profiles, route, rng, relief_m=preset.relief * rng.uniform(0.3, 1.0),
                    roughness_m=rng.uniform(0.01, 0.04), reach_m=REACH_M)
    layout = Layout(rng, preset, ground, route)
    street_objects = [layout.new_object(False) for _ in streets]
    for street, object_id in zip(streets, street_objects):
        layout.builder.extend(street.mesh(), np.eye(3), np.zeros(3), object_id)
    layout.builder.extend(ground.mesh(), np.eye(3), np.zeros(3), layout.new_object(False))
    if preset.median:  # in 20 m pieces that follow the curves
        for a in np.arange(0.0, length - 1.0, 20.0):
            rotation, origin = layout.frame(main, 1, a, 0.0)
            origin[2] = float(main.at(a)[2])
            layout.builder.extend(objects.jersey_barrier(min(20.0, length - a)), rotation, origin,
                                  layout.new_object(False))
    for street in streets:
        for side in (0, 1):
            fill_side(layout, street, side, 0.0, street.length)
            for a, b in open_spans(street, side, 0.0, street.length):
                furnish(layout, street, side, a, b, street.parking[side])
    if rng.random() < (0.2 if preset.name in ("urban", "highway") else 0.5):
        utility_wires(layout, main, int(rng.integers(2)), 0.0, length)
    vertices, faces, materials, labels, object_ids = layout.builder.build()
    if object_ids.max() > MAX_INSTANCE:
        raise SimulationError(f"{object_ids.max()} objects in one scene; instance ids go up to {MAX_INSTANCE}")
    return Scene(vertices, faces, materials, labels, object_ids, main, drive_start, drive_end,
                 -(lane_width * (int(rng.integers(lanes)) + 0.5) + median / 2), preset.name, lanes, lane_width, median,
                 street_objects[0])


def _centre_line(rng: np.random.Generator, length: float, preset: Preset) -> np.ndarray:
    """(K, 2) centre line sampled every STEP_M: straights and circular arcs."""
    heading = rng.uniform(0.0, 2 * np.pi)
    headings = []
    while len(headings) * STEP_M < length:
        if rng.random() < preset.curviness:
            radius = rng.uniform(*preset.curve_radius)
            angle = rng.uniform(np.deg2rad(15), np.deg2rad(90)) * rng.choice([-1, 1])
            steps = max(1, int(abs(angle) * radius / STEP_M))
            headings.extend(heading + np.arange(1, steps + 1) * angle / steps)
            heading += angle
        else:
            headings.extend([heading] * int(rng.uniform(30.0, 150.0) / STEP_M))
    headings = np.array(headings[: int(length / STEP_M) + 1])
    steps = STEP_M * np.column_stack([np.cos(headings), np.sin(headings)])
    return np.vstack([[0.0, 0.0], np.cumsum(steps, axis=0)])


def _elevation(rng: np.random.Generator, s: np.ndarray, grade: float) -> np.ndarray:
    """A smooth road elevation profile (metres) whose grade stays below `grade`."""
    z = np.zeros_like(s)
    for _ in range(3):
        wavelength = rng.uniform(80.0, 600.0)
        amplitude = rng.uniform(0.0, grade / 3) * wavelength / (2 * np.pi)
        z += amplitude * np.sin(2 * np.pi * s / wavelength + rng.uniform(0, 2 * np.pi))
    return z


def _side_profile(rng: np.random.Generator, preset: Preset) -> SideProfile:
    rural = preset.kerb[1] == 0
    profile = SideProfile()
    if rural and rng.random() < 0.6:
        profile.ditch_depth = rng.uniform(0.3, 1.2)
        profile.ditch_offset = rng.uniform(1.0, 3.0)
        profile.ditch_width = rng.uniform(1.5, 3.0)
    if rng.random() < 0.6:
        profile.slope = rng.uniform(-1.0, 1.0) * preset.side_slope
        profile.slope_start = rng.uniform(2.0, 8.0) if rural else rng.uniform(4.0, 15.0)
        profile.slope_limit = rng.uniform(1.0, 6.0)
    return profile


def _cross_street(rng: np.random.Generator, main: Street, preset: Preset, s: float, side: int) -> Street:
    """A straight street leaving the main street at arc length `s` on `side`, with a gap in the main sidewalk."""
    sign = 1.0 if side == 1 else -1.0
    lanes_width = rng.uniform(*preset.lane_width)
    parking = np.array([rng.uniform(2.0, 2.4) if rng.random() < preset.parking * 0.6 else 0.0 for _ in range(2)])
    half = lanes_width + parking
    start = main.point(s, sign * main.half_width[side])
    _, heading, z0 = main.at(s)
    direction = heading + sign * np.pi / 2
    length = REACH_M + 12.0
    steps = np.arange(int(length / STEP_M) + 1) * STEP_M
    xy = start + steps[:, None] * [np.cos(direction), np.sin(direction)]
    z = float(z0) - main.camber * main.half_width[side] + rng.uniform(-0.03, 0.03) * steps
    sidewalk = np.array([rng.uniform(*preset.sidewalk) for _ in range(2)])
    mouth = main.sidewalk[side]
    street = Street(xy, z, half, main.kerb_height, sidewalk, parking=parking, gaps=[(0, 0.0, mouth), (1, 0.0, mouth)],
                    bumps=random_bumps(rng, rng.uniform(0.005, 0.02)))
    main.gaps.append((side, s - half.max() - 0.5, s + half.max() + 0.5))
    return street
