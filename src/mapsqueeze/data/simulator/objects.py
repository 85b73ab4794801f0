"""Procedural scene objects (buildings are in `buildings`), each built in its own frame and returned as a `MeshBuilder`.

Object frame (metres): x runs along the street, y points away from the street (into the lot), z is up; the origin
lies on the ground at the middle of the object's street-side edge. Every generator takes a seeded
`np.random.Generator` and draws its own proportions, so no two buildings, cars or trees are alike.
"""

import numpy as np

from mapsqueeze.data.simulator.shapes import (
    Material,
    MeshBuilder,
    Semantic,
    boxes,
    prism,
    quads,
    random_triangles,
    tubes,
)

# --- vehicles ----------------------------------------------------------------------------------------------------

_VEHICLE_KINDS = ("sedan", "hatchback", "wagon", "suv", "van", "pickup", "truck", "small")
_VEHICLE_WEIGHTS = np.array([0.3, 0.2, 0.15, 0.15, 0.08, 0.03, 0.03, 0.06])


def vehicle(rng: np.random.Generator, kind: str | None = None) -> tuple[MeshBuilder, float, float]:
    """A parked vehicle centred on the origin, x forward: (mesh, length, width) in metres.

    Body: a convex side profile extruded over the width; cabin: a glass greenhouse with a solid roof and
    pillars; four wheels under the arches and ground clearance, so rays pass under the car as in real scans.
    """
    kind = kind or str(rng.choice(_VEHICLE_KINDS, p=_VEHICLE_WEIGHTS))
    dims = {  # length, width, body-top height, roof height, clearance
        "sedan": (4.6, 1.8, 0.95, 1.45, 0.15), "hatchback": (4.1, 1.75, 0.95, 1.48, 0.15),
        "wagon": (4.8, 1.82, 0.98, 1.5, 0.16), "suv": (4.7, 1.9, 1.1, 1.75, 0.22),
        "van": (5.2, 2.0, 1.05, 2.2, 0.2), "pickup": (5.4, 2.0, 1.1, 1.85, 0.25),
        "truck": (7.5, 2.4, 1.3, 3.2, 0.3), "small": (3.4, 1.6, 0.9, 1.5, 0.14),
    }[kind]
    scale = rng.uniform(0.93, 1.07, 5)
    length, width, belt, roof, clearance = np.array(dims) * scale
    builder = MeshBuilder(Semantic.TRUCK if kind == "truck" else Semantic.CAR, countable=True)
    half = length / 2
    bumper = clearance + 0.12
    body = np.array([[-half, bumper], [-half + 0.15, clearance], [half - 0.15, clearance], [half, bumper],
                     [half, belt - 0.25], [half - 0.35, belt], [-half + 0.25, belt], [-half, belt - 0.1]])
    if kind in ("truck", "pickup"):
        cab_length = 2.3 if kind == "truck" else 2.6
        cab_x0 = half - cab_length
        builder.add(prism(body, width))
        builder.add(prism(np.array([[cab_x0, belt], [half - 0.2, belt], [half - 0.5, roof], [cab_x0, roof]]),
                          width - 0.1), Material.GLASS)
        cab_roof = half - 0.5 - cab_x0
        builder.add(boxes([[cab_x0 + cab_roof / 2, 0.0, roof - 0.05]], [[cab_roof, width - 0.1, 0.1]]))
        if kind == "truck":
            cargo = (cab_x0 - 0.2 + half) / 2
            builder.add(boxes([[-half + cargo, 0.0, (belt - 0.3 + roof + 0.2) / 2]],
                              [[2 * cargo, width, roof + 0.2 - belt + 0.3]]))
        else:
            for y in (-width / 2 + 0.05, width / 2 - 0.05):  # bed walls
                builder.add(boxes([[(-half + cab_x0) / 2, y, belt + 0.25]], [[cab_x0 + half, 0.06, 0.5]]))
    else:
        if kind == "van":
            cabin = [[-half + 0.05, belt], [half - 0.6, belt], [half - 1.3, roof], [-half + 0.1, roof]]
        elif kind in ("hatchback", "wagon", "suv", "small"):
            rear_top = -half + rng.uniform(0.15, 0.5)
            cabin = [[-half + 0.1, belt], [half - 1.1, belt], [half - 1.9, roof], [rear_top, roof]]
        else:
            cabin = [[-half + 0.7, belt], [half - 1.2, belt], [half - 2.0, roof], [-half + 1.3, roof]]
        cabin = np.array(cabin)
        builder.add(prism(body, width))
        builder.add(prism(cabin, width - 0.14), Material.GLASS)
        top = cabin[2:, 0]
        builder.add(boxes([[top.mean(), 0.0, roof - 0.04]], [[top[0] - top[1] + 0.05, width - 0.16, 0.08]]))
        for x in (cabin[:2, 0].mean(), cabin[[0, 3], 0].mean()):  # B- and C-pillar-ish
            for y in (-(width - 0.14) / 2, (width - 0.14) / 2):
                builder.add(boxes([[x, y, (belt + roof) / 2]], [[0.12, 0.03, roof - belt]]))
    wheel_radius = rng.uniform(0.29, 0.36) * (1.3 if kind == "truck" else 1.0)
    wheelbase = length * rng.uniform(0.55, 0.62)
    axles = [-wheelbase / 2, wheelbase / 2]
    starts, ends = [], []
    for x in axles:
        for sign in (-1, 1):
            starts.append([x, sign * (width / 2 - 0.25), wheel_radius])
            ends.append([x, sign * (width / 2 + 0.01), wheel_radius])
    builder.add(tubes(np.array(starts), np.array(ends), wheel_radius, 10))
    for sign in (-1, 1):  # mirrors
        builder.add(boxes([[half - 1.5 if kind != "truck" else half - 0.3, sign * (width / 2 + 0.1), belt + 0.1]],
                          [[0.12, 0.2, 0.14]]))
    return builder, float(length), float(width)


