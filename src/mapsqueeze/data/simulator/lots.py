"""What fills a street side: lots of random kinds one after another (building rows, houses with gardens, parks,
parking, industry, fields, forest, noise walls), then street furniture, parked cars and utility wires."""

from collections.abc import Callable

import numpy as np

from mapsqueeze.data.simulator import buildings, objects
from mapsqueeze.data.simulator.layout import REACH_M, Layout
from mapsqueeze.data.simulator.shapes import MeshBuilder, Semantic, boxes, tubes
from mapsqueeze.data.simulator.streets import FREE, SIDEWALK, Street


def _boundary(layout: Layout, street: Street, side: int, s0: float, s1: float, t: float, kinds: list[str],
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


def _lot_block(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
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
        part = buildings.building(rng, width, depth, floors, style)
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


def _lot_house(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
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
    part = buildings.building(rng, house_width, depth, int(rng.integers(1, 4)), "house")
    layout.place(part, street, side, centre, t + setback, shift=(-house_width / 2, 0.0, 0.0),
                 claim=(-house_width / 2, house_width / 2, 0.0, depth))
    if rng.random() < 0.4:  # garage beside the house
        garage = buildings.building(rng, 3.5, 6.0, 1, "industrial")
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


def _lot_park(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
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


def _lot_parking(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
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


def _lot_industrial(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    _boundary(layout, street, side, s0, s1, t, ["chainlink", "bars", "wall", "none"], [0.4, 0.2, 0.2, 0.2])
    width = (s1 - s0) * rng.uniform(0.5, 0.9)
    depth = rng.uniform(15.0, 40.0)
    setback = rng.uniform(5.0, 15.0)
    centre = (s0 + s1) / 2
    layout.place(buildings.building(rng, width, depth, 1, "industrial"), street, side, centre, t + setback,
                 shift=(-width / 2, 0.0, 0.0), claim=(-width / 2, width / 2, 0.0, depth))
    for _ in range(int(rng.integers(0, 4))):
        car, length, car_width = objects.vehicle(rng, "truck" if rng.random() < 0.4 else None)
        layout.place(car, street, side, rng.uniform(s0, s1), t + rng.uniform(2.0, setback),
                     yaw=rng.uniform(0, 2 * np.pi), claim=(-length / 2, length / 2, -car_width / 2, car_width / 2))
    _scatter(layout, street, side, s0, s1, t + 1.0, t + setback, int(rng.integers(0, 4)), "clutter")


def _lot_field(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
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


def _lot_forest(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    edge = t + rng.uniform(2.0, 10.0)
    depth = 12.0  # deeper trees are hidden behind the first rows
    area = (s1 - s0) * depth
    conifer = rng.random()
    _scatter(layout, street, side, s0, s1, edge, edge + depth, int(area / rng.uniform(20, 50)), "tree",
             conifer=conifer)
    _scatter(layout, street, side, s0, s1, edge - 1.0, edge + depth, int(area / rng.uniform(25, 70)), "bush")


def _lot_tree_row(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
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


def _lot_farm(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    _boundary(layout, street, side, s0, s1, t + 1.0, ["post_wire", "boards", "hedge", "none"], [0.3, 0.2, 0.2, 0.3])
    for _ in range(int(rng.integers(1, 3))):
        width, depth = rng.uniform(8.0, 25.0), rng.uniform(8.0, 18.0)
        style = "house" if rng.random() < 0.5 else "industrial"
        centre = rng.uniform(s0 + width / 2, max(s0 + width / 2 + 0.1, s1 - width / 2))
        layout.place(buildings.building(rng, width, depth, int(rng.integers(1, 3)), style), street, side, centre,
                     t + rng.uniform(6.0, 18.0), shift=(-width / 2, 0, 0), claim=(-width / 2, width / 2, 0, depth))
    _scatter(layout, street, side, s0, s1, t + 2.0, t + REACH_M, int(rng.integers(1, 5)), "tree")
    _scatter(layout, street, side, s0, s1, t + 2.0, t + 15.0, int(rng.integers(0, 3)), "clutter")


def _lot_noise_wall(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side) + rng.uniform(1.0, 6.0)
    length = s1 - s0
    height = rng.uniform(2.5, 5.0)
    wall = MeshBuilder(Semantic.OTHER_STRUCTURE)
    wall.add(boxes([[length / 2, 0.15, height / 2 - 0.3]], [[length, 0.3, height + 0.6]]))
    posts = np.arange(0.0, length, rng.uniform(3.0, 5.0))
    wall.add(boxes(np.column_stack([posts, np.full(len(posts), -0.1), np.full(len(posts), height / 2)]),
                           [0.2, 0.2, height]))
    layout.place(wall, street, side, (s0 + s1) / 2, t, shift=(-length / 2, 0, 0),
                 claim=(-length / 2, length / 2, -0.2, 0.4))
    _scatter(layout, street, side, s0, s1, street.corridor(side) + 0.5, t - 0.5, int(rng.integers(0, 6)), "bush")


def _lot_vacant(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
    rng = layout.rng
    t = street.corridor(side)
    if rng.random() < 0.6:  # weeds
        depth = rng.uniform(3.0, 15.0)
        patch = objects.tall_grass(rng, s1 - s0, depth, rng.uniform(0.2, 1.0))
        layout.place(patch, street, side, (s0 + s1) / 2, t + 0.5, shift=(-(s1 - s0) / 2, 0.0, 0.0))
    _scatter(layout, street, side, s0, s1, t + 1.0, t + REACH_M, int(rng.integers(0, 3)), "bush")
    _scatter(layout, street, side, s0, s1, t + 1.0, t + 10.0, int(rng.integers(0, 3)), "clutter")


LOTS: dict[str, tuple[Callable[[Layout, Street, int, float, float], None], tuple[float, float]]] = {
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


def _scatter(layout: Layout, street: Street, side: int, s0: float, s1: float, t0: float, t1: float, count: int,
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


def furnish(layout: Layout, street: Street, side: int, s0: float, s1: float, parking_width: float) -> None:
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


def utility_wires(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
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
            layout.builder.add(tubes(points[:-1], points[1:], 0.012, 3), label=Semantic.OTHER_STRUCTURE)


def open_spans(street: Street, side: int, s0: float, s1: float) -> list[tuple[float, float]]:
    """Pieces of [s0, s1] on `side` that are not a junction mouth (gap), with 3 m clearance around mouths."""
    spans = [(s0, s1)]
    for gap_side, a, b in street.gaps:
        if gap_side != side:
            continue
        spans = [piece for start, end in spans
                 for piece in ((start, min(end, a - 3.0)), (max(start, b + 3.0), end)) if piece[1] - piece[0] > 1.0]
    return spans


def fill_side(layout: Layout, street: Street, side: int, s0: float, s1: float) -> None:
    """Lots of random kinds one after another along [s0, s1] on `side`, skipping junction mouths."""
    rng = layout.rng
    kinds = list(layout.preset.lots)
    weights = np.array([layout.preset.lots[kind] for kind in kinds])
    for a, b in open_spans(street, side, s0, s1):
        s = a
        while s < b - 3.0:
            kind = str(rng.choice(kinds, p=weights / weights.sum()))
            generator, (low, high) = LOTS[kind]
            end = min(b, s + rng.uniform(low, high))
            generator(layout, street, side, s, end)
            s = end + rng.uniform(0.0, 2.0)
