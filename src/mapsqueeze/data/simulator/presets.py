"""Scene presets: the statistics of one kind of environment (street layout, lot mix, speeds, relief, clutter)."""

from dataclasses import dataclass

from mapsqueeze.errors import SimulationError


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