# --- vegetation --------------------------------------------------------------------------------------------------


def _shell_points(rng: np.random.Generator, centre: np.ndarray, radii: np.ndarray, n: int,
                  shell: float) -> np.ndarray:
    """`n` points in an ellipsoid, concentrated in its outer `shell` fraction (foliage grows outside)."""
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    fraction = np.clip(1.0 - np.abs(rng.normal(0.0, shell, n)), 0.05, 1.0)
    return centre + direction * fraction[:, None] * radii


def _leaf_count(radii: np.ndarray, density: float) -> int:
    """Leaves for an ellipsoid: `density` per square metre of its (approximate) surface."""
    a, b, c = radii
    area = 4 * np.pi * ((a * b) ** 1.6 + (a * c) ** 1.6 + (b * c) ** 1.6) ** (1 / 1.6) / 3 ** (1 / 1.6)
    return int(area * density)


def tree(rng: np.random.Generator, conifer: bool = False, scale: float = 1.0) -> MeshBuilder:
    """A tree at the origin: leaning, tapering trunk with a few branches and an irregular, porous crown.

    The crown is a union of 3-8 random ellipsoids filled with small randomly oriented leaf triangles, most in
    their outer shell, so some rays reach the trunk and the far side while others stop at the first leaves.
    """
    builder = MeshBuilder(Semantic.TRUNK, countable=True)
    height = rng.uniform(5.0, 14.0) * scale
    trunk_radius = rng.uniform(0.08, 0.3) * np.sqrt(scale)
    crown_base = rng.uniform(0.2, 0.5) * height if not conifer else rng.uniform(0.05, 0.3) * height
    lean = rng.normal(0.0, 0.04, 2)
    points = [np.zeros(3)]
    for level in (0.5, 1.0):
        z = crown_base + (height - crown_base) * 0.5 * level
        points.append(np.array([*(lean * z + rng.normal(0, 0.05, 2)), z]))
    points = np.array(points)
    radii = trunk_radius * np.array([1.0, 0.8, 0.55])
    builder.add(tubes(points[:-1], points[1:], radii[:-1], 8, radii[1:]))
    density = rng.uniform(40.0, 110.0)
    leaf_size = rng.uniform(0.08, 0.22)
    leaves = []
    if conifer:
        levels = np.linspace(crown_base, height, 6)
        for z0, z1 in zip(levels[:-1], levels[1:]):
            radius = (height - z0) / (height - crown_base) * rng.uniform(1.2, 2.5) * scale
            centre = np.array([*(lean * z0), (z0 + z1) / 2])
            shape = np.array([radius, radius, (z1 - z0) * 0.8])
            leaves.append(_shell_points(rng, centre, shape, _leaf_count(shape, density), 0.3))
    else:
        crown_height = height - crown_base
        crown_radius = crown_height * rng.uniform(0.35, 0.6)
        centre = np.array([*(lean * (crown_base + crown_height / 2)), crown_base + crown_height / 2])
        branch_starts, branch_ends = [], []
        for _ in range(int(rng.integers(3, 9))):
            offset = rng.normal(0.0, 1.0, 3) * [crown_radius * 0.5, crown_radius * 0.5, crown_height * 0.2]
            shape = rng.uniform(0.35, 0.7, 3) * [crown_radius, crown_radius, crown_height * 0.6]
            leaves.append(_shell_points(rng, centre + offset, shape, _leaf_count(shape, density), 0.25))
            branch_starts.append(points[1] + [0, 0, rng.uniform(-0.3, 0.3) * crown_height])
            branch_ends.append(centre + offset)
        builder.add(tubes(np.array(branch_starts), np.array(branch_ends), trunk_radius * 0.35, 5,
                          trunk_radius * 0.1))
    leaves = np.concatenate(leaves)
    builder.add(random_triangles(leaves, rng.uniform(0.6, 1.4, len(leaves)) * leaf_size, rng), Material.VEGETATION,
                Semantic.VEGETATION)
    return builder


