"""Procedural driving scenes: a main street with junctions, lots along it (building rows, houses with gardens,
parks, parking, industry, fields, forest, noise walls), parked cars, street furniture and terrain.

`build_scene(preset, drive_length_m, rng)` returns a `Scene`: one triangle mesh with a material per face, the
street the car drives along and the lane it keeps. Only what a sensor on the driven stretch can see within
the 20 m mapping range is built (objects up to REACH_M from the route).
"""

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mapsqueeze.data.simulator import objects
from mapsqueeze.data.simulator.shapes import MeshBuilder, boxes, rotation_z
from mapsqueeze.data.simulator.streets import FREE, SIDEWALK, STEP_M, Ground, SideProfile, Street, random_bumps
from mapsqueeze.errors import SimulationError

REACH_M = 28.0
"""Objects farther than this from the driven route are not built (they are beyond the 20 m mapping range)."""

LEAD_M = 30.0
"""Street built before the start and after the end of the driven stretch."""


@dataclass(frozen=True)
class Preset:
    """The statistics of one kind of environment (KITTI has city, residential, road and highway sequences)."""

    name: str
    description: str
    lanes: tuple[int, int]  # driving lanes per direction (min, max)
    lane_width: tuple[float, float]  # metres
    parking: float  # probability of a parking lane on each side
    kerb: tuple[float, float]  # kerb height range (metres); (0, 0): shoulders at road level
    sidewalk: tuple[float, float]  # sidewalk or shoulder width range (metres)
    junction_spacing: tuple[float, float] | None  # metres between cross streets; None: none
    lots: dict[str, float]  # lot kind -> weight
    street_trees: float  # probability that a sidewalk has a row of street trees
    speed: tuple[float, float]  # cruising speed range (m/s)
    curve_radius: tuple[float, float]  # metres
    curviness: float  # probability that a route piece is a curve
    grade: float  # steepest road grade (fraction)
    relief: float  # terrain relief away from the road (metres, 1 sigma)
    side_slope: float  # steepest cut / embankment slope (rise per metre)
    car_occupancy: tuple[float, float]  # fraction of the parking lane taken
    clutter_every: float  # metres of sidewalk per piece of clutter (mean)
    median: bool = False  # a concrete barrier between the directions


PRESETS: dict[str, Preset] = {
    "urban": Preset(
        name="urban", description="city streets: closed building rows, shops, dense parking, street furniture",
        lanes=(1, 2), lane_width=(2.9, 3.5), parking=0.8, kerb=(0.1, 0.18), sidewalk=(2.0, 5.0),
        junction_spacing=(60.0, 140.0),
        lots={"block": 0.62, "house": 0.08, "park": 0.08, "parking": 0.07, "industrial": 0.05, "vacant": 0.05,
              "tree_row": 0.05},
        street_trees=0.6, speed=(3.0, 12.0), curve_radius=(40.0, 200.0), curviness=0.25, grade=0.04, relief=0.3,
        side_slope=0.1, car_occupancy=(0.5, 0.95), clutter_every=7.0,
    ),
    "suburban": Preset(
        name="suburban", description="residential streets: houses with front gardens, hedges, fences, many trees",
        lanes=(1, 1), lane_width=(2.8, 3.4), parking=0.7, kerb=(0.08, 0.16), sidewalk=(1.5, 3.0),
        junction_spacing=(70.0, 200.0),
        lots={"house": 0.68, "park": 0.07, "block": 0.05, "parking": 0.04, "vacant": 0.05, "tree_row": 0.06,
              "field": 0.03, "industrial": 0.02},
        street_trees=0.6, speed=(3.0, 11.0), curve_radius=(30.0, 150.0), curviness=0.35, grade=0.05, relief=0.4,
        side_slope=0.2, car_occupancy=(0.3, 0.9), clutter_every=12.0,
    ),
    "rural": Preset(
        name="rural", description="country roads: fields, forest edges, tree rows, farms, ditches and slopes",
        lanes=(1, 1), lane_width=(2.8, 3.5), parking=0.0, kerb=(0.0, 0.0), sidewalk=(0.8, 2.0),
        junction_spacing=(150.0, 400.0),
        lots={"field": 0.3, "forest": 0.22, "tree_row": 0.16, "farm": 0.12, "house": 0.1, "vacant": 0.1},
        street_trees=0.0, speed=(8.0, 20.0), curve_radius=(60.0, 400.0), curviness=0.45, grade=0.06, relief=1.5,
        side_slope=0.6, car_occupancy=(0.0, 0.0), clutter_every=60.0,
    ),
    "highway": Preset(
        name="highway", description="motorway: several lanes, median barrier, guard rails, noise walls, embankments",
        lanes=(2, 3), lane_width=(3.5, 3.75), parking=0.0, kerb=(0.0, 0.0), sidewalk=(2.0, 3.5),
        junction_spacing=None,
        lots={"field": 0.2, "forest": 0.15, "tree_row": 0.15, "noise_wall": 0.25, "vacant": 0.25},
        street_trees=0.0, speed=(18.0, 30.0), curve_radius=(400.0, 1500.0), curviness=0.4, grade=0.04, relief=1.5,
        side_slope=0.5, car_occupancy=(0.0, 0.0), clutter_every=150.0, median=True,
    ),
}
"""Scene presets by CLI name."""


def get_preset(name: str) -> Preset:
    """The preset called `name` (a key of PRESETS)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise SimulationError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}") from None


@dataclass
class Scene:
    """A built scene: the mesh, the main street and the driven stretch (metres along it) and lane (offset)."""

    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    materials: np.ndarray  # (F,) int8, `shapes.Material` codes
    street: Street
    drive_start_m: float
    drive_end_m: float
    lane_offset_m: float  # lateral offset of the driven lane (negative: right of the centre line)
    preset: str

    @property
    def top_z(self) -> float:
        """Highest point of the scene (metres): no return can come from above it."""
        return float(self.vertices[:, 2].max())


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


class _Layout:
    """Places objects along streets and collects them into one mesh."""

    def __init__(self, rng: np.random.Generator, preset: Preset, ground: Ground, route: np.ndarray):
        self.rng = rng
        self.preset = preset
        self.ground = ground
        self.builder = MeshBuilder()
        self._route = cKDTree(route)

    def near_route(self, xy: np.ndarray, margin: float = 0.0) -> bool:
        return bool(self._route.query(np.atleast_2d(xy))[0].min() < REACH_M + margin)

    def frame(self, street: Street, side: int, s: float, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Rotation and ground-level origin of an object frame at (s, distance t from the centre line) on `side`:
        local y points away from the street, local x along it."""
        sign = 1.0 if side == 1 else -1.0
        xy = street.point(s, sign * t)
        _, heading, _ = street.at(s)
        yaw = float(heading) if side == 1 else float(heading) + np.pi
        return rotation_z(yaw), np.array([*xy, float(self.ground.height(xy)[0])])

    def footprint(self, street: Street, side: int, s: float, t: float, x0: float, x1: float, y0: float,
                  y1: float) -> np.ndarray:
        rotation, origin = self.frame(street, side, s, t)
        local = np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=np.float64)
        return (local @ rotation.T + origin)[:, :2]

    def place(self, part: MeshBuilder, street: Street, side: int, s: float, t: float,
              shift: tuple[float, float, float] = (0.0, 0.0, 0.0), z: float | None = None,
              yaw: float = 0.0, claim: tuple[float, float, float, float] | None = None,
              allowed: tuple[int, ...] = (FREE,)) -> bool:
        """Put `part` (built in its own frame) at (s, t) on `side`, shifted in that frame and turned by `yaw`.

        `claim` = (x0, x1, y0, y1) in the object frame: the ground it needs, which must be free and of an
        `allowed` class; the object is dropped (False) otherwise or when it is out of the route's reach.
        """
        rotation, origin = self.frame(street, side, s, t)
        if not self.near_route(origin[:2], margin=4.0):
            return False
        if claim is not None and not self.ground.claim(self.footprint(street, side, s, t, *claim), allowed):
            return False
        if z is not None:
            origin[2] = z
        turn = rotation_z(yaw)
        self.builder.extend(part, rotation @ turn, origin + rotation @ np.asarray(shift))
        return True


# --- lots ----------------------------------------------------------------------------------------------------