def bush(rng: np.random.Generator, radius: float) -> MeshBuilder:
    """A bush of 1-4 overlapping leafy clumps on the ground around the origin (about `radius` metres)."""
    builder = MeshBuilder(Semantic.VEGETATION, countable=True)
    density = rng.uniform(60.0, 160.0)
    leaves = []
    for _ in range(int(rng.integers(1, 5))):
        r = radius * rng.uniform(0.5, 1.0)
        shape = np.array([r, r * rng.uniform(0.7, 1.3), r * rng.uniform(0.5, 1.0)])
        centre = np.array([*rng.normal(0.0, radius * 0.4, 2), shape[2] * rng.uniform(0.5, 0.9)])
        leaves.append(_shell_points(rng, centre, shape, _leaf_count(shape, density), 0.3))
    leaves = np.concatenate(leaves)
    builder.add(random_triangles(leaves, rng.uniform(0.08, 0.2, len(leaves)), rng), Material.VEGETATION)
    return builder


def hedge(rng: np.random.Generator, length: float) -> MeshBuilder:
    """A trimmed hedge along x from 0 to `length`, starting at y = 0: a leafy box with a fuzzy surface."""
    builder = MeshBuilder(Semantic.VEGETATION)
    height = rng.uniform(0.8, 2.6)
    thickness = rng.uniform(0.5, 1.3)
    density = rng.uniform(120.0, 220.0)
    faces = [  # (origin, u axis, v axis, outward normal) of each visible side
        ([0, 0, 0], [length, 0, 0], [0, 0, height], [0, -1, 0]),
        ([0, thickness, 0], [length, 0, 0], [0, 0, height], [0, 1, 0]),
        ([0, 0, height], [length, 0, 0], [0, thickness, 0], [0, 0, 1]),
        ([0, 0, 0], [0, thickness, 0], [0, 0, height], [-1, 0, 0]),
        ([length, 0, 0], [0, thickness, 0], [0, 0, height], [1, 0, 0]),
    ]
    leaves = []
    for origin, u, v, normal in faces:
        u, v, normal = np.array(u, float), np.array(v, float), np.array(normal, float)
        n = int(np.linalg.norm(u) * np.linalg.norm(v) * density)
        a, b = rng.random(n), rng.random(n)
        wavelength = rng.uniform(0.8, 3.0)  # the surface bulges in and out like a real trimmed hedge
        wobble = 0.06 * (1 + np.sin(2 * np.pi * a * np.linalg.norm(u) / wavelength + rng.uniform(0, 6.3)))
        depth = np.abs(rng.normal(0.0, 0.1, n)) + wobble
        leaves.append(np.array(origin) + a[:, None] * u + b[:, None] * v - depth[:, None] * normal)
    leaves = np.concatenate(leaves)
    builder.add(random_triangles(leaves, rng.uniform(0.06, 0.16, len(leaves)), rng), Material.VEGETATION)
    return builder