def _boundary(layout: _Layout, street: Street, side: int, s0: float, s1: float, t: float, kinds: list[str],
              weights: list[float]) -> None:
    """A hedge, fence or wall along the front of a lot (or nothing), with a gap for a gate or driveway."""
    rng = layout.rng
    kind = str(rng.choice(kinds, p=np.array(weights) / sum(weights)))
    if kind == "none" or s1 - s0 < 3:
        return
    gate = rng.uniform(s0 + 1, s1 - 2)
    for a, b in ((s0, gate), (gate + rng.uniform(1.0, 3.5), s1)):
        if b - a < 0.8:
            continue
        length = b - a
        part = objects.hedge(rng, length) if kind == "hedge" else objects.fence(rng, length, kind)
        layout.place(part, street, side, (a + b) / 2, t + 0.1, shift=(-length / 2, 0.0, 0.0),
                     claim=(-length / 2, length / 2, 0.0, 0.6))


def _lot_block(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    """A closed row of urban buildings of varied width, height and setback."""
    rng = layout.rng
    t = street.corridor(side)
    setback = rng.uniform(0.0, 1.5)
    s = s0
    while s < s1 - 5:
        width = min(rng.uniform(8.0, 25.0), s1 - s)
        depth = rng.uniform(10.0, 20.0)
        floors = int(rng.integers(2, 8))
        style = "industrial" if rng.random() < 0.05 else "urban"
        offset = setback + (rng.uniform(0.0, 1.0) if rng.random() < 0.3 else 0.0)
        part = objects.building(rng, width, depth, floors, style)
        centre = s + width / 2
        layout.place(part, street, side, centre, t + offset, shift=(-width / 2, 0.0, 0.0),
                     claim=(-width / 2, width / 2, 0.0, depth))
        if offset > 0.8:  # shrubs, planters or bikes in front of the building
            _scatter(layout, street, side, s, s + width, t + 0.3, t + offset - 0.3, int(rng.integers(0, 4)),
                     str(rng.choice(["bush", "bush", "clutter"])))
        s += width
        if rng.random() < 0.2:  # a passage or yard between buildings, behind a gate, fence or hedge
            gap = rng.uniform(2.0, 8.0)
            _boundary(layout, street, side, s, s + gap, t + setback, ["bars", "wall", "hedge", "boards", "none"],
                      [0.3, 0.2, 0.2, 0.1, 0.2])
            _scatter(layout, street, side, s, s + gap, t + setback + 1.0, t + setback + 10.0,
                     int(rng.integers(0, 3)), str(rng.choice(["tree", "bush", "clutter"])))
            s += gap


def _lot_house(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    """A detached house with a front garden: boundary hedge or fence, bushes, trees, a car on the drive."""
    rng = layout.rng
    t = street.corridor(side)
    width = s1 - s0
    _boundary(layout, street, side, s0 + 0.3, s1 - 0.3, t,
              ["hedge", "pickets", "bars", "boards", "wall", "wall_fence", "chainlink", "none"],
              [0.3, 0.1, 0.1, 0.05, 0.1, 0.08, 0.05, 0.22])
    setback = rng.uniform(3.0, 10.0)
    house_width = width * rng.uniform(0.45, 0.7)
    depth = rng.uniform(8.0, 13.0)
    centre = s0 + width * rng.uniform(0.35, 0.65)
    part = objects.building(rng, house_width, depth, int(rng.integers(1, 4)), "house")
    layout.place(part, street, side, centre, t + setback, shift=(-house_width / 2, 0.0, 0.0),
                 claim=(-house_width / 2, house_width / 2, 0.0, depth))
    if rng.random() < 0.4:  # garage beside the house
        garage = objects.building(rng, 3.5, 6.0, 1, "industrial")
        gx = centre + house_width / 2 + 2.2 if side == 1 else centre - house_width / 2 - 2.2
        layout.place(garage, street, side, gx, t + setback + 1.0, shift=(-1.75, 0.0, 0.0),
                     claim=(-1.75, 1.75, 0.0, 6.0))
    if rng.random() < 0.5:  # a car on the drive, nose to the street or to the house
        car, length, car_width = objects.vehicle(rng)
        ds = (house_width / 2 + 2.0) * (1 if rng.random() < 0.5 else -1)
        layout.place(car, street, side, centre + ds, t + 1.0 + length / 2, yaw=np.pi / 2 + rng.choice([0, np.pi]),
                     claim=(-car_width / 2, car_width / 2, -length / 2, length / 2))
    _scatter(layout, street, side, s0, s1, t + 0.8, t + setback - 0.5, int(rng.integers(1, 8)), "bush")
    _scatter(layout, street, side, s0, s1, t + 1.0, t + setback + depth + 5, int(rng.integers(1, 5)), "tree")
    _scatter(layout, street, side, s0, s1, t + 0.5, t + 2.5, int(rng.random() < 0.4), "clutter")


def _lot_park(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    if rng.random() < 0.5:
        _boundary(layout, street, side, s0, s1, t, ["bars", "pickets", "hedge", "wall"], [0.3, 0.2, 0.3, 0.2])
    area = (s1 - s0) * REACH_M
    if rng.random() < 0.4:  # a meadow
        patch = objects.tall_grass(rng, s1 - s0, rng.uniform(5.0, 20.0), rng.uniform(0.15, 0.6))
        layout.place(patch, street, side, (s0 + s1) / 2, t + 1.0, shift=(-(s1 - s0) / 2, 0.0, 0.0))
    _scatter(layout, street, side, s0, s1, t + 2.0, t + REACH_M, int(area / rng.uniform(60, 200)), "tree")
    _scatter(layout, street, side, s0, s1, t + 1.0, t + REACH_M, int(area / rng.uniform(40, 150)), "bush")
    _scatter(layout, street, side, s0, s1, t + 1.0, t + 6.0, int(rng.integers(0, 3)), "bench")


def _lot_parking(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    """A parking lot: rows of cars at right angles to the street behind a low wall, hedge or nothing."""
    rng = layout.rng
    t = street.corridor(side)
    _boundary(layout, street, side, s0, s1, t, ["wall", "hedge", "none", "bars"], [0.3, 0.2, 0.4, 0.1])
    for row_start in (t + 1.5, t + 12.0) if rng.random() < 0.5 else (t + 1.5,):
        s = s0 + 1.0
        while s < s1 - 2.5:
            if rng.random() < rng.uniform(0.5, 0.9):
                car, length, width = objects.vehicle(rng)
                layout.place(car, street, side, s + 1.25, row_start + length / 2,
                             yaw=np.pi / 2 + rng.choice([0, np.pi]) + rng.normal(0, 0.03),
                             claim=(-width / 2, width / 2, -length / 2, length / 2))
            s += 2.5
    _scatter(layout, street, side, s0, s1, t + 0.5, t + 15.0, int(rng.integers(0, 3)), "pole")


def _lot_industrial(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    _boundary(layout, street, side, s0, s1, t, ["chainlink", "bars", "wall", "none"], [0.4, 0.2, 0.2, 0.2])
    width = (s1 - s0) * rng.uniform(0.5, 0.9)
    depth = rng.uniform(15.0, 40.0)
    setback = rng.uniform(5.0, 15.0)
    centre = (s0 + s1) / 2
    layout.place(objects.building(rng, width, depth, 1, "industrial"), street, side, centre, t + setback,
                 shift=(-width / 2, 0.0, 0.0), claim=(-width / 2, width / 2, 0.0, depth))
    for _ in range(int(rng.integers(0, 4))):
        car, length, car_width = objects.vehicle(rng, "truck" if rng.random() < 0.4 else None)
        layout.place(car, street, side, rng.uniform(s0, s1), t + rng.uniform(2.0, setback),
                     yaw=rng.uniform(0, 2 * np.pi), claim=(-length / 2, length / 2, -car_width / 2, car_width / 2))
    _scatter(layout, street, side, s0, s1, t + 1.0, t + setback, int(rng.integers(0, 4)), "clutter")


def _lot_field(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    if rng.random() < 0.5:
        _boundary(layout, street, side, s0, s1, t + rng.uniform(0.5, 4.0), ["post_wire", "pickets", "railing"],
                  [0.7, 0.15, 0.15])
    if rng.random() < 0.6:  # weeds along the verge
        length = s1 - s0
        patch = objects.tall_grass(rng, length, rng.uniform(1.0, 4.0), rng.uniform(0.2, 0.8))
        layout.place(patch, street, side, (s0 + s1) / 2, t, shift=(-length / 2, 0.2, 0.0))
    _scatter(layout, street, side, s0, s1, t + 2.0, t + REACH_M, int(rng.integers(0, 4)), "bush")
    _scatter(layout, street, side, s0, s1, t + 3.0, t + REACH_M, int(rng.integers(0, 3)), "tree")


def _lot_forest(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    edge = t + rng.uniform(2.0, 10.0)
    depth = 12.0  # deeper trees are hidden behind the first rows
    area = (s1 - s0) * depth
    conifer = rng.random()
    _scatter(layout, street, side, s0, s1, edge, edge + depth, int(area / rng.uniform(20, 50)), "tree",
             conifer=conifer)
    _scatter(layout, street, side, s0, s1, edge - 1.0, edge + depth, int(area / rng.uniform(25, 70)), "bush")


def _lot_tree_row(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side) + rng.uniform(0.5, 5.0)
    spacing = rng.uniform(5.0, 14.0)
    for s in np.arange(s0 + spacing / 2, s1, spacing):
        layout.place(objects.tree(rng, conifer=rng.random() < 0.2), street, side, s + rng.normal(0, 0.5),
                     t + rng.normal(0, 0.3), claim=(-0.3, 0.3, -0.3, 0.3))
    if rng.random() < 0.5:
        length = s1 - s0
        layout.place(objects.hedge(rng, length), street, side, (s0 + s1) / 2, t + 1.5, shift=(-length / 2, 0, 0),
                     claim=(-length / 2, length / 2, 0.0, 1.0))


def _lot_farm(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    _boundary(layout, street, side, s0, s1, t + 1.0, ["post_wire", "boards", "hedge", "none"], [0.3, 0.2, 0.2, 0.3])
    for _ in range(int(rng.integers(1, 3))):
        width, depth = rng.uniform(8.0, 25.0), rng.uniform(8.0, 18.0)
        style = "house" if rng.random() < 0.5 else "industrial"
        centre = rng.uniform(s0 + width / 2, max(s0 + width / 2 + 0.1, s1 - width / 2))
        layout.place(objects.building(rng, width, depth, int(rng.integers(1, 3)), style), street, side, centre,
                     t + rng.uniform(6.0, 18.0), shift=(-width / 2, 0, 0), claim=(-width / 2, width / 2, 0, depth))
    _scatter(layout, street, side, s0, s1, t + 2.0, t + REACH_M, int(rng.integers(1, 5)), "tree")
    _scatter(layout, street, side, s0, s1, t + 2.0, t + 15.0, int(rng.integers(0, 3)), "clutter")


def _lot_noise_wall(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side) + rng.uniform(1.0, 6.0)
    length = s1 - s0
    height = rng.uniform(2.5, 5.0)
    wall = MeshBuilder()
    wall.add(boxes([[length / 2, 0.15, height / 2 - 0.3]], [[length, 0.3, height + 0.6]]))
    posts = np.arange(0.0, length, rng.uniform(3.0, 5.0))
    wall.add(boxes(np.column_stack([posts, np.full(len(posts), -0.1), np.full(len(posts), height / 2)]),
                           [0.2, 0.2, height]))
    layout.place(wall, street, side, (s0 + s1) / 2, t, shift=(-length / 2, 0, 0),
                 claim=(-length / 2, length / 2, -0.2, 0.4))
    _scatter(layout, street, side, s0, s1, street.corridor(side) + 0.5, t - 0.5, int(rng.integers(0, 6)), "bush")


def _lot_vacant(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    if rng.random() < 0.6:  # weeds
        depth = rng.uniform(3.0, 15.0)
        patch = objects.tall_grass(rng, s1 - s0, depth, rng.uniform(0.2, 1.0))
        layout.place(patch, street, side, (s0 + s1) / 2, t + 0.5, shift=(-(s1 - s0) / 2, 0.0, 0.0))
    _scatter(layout, street, side, s0, s1, t + 1.0, t + REACH_M, int(rng.integers(0, 3)), "bush")
    _scatter(layout, street, side, s0, s1, t + 1.0, t + 10.0, int(rng.integers(0, 3)), "clutter")


LOTS: dict[str, tuple[Callable[[_Layout, Street, int, float, float], None], tuple[float, float]]] = {
    "block": (_lot_block, (30.0, 120.0)),
    "house": (_lot_house, (12.0, 25.0)),
    "park": (_lot_park, (25.0, 80.0)),
    "parking": (_lot_parking, (20.0, 50.0)),
    "industrial": (_lot_industrial, (30.0, 80.0)),
    "field": (_lot_field, (30.0, 150.0)),
    "forest": (_lot_forest, (30.0, 150.0)),
    "tree_row": (_lot_tree_row, (30.0, 120.0)),
    "farm": (_lot_farm, (30.0, 80.0)),
    "noise_wall": (_lot_noise_wall, (50.0, 200.0)),
    "vacant": (_lot_vacant, (10.0, 40.0)),
}
"""Lot kind -> (generator(layout, street, side, s0, s1), lot length range in metres)."""


def _scatter(layout: _Layout, street: Street, side: int, s0: float, s1: float, t0: float, t1: float, count: int,
             kind: str, conifer: float = 0.15) -> None:
    """`count` objects of `kind` (tree, bush, bench, clutter, pole) at random free spots of a lot."""
    rng = layout.rng
    for _ in range(count):
        s, t = rng.uniform(s0, s1), rng.uniform(t0, max(t0 + 0.1, t1))
        if kind == "tree":
            part, radius = objects.tree(rng, conifer=rng.random() < conifer), 0.4
        elif kind == "bush":
            radius = rng.uniform(0.4, 1.6)
            part = objects.bush(rng, radius)
        elif kind == "bench":
            part, radius = objects.clutter(rng, "bench"), 1.0
        elif kind == "pole":
            part, radius = objects.pole(rng, "street_light"), 0.2
        else:
            part, radius = objects.clutter(rng, str(rng.choice(objects.CLUTTER_KINDS))), 0.6
        layout.place(part, street, side, s, t, yaw=rng.uniform(0, 2 * np.pi), claim=(-radius, radius, -radius, radius))


# --- street-side furniture and parked cars ----------------------------------------------------------------------


def _furnish(layout: _Layout, street: Street, side: int, s0: float, s1: float, parking_width: float) -> None:
    """Parked cars in the parking lane, then street trees, lights, signs, poles and clutter on the sidewalk."""
    rng = layout.rng
    preset = layout.preset
    sign = 1.0 if side == 1 else -1.0
    half = street.half_width[side]
    if parking_width > 0:
        occupancy = rng.uniform(*preset.car_occupancy)
        s = s0 + rng.uniform(0.0, 3.0)
        while s < s1:
            car, length, width = objects.vehicle(rng)
            if rng.random() < occupancy:
                t = half - parking_width / 2 + rng.normal(0.0, 0.15)
                z = float(street.surface_z(s + length / 2, sign * t))
                flip = np.pi if rng.random() < 0.1 else 0.0
                layout.place(car, street, side, s + length / 2, t, z=z, yaw=flip + rng.normal(0.0, 0.02))
            s += length + rng.uniform(0.4, 2.5)
    width = street.sidewalk[side]
    if width <= 0:
        return
    kerb_t = half + 0.5
    if street.kerb_height == 0:  # country road: delineator posts and guard rails on the shoulder
        if rng.random() < 0.5:
            for s in np.arange(s0, s1, 50.0):
                layout.place(objects.pole(rng, "post"), street, side, s, half + width - 0.3,
                             claim=(-0.1, 0.1, -0.1, 0.1), allowed=(SIDEWALK, FREE))
        if rng.random() < (0.7 if preset.name == "highway" else 0.25):
            length = s1 - s0
            layout.place(objects.guard_rail(length), street, side, (s0 + s1) / 2, half + width - 0.5,
                         shift=(-length / 2, 0, 0), yaw=0.0)
        for s in np.sort(rng.uniform(s0, s1, int((s1 - s0) / 120))):
            layout.place(objects.pole(rng, "sign"), street, side, s, half + width + 0.3, yaw=np.pi,
                         claim=(-0.2, 0.2, -0.2, 0.2), allowed=(SIDEWALK, FREE))
        return
    if rng.random() < preset.street_trees:
        spacing = rng.uniform(7.0, 16.0)
        t = half + min(width - 0.6, rng.uniform(0.8, 1.5))
        for s in np.arange(s0 + rng.uniform(0, spacing), s1, spacing):
            if rng.random() < 0.9:
                layout.place(objects.tree(rng, scale=rng.uniform(0.7, 1.1)), street, side, s, t,
                             claim=(-0.3, 0.3, -0.3, 0.3), allowed=(SIDEWALK,))
    spacing = rng.uniform(20.0, 40.0)
    for s in np.arange(s0 + rng.uniform(0, spacing), s1, spacing):
        layout.place(objects.pole(rng, "street_light"), street, side, s, kerb_t, yaw=np.pi,
                     claim=(-0.2, 0.2, -0.2, 0.2), allowed=(SIDEWALK,))
    for s in rng.uniform(s0, s1, rng.poisson((s1 - s0) / 40.0)):
        kind = str(rng.choice(["sign", "sign", "traffic_light", "bollard", "utility"]))
        layout.place(objects.pole(rng, kind), street, side, s, kerb_t, yaw=np.pi,
                     claim=(-0.2, 0.2, -0.2, 0.2), allowed=(SIDEWALK,))
    for s in rng.uniform(s0, s1, rng.poisson((s1 - s0) / preset.clutter_every)):
        kind = str(rng.choice(objects.CLUTTER_KINDS))
        t = half + rng.uniform(0.5, max(0.6, width - 0.5))
        layout.place(objects.clutter(rng, kind), street, side, s, t, yaw=rng.choice([0.0, np.pi / 2, np.pi]),
                     claim=(-0.5, 0.5, -0.5, 0.5), allowed=(SIDEWALK,))


def _utility_wires(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    """A line of utility poles with two to four sagging wires hung from their cross-arms."""
    rng = layout.rng
    t = street.corridor(side) + rng.uniform(0.3, 2.0)
    spacing = rng.uniform(30.0, 50.0)
    anchors = []  # (top of the pole, direction of its cross-arm)
    for s in np.arange(s0, s1, spacing):
        if layout.place(objects.pole(rng, "utility"), street, side, s, t, claim=(-0.2, 0.2, -0.2, 0.2),
                        allowed=(SIDEWALK, FREE)):
            rotation, origin = layout.frame(street, side, s, t)
            anchors.append((origin + [0.0, 0.0, 6.4], rotation[:, 1]))
    offsets = np.linspace(-0.7, 0.7, int(rng.integers(2, 5)))
    u = np.linspace(0.0, 1.0, 16)[:, None]
    for (a, arm_a), (b, arm_b) in zip(anchors[:-1], anchors[1:]):
        for offset in offsets:
            start, end = a + offset * arm_a, b + offset * arm_b
            points = start + (end - start) * u - [0.0, 0.0, 2.4] * u * (1 - u)  # 0.6 m sag
            layout.builder.add(objects.tubes(points[:-1], points[1:], 0.012, 3))


# --- the scene -------------------------------------------------------------------------------------------------


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
    layout = _Layout(rng, preset, ground, route)
    for street in streets:
        layout.builder.extend(street.mesh(), np.eye(3), np.zeros(3))
    layout.builder.extend(ground.mesh(), np.eye(3), np.zeros(3))
    if preset.median:  # in 20 m pieces that follow the curves
        for a in np.arange(0.0, length - 1.0, 20.0):
            rotation, origin = layout.frame(main, 1, a, 0.0)
            origin[2] = float(main.at(a)[2])
            layout.builder.extend(objects.jersey_barrier(min(20.0, length - a)), rotation, origin)
    for street in streets:
        for side in (0, 1):
            _fill_side(layout, street, side, 0.0, street.length)
            for a, b in _open_spans(street, side, 0.0, street.length):
                _furnish(layout, street, side, a, b, street.parking[side])
    if rng.random() < (0.2 if preset.name in ("urban", "highway") else 0.5):
        _utility_wires(layout, main, int(rng.integers(2)), 0.0, length)
    vertices, faces, materials = layout.builder.build()
    return Scene(vertices, faces, materials, main, drive_start, drive_end,
                 -(lane_width * (int(rng.integers(lanes)) + 0.5) + median / 2), preset.name)


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


def _open_spans(street: Street, side: int, s0: float, s1: float) -> list[tuple[float, float]]:
    """Pieces of [s0, s1] on `side` that are not a junction mouth (gap), with 3 m clearance around mouths."""
    spans = [(s0, s1)]
    for gap_side, a, b in street.gaps:
        if gap_side != side:
            continue
        spans = [piece for start, end in spans
                 for piece in ((start, min(end, a - 3.0)), (max(start, b + 3.0), end)) if piece[1] - piece[0] > 1.0]
    return spans


def _fill_side(layout: _Layout, street: Street, side: int, s0: float, s1: float) -> None:
    """Lots of random kinds one after another along [s0, s1] on `side`, skipping junction mouths."""
    rng = layout.rng
    kinds = list(layout.preset.lots)
    weights = np.array([layout.preset.lots[kind] for kind in kinds])
    for a, b in _open_spans(street, side, s0, s1):
        s = a
        while s < b - 3.0:
            kind = str(rng.choice(kinds, p=weights / weights.sum()))
            generator, (low, high) = LOTS[kind]
            end = min(b, s + rng.uniform(low, high))
            generator(layout, street, side, s, end)
            s = end + rng.uniform(0.0, 2.0)