def tall_grass(rng: np.random.Generator, size_x: float, size_y: float, height: float) -> MeshBuilder:
    """Weeds / long grass over a size_x by size_y patch (origin at its corner), up to `height` metres."""
    builder = MeshBuilder(Semantic.TERRAIN)
    n = int(size_x * size_y * rng.uniform(20.0, 60.0))
    centres = np.column_stack([rng.random(n) * size_x, rng.random(n) * size_y, rng.random(n) ** 1.5 * height])
    builder.add(random_triangles(centres, rng.uniform(0.05, 0.15, n), rng), Material.VEGETATION)
    return builder


# --- fences, walls, rails ----------------------------------------------------------------------------------------

FENCE_KINDS = ("pickets", "bars", "boards", "chainlink", "wall", "wall_fence", "post_wire", "railing")


def fence(rng: np.random.Generator, length: float, kind: str) -> MeshBuilder:
    """A fence or wall along x from 0 to `length` at y = 0 (see FENCE_KINDS); thin parts are real thin geometry."""
    builder = MeshBuilder(Semantic.FENCE)
    height = {"pickets": (0.8, 1.4), "bars": (1.0, 2.2), "boards": (1.2, 2.0), "chainlink": (1.2, 2.5),
              "wall": (0.4, 2.4), "wall_fence": (0.4, 0.9), "post_wire": (1.0, 1.4), "railing": (0.9, 1.2)}[kind]
    height = rng.uniform(*height)
    post_spacing = rng.uniform(2.0, 3.0)
    posts = np.linspace(0.0, length, max(2, int(length / post_spacing) + 1))
    if kind in ("wall", "wall_fence"):
        thickness = rng.uniform(0.15, 0.45)
        builder.add(boxes([[length / 2, thickness / 2, height / 2 - 0.2]], [[length, thickness, height + 0.4]]))
        if rng.random() < 0.5:  # coping
            builder.add(boxes([[length / 2, thickness / 2, height + 0.04]], [[length + 0.05, thickness + 0.08, 0.08]]))
        if kind == "wall_fence":
            builder.extend(fence(rng, length, "bars"), np.eye(3), [0.0, thickness / 2, height])
        return builder
    post_size = rng.uniform(0.05, 0.12)
    n_posts = len(posts)
    if kind in ("post_wire", "railing", "chainlink"):
        builder.add(tubes(np.column_stack([posts, np.zeros(n_posts), np.full(n_posts, -0.3)]),
                          np.column_stack([posts, np.zeros(n_posts), np.full(n_posts, height)]), post_size / 2, 6))
    else:
        builder.add(boxes(np.column_stack([posts, np.zeros(n_posts), np.full(n_posts, (height - 0.3) / 2)]),
                          [post_size, post_size, height + 0.3]))
    if kind == "post_wire":
        for z in np.linspace(0.3, height - 0.05, int(rng.integers(2, 5))):
            builder.add(tubes([[0, 0, z]], [[length, 0, z]], 0.004, 3))
    elif kind == "railing":
        for z in (height, height * 0.5):
            builder.add(tubes([[0, 0, z]], [[length, 0, z]], 0.025, 6))
    elif kind == "chainlink":
        builder.add(quads(np.array([[[0, 0, 0.02], [length, 0, 0.02], [length, 0, height], [0, 0, height]]])),
                    Material.MESH)
        builder.add(tubes([[0, 0, height]], [[length, 0, height]], 0.02, 6))
    elif kind == "boards":
        builder.add(boxes([[length / 2, 0.05, height / 2]], [[length, 0.03, height - 0.05]]))
    else:  # pickets or bars
        width = rng.uniform(0.02, 0.09) if kind == "pickets" else rng.uniform(0.015, 0.03)
        gap = rng.uniform(0.05, 0.12)
        xs = np.arange(width, length, width + gap)
        builder.add(boxes(np.column_stack([xs, np.full(len(xs), 0.04), np.full(len(xs), height / 2)]),
                          [width, 0.02, height]))
        for z in (0.15, height - 0.15):
            builder.add(boxes([[length / 2, 0.02, z]], [[length, 0.025, 0.06]]))
    return builder


def guard_rail(length: float) -> MeshBuilder:
    """A highway W-beam guard rail along x: posts every 2 m and a 0.3 m beam at 0.55-0.85 m."""
    builder = MeshBuilder(Semantic.FENCE)
    posts = np.arange(0.0, length, 2.0)
    builder.add(boxes(np.column_stack([posts, np.full(len(posts), 0.1), np.full(len(posts), 0.25)]),
                      [0.1, 0.15, 1.0]))
    for z0, z1, y in ((0.55, 0.7, 0.0), (0.7, 0.85, 0.06)):
        builder.add(quads(np.array([[[0, y, z0], [length, y, z0], [length, 0.03, z1], [0, 0.03, z1]]])))
    return builder


def jersey_barrier(length: float) -> MeshBuilder:
    """A concrete median barrier along x (0.8 m high, sloped sides), centred on y = 0."""
    profile = np.array([[-0.3, 0.0], [0.3, 0.0], [0.2, 0.3], [0.1, 0.8], [-0.1, 0.8], [-0.2, 0.3]])
    vertices, faces = prism(profile, length)
    builder = MeshBuilder(Semantic.OTHER_STRUCTURE)
    builder.add((vertices[:, [1, 0, 2]] + [length / 2, 0.0, 0.0], faces[:, ::-1]))
    return builder


# --- poles and street furniture ----------------------------------------------------------------------------------

POLE_KINDS = ("street_light", "sign", "traffic_light", "utility", "bollard", "post")


def pole(rng: np.random.Generator, kind: str) -> MeshBuilder:
    """A pole-like object at the origin; arms and signs point to -y (over the street)."""
    builder = MeshBuilder(Semantic.POLE, countable=True)
    if kind == "street_light":
        height = rng.uniform(4.5, 9.0)
        radius = rng.uniform(0.06, 0.12)
        builder.add(tubes([[0, 0, -0.2]], [[0, 0, height]], radius, 8, radius * 0.6))
        reach = rng.uniform(0.5, 2.0)
        builder.add(tubes([[0, 0, height - 0.1]], [[0, -reach, height + 0.1]], 0.04, 5))
        builder.add(boxes([[0, -reach, height]], [[0.3, 0.6, 0.15]]))
    elif kind == "sign":
        height = rng.uniform(2.0, 3.2)
        builder.add(tubes([[0, 0, -0.2]], [[0, 0, height]], 0.03, 6))
        size = rng.uniform(0.45, 0.9)
        shape = rng.integers(3)
        if shape == 0:  # rectangle
            builder.add(boxes([[0, -0.05, height - size / 2]], [[size, 0.02, size * rng.uniform(0.6, 1.2)]]),
                        label=Semantic.TRAFFIC_SIGN)
        else:  # disc or triangle as a thin prism
            sides = 12 if shape == 1 else 3
            angles = np.linspace(0, 2 * np.pi, sides, endpoint=False) + np.pi / 2
            outline = np.column_stack([np.cos(angles), np.sin(angles)]) * size / 2 + [0, height - size / 2]
            vertices, faces = prism(outline, 0.02)
            builder.add((vertices + [0.0, -0.05, 0.0], faces), label=Semantic.TRAFFIC_SIGN)
        if rng.random() < 0.3:
            builder.add(boxes([[0, -0.05, height - size - 0.25]], [[size * 0.9, 0.02, 0.3]]),
                        label=Semantic.TRAFFIC_SIGN)
    elif kind == "traffic_light":
        height = rng.uniform(3.0, 4.5)
        builder.add(tubes([[0, 0, -0.2]], [[0, 0, height]], 0.07, 8))
        builder.add(boxes([[0, -0.2, height - 0.6]], [[0.35, 0.3, 1.0]]), label=Semantic.TRAFFIC_SIGN)
        if rng.random() < 0.4:
            reach = rng.uniform(3.0, 6.0)
            builder.add(tubes([[0, 0, height - 0.2]], [[0, -reach, height - 0.2]], 0.06, 6))
            builder.add(boxes([[0, -reach, height - 0.8]], [[0.35, 0.3, 1.0]]), label=Semantic.TRAFFIC_SIGN)
    elif kind == "utility":
        height = rng.uniform(7.0, 10.0)
        builder.add(tubes([[0, 0, -0.3]], [[0, 0, height]], rng.uniform(0.1, 0.16), 8, 0.09))
        builder.add(boxes([[0, 0, height - 0.5]], [[0.1, 1.6, 0.1]]))
    elif kind == "bollard":
        builder.add(tubes([[0, 0, -0.1]], [[0, 0, rng.uniform(0.6, 1.1)]], rng.uniform(0.05, 0.12), 8))
    else:  # short post, e.g. delineator or parking post
        builder.add(boxes([[0, 0, 0.5]], [[0.12, 0.12, 1.2]]))
    return builder


CLUTTER_KINDS = ("bins", "bike", "bench", "cabinet", "planter", "bike_rack", "shelter", "column", "mailbox", "stones",
                 "person")
_CLUTTER_LABELS = {kind: Semantic.OTHER_OBJECT for kind in CLUTTER_KINDS} | {
    "bike": Semantic.BICYCLE, "person": Semantic.PERSON, "shelter": Semantic.OTHER_STRUCTURE,
    "column": Semantic.OTHER_STRUCTURE}


def clutter(rng: np.random.Generator, kind: str) -> MeshBuilder:
    """Small street clutter at the origin (see CLUTTER_KINDS)."""
    builder = MeshBuilder(_CLUTTER_LABELS[kind], countable=True)
    if kind == "bins":
        for i in range(int(rng.integers(1, 4))):
            w = rng.uniform(0.5, 0.75)
            h = rng.uniform(0.9, 1.2)
            builder.add(boxes([[i * (w + 0.1), 0, h / 2]], [[w, w * 1.2, h]]))
            builder.add(boxes([[i * (w + 0.1), -0.05, h + 0.03]], [[w + 0.05, w * 1.3, 0.05]]))
    elif kind == "bike":
        wheel = 0.34
        angles = np.linspace(0, 2 * np.pi, 13)
        for x in (-0.55, 0.55):
            ring = np.column_stack([x + wheel * np.cos(angles), np.zeros(13), wheel + wheel * np.sin(angles)])
            builder.add(tubes(ring[:-1], ring[1:], 0.02, 4))
        frame = np.array([[-0.55, 0, wheel], [0.0, 0, wheel], [0.4, 0, 0.85], [-0.15, 0, 0.8], [0.0, 0, wheel],
                          [-0.15, 0, 0.8], [-0.55, 0, wheel]])
        builder.add(tubes(frame[:-1], frame[1:], 0.018, 4))
        builder.add(tubes([[0.4, 0, 0.85], [-0.15, 0, 0.8]], [[0.45, 0, 1.0], [-0.18, 0, 0.92]], 0.018, 4))
        builder.add(tubes([[0.45, -0.28, 1.0]], [[0.45, 0.28, 1.0]], 0.015, 4))
    elif kind == "bench":
        length = rng.uniform(1.5, 2.2)
        for y, z in ((0.0, 0.45), (0.12, 0.45), (0.24, 0.45), (0.3, 0.65), (0.32, 0.8)):
            builder.add(boxes([[0, y, z]], [[length, 0.08, 0.04]]))
        for x in (-length / 2 + 0.1, length / 2 - 0.1):
            builder.add(boxes([[x, 0.12, 0.22]], [[0.06, 0.4, 0.45]]))
    elif kind == "cabinet":
        builder.add(boxes([[0, 0, 0.6]], [[rng.uniform(0.5, 1.5), rng.uniform(0.3, 0.5), rng.uniform(0.9, 1.6)]]))
    elif kind == "planter":
        size = rng.uniform(0.6, 1.5)
        builder.add(boxes([[0, 0, 0.3]], [[size, size, 0.6]]))
        builder.extend(bush(rng, size * 0.5), np.eye(3), [0.0, 0.0, 0.6])
    elif kind == "bike_rack":
        for x in np.arange(0, rng.uniform(2, 6), 0.8):
            arc = np.array([[x, -0.3, 0], [x, -0.3, 0.7], [x, -0.2, 0.85], [x, 0.2, 0.85], [x, 0.3, 0.7],
                            [x, 0.3, 0]])
            builder.add(tubes(arc[:-1], arc[1:], 0.025, 5))
    elif kind == "shelter":
        length = rng.uniform(3.0, 6.0)
        for x in (-length / 2, length / 2):
            for y in (0.0, 1.4):
                builder.add(boxes([[x, y, 1.25]], [[0.08, 0.08, 2.5]]))
        builder.add(boxes([[0, 0.7, 2.55]], [[length + 0.3, 1.8, 0.1]]))
        builder.add(quads(np.array([[[-length / 2, 1.4, 0.1], [length / 2, 1.4, 0.1], [length / 2, 1.4, 2.4],
                                     [-length / 2, 1.4, 2.4]]])), Material.GLASS)
    elif kind == "column":
        builder.add(tubes([[0, 0, 0]], [[0, 0, rng.uniform(2.5, 3.5)]], rng.uniform(0.5, 0.7), 14))
    elif kind == "mailbox":
        builder.add(tubes([[0, 0, 0]], [[0, 0, 1.0]], 0.04, 5))
        builder.add(boxes([[0, 0, 1.15]], [[0.4, 0.3, 0.35]]))
    elif kind == "person":  # someone standing: legs, torso, arms, head
        height = rng.uniform(1.55, 1.95)
        hip, shoulder = 0.5 * height, 0.8 * height
        builder.add(tubes([[0, -0.1, 0], [0, 0.1, 0]], [[0, -0.1, hip], [0, 0.1, hip]], 0.07, 6))
        builder.add(tubes([[0, 0, hip - 0.05]], [[0, 0, shoulder]], 0.17, 8, 0.2))
        builder.add(tubes([[0, -0.24, shoulder], [0, 0.24, shoulder]], [[0.05, -0.27, hip], [0.05, 0.27, hip]],
                          0.045, 5))
        builder.add(tubes([[0, 0, shoulder + 0.03]], [[0, 0, height]], 0.1, 8))
    else:  # stones / concrete blocks
        for _ in range(int(rng.integers(1, 5))):
            size = rng.uniform(0.3, 0.9, 3)
            builder.add(boxes([[*rng.normal(0, 0.8, 2), size[2] / 2]], [size], rng.uniform(0, np.pi)))
    return builder
