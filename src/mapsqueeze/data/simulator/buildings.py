"""Procedural buildings: facades with reliefs (windows, doors, shop fronts, balconies) and whole buildings (urban,
house, industrial), each built in its own object frame (see `objects`) as a `MeshBuilder`."""

import numpy as np

from mapsqueeze.data.simulator.shapes import (
    Material,
    MeshBuilder,
    Semantic,
    boxes,
    prism,
    quads,
    tubes,
)


def relief_facade(width: float, height: float, openings: list[tuple[float, float, float, float, float, Material]],
                  ) -> MeshBuilder:
    """A wall in the plane y = 0 facing -y, x in [0, width], z in [0, height], with rectangular reliefs.

    `openings`: (x0, x1, z0, z1, depth, material) rectangles; positive depth is a recess into the wall (+y:
    windows, doors), negative a protrusion (plinths, pilasters). Later rectangles win where they overlap. The
    wall is cut into the grid of all rectangle edges; each cell is a quad at its depth and reveal quads join
    neighbouring cells (and the wall's border) of different depth, so the surface is closed and watertight.
    """
    xs = np.unique(np.clip([0.0, width, *[v for o in openings for v in o[:2]]], 0.0, width))
    zs = np.unique(np.clip([0.0, height, *[v for o in openings for v in o[2:4]]], 0.0, height))
    nx, nz = len(xs) - 1, len(zs) - 1
    depth = np.zeros((nx, nz))
    material = np.full((nx, nz), int(Material.SOLID))
    cx, cz = (xs[:-1] + xs[1:]) / 2, (zs[:-1] + zs[1:]) / 2
    for x0, x1, z0, z1, d, m in openings:
        inside = ((cx > x0) & (cx < x1))[:, None] & ((cz > z0) & (cz < z1))[None, :]
        depth[inside] = d
        material[inside] = int(m)
    builder = MeshBuilder(Semantic.BUILDING)
    i, k = np.meshgrid(np.arange(nx), np.arange(nz), indexing="ij")
    i, k = i.ravel(), k.ravel()
    d = depth[i, k]
    cells = np.stack([
        np.column_stack([xs[i], d, zs[k]]), np.column_stack([xs[i + 1], d, zs[k]]),
        np.column_stack([xs[i + 1], d, zs[k + 1]]), np.column_stack([xs[i], d, zs[k + 1]]),
    ], 1)
    for code in np.unique(material):
        builder.add(quads(cells[material[i, k] == code]), Material(int(code)))
    padded = np.pad(depth, 1)  # border cells at depth 0: reveals close recesses and protrusions at the edges
    reveals = []
    for a in range(nx + 1):  # vertical reveals between columns a-1 and a
        left, right = padded[a, 1:-1], padded[a + 1, 1:-1]
        for b in np.flatnonzero(left != right):
            reveals.append([[xs[a], left[b], zs[b]], [xs[a], right[b], zs[b]],
                            [xs[a], right[b], zs[b + 1]], [xs[a], left[b], zs[b + 1]]])
    for b in range(nz + 1):  # horizontal reveals between rows b-1 and b
        below, above = padded[1:-1, b], padded[1:-1, b + 1]
        for a in np.flatnonzero(below != above):
            reveals.append([[xs[a], below[a], zs[b]], [xs[a + 1], below[a], zs[b]],
                            [xs[a + 1], above[a], zs[b]], [xs[a], above[a], zs[b]]])
    if reveals:
        builder.add(quads(np.array(reveals)))
    return builder


def _railing(builder: MeshBuilder, x0: float, x1: float, y: float, z: float, height: float,
             rng: np.random.Generator) -> None:
    """A balcony or stair railing along x at (y, z): top rail plus vertical bars, or a solid parapet."""
    if rng.random() < 0.4:
        builder.add(boxes([[(x0 + x1) / 2, y, z + height / 2]], [[x1 - x0, 0.08, height]]))
        return
    spacing = rng.uniform(0.1, 0.16)
    bars = np.arange(x0 + spacing / 2, x1, spacing)
    builder.add(tubes(np.column_stack([bars, np.full_like(bars, y), np.full_like(bars, z)]),
                      np.column_stack([bars, np.full_like(bars, y), np.full_like(bars, z + height)]), 0.012, 4))
    builder.add(tubes([[x0, y, z + height]], [[x1, y, z + height]], 0.03, 6))


def building(rng: np.random.Generator, length: float, depth: float, floors: int, style: str) -> MeshBuilder:
    """A building with its street facade (at y = 0) detailed: windows, doors, shop fronts, balconies, plinth.

    `style`: "urban" (flat roof, parapet, shops possible), "house" (gable roof, eaves) or "industrial" (tall
    plain walls, large gates, few windows). The walls reach 0.5 m below z = 0 so that they meet sloping ground.
    """
    builder = MeshBuilder(Semantic.BUILDING)
    ground_floor = rng.uniform(3.2, 4.5) if style == "urban" else rng.uniform(2.6, 3.2)
    upper_floor = rng.uniform(2.7, 3.4)
    height = ground_floor + (floors - 1) * upper_floor if style != "industrial" else rng.uniform(4.0, 9.0)
    base = -0.5
    openings: list[tuple[float, float, float, float, float, Material]] = []
    bay = rng.uniform(2.2, 3.8)
    n_bays = max(1, int(length // bay))
    margin = (length - n_bays * bay) / 2
    window_width = bay * rng.uniform(0.35, 0.6)
    window_depth = rng.uniform(0.08, 0.3)
    window_height = upper_floor * rng.uniform(0.4, 0.55)
    sill = rng.uniform(0.8, 1.0)
    if style == "industrial":
        for x in np.sort(rng.choice(n_bays, size=min(n_bays, rng.integers(1, 3)), replace=False)):
            gate_x = margin + x * bay
            openings.append((gate_x + 0.2, gate_x + bay - 0.2, -base, -base + rng.uniform(3.0, 4.2),
                             rng.uniform(0.05, 0.3), Material.SOLID))
        if rng.random() < 0.7:
            band_z = height - rng.uniform(1.5, 2.5) - base
            openings.append((0.5, length - 0.5, band_z, band_z + 1.0, 0.08, Material.GLASS))
    else:
        shop = style == "urban" and rng.random() < 0.55
        door_bay = int(rng.integers(n_bays))
        for b in range(n_bays):
            bx0 = margin + b * bay
            centre = bx0 + bay / 2
            if b == door_bay or (shop and rng.random() < 0.2):
                door_width = rng.uniform(1.0, 1.8)
                openings.append((centre - door_width / 2, centre + door_width / 2, -base,
                                 -base + rng.uniform(2.1, 2.6), rng.uniform(0.15, 0.8), Material.SOLID))
            elif shop:
                openings.append((bx0 + 0.25, bx0 + bay - 0.25, -base + rng.uniform(0.3, 0.6),
                                 -base + ground_floor - 0.5, rng.uniform(0.05, 0.25), Material.GLASS))
            elif rng.random() < 0.85:
                ground_sill = rng.uniform(0.9, 1.6)
                openings.append((centre - window_width / 2, centre + window_width / 2, -base + ground_sill,
                                 -base + ground_sill + window_height, window_depth, Material.GLASS))
            for f in range(1, floors):
                if rng.random() < 0.05:
                    continue
                z0 = -base + ground_floor + (f - 1) * upper_floor + sill
                openings.append((centre - window_width / 2, centre + window_width / 2, z0,
                                 min(z0 + window_height, height - base - 0.3), window_depth, Material.GLASS))
        if rng.random() < 0.7:  # plinth
            plinth = rng.uniform(0.3, 1.0)
            openings.insert(0, (0.0, length, 0.0, -base + plinth, -rng.uniform(0.03, 0.1), Material.SOLID))
        if rng.random() < 0.35:  # pilasters / cornice band
            band_z = -base + ground_floor
            openings.insert(0, (0.0, length, band_z, band_z + rng.uniform(0.2, 0.5), -rng.uniform(0.05, 0.2),
                                Material.SOLID))
    wall_height = height - base
    facade = relief_facade(length, wall_height, openings)
    builder.extend(facade, np.eye(3), [0.0, 0.0, base])
    # side and back walls, roof
    corners = np.array([[0, 0], [length, 0], [length, depth], [0, depth]], dtype=np.float64)
    walls = []
    for (xa, ya), (xb, yb) in [(corners[1], corners[2]), (corners[2], corners[3]), (corners[3], corners[0])]:
        walls.append([[xa, ya, base], [xb, yb, base], [xb, yb, height], [xa, ya, height]])
    builder.add(quads(np.array(walls)))
    if style == "house":
        overhang = rng.uniform(0.2, 0.6)
        ridge = rng.uniform(2.0, 4.5)
        roof = np.array([[-overhang, height - 0.15], [depth + overhang, height - 0.15], [depth / 2, height + ridge]])
        vertices, faces = prism(np.column_stack([roof[:, 0], roof[:, 1]]), length + 2 * overhang)
        # prism extrudes over y; swap so the ridge runs along x
        vertices = vertices[:, [1, 0, 2]] + [length / 2, 0.0, 0.0]
        builder.add((vertices, faces[:, ::-1]))
    else:
        builder.add(quads(np.array([[[0, 0, height], [length, 0, height], [length, depth, height],
                                     [0, depth, height]]])))
        parapet = rng.uniform(0.3, 1.1)
        builder.add(boxes([[length / 2, 0.1, height + parapet / 2]], [[length, 0.2, parapet]]))
    if style == "urban" and floors > 1 and rng.random() < 0.5:  # balconies on upper floors
        slab_depth = rng.uniform(0.8, 1.6)
        for b in range(n_bays):
            if rng.random() < 0.5:
                continue
            x0, x1 = margin + b * bay + 0.15, margin + (b + 1) * bay - 0.15
            for f in range(1, floors):
                z = ground_floor + (f - 1) * upper_floor
                builder.add(boxes([[(x0 + x1) / 2, -slab_depth / 2, z + 0.08]], [[x1 - x0, slab_depth, 0.16]]))
                _railing(builder, x0, x1, -slab_depth + 0.05, z + 0.16, 1.0, rng)
    if style == "urban" and rng.random() < 0.3:  # shop awning
        a0 = margin
        a1 = length - margin
        z = ground_floor - 0.3
        reach = rng.uniform(1.0, 2.0)
        builder.add(quads(np.array([[[a0, 0, z], [a1, 0, z], [a1, -reach, z - 0.6], [a0, -reach, z - 0.6]]])))
    if rng.random() < 0.5:  # drain pipes at the facade ends
        for x in (0.15, length - 0.15):
            builder.add(tubes([[x, -0.12, base]], [[x, -0.12, height]], 0.05, 6))
    if style != "industrial" and rng.random() < 0.4:  # entrance steps
        centre = margin + (door_bay + 0.5) * bay
        for step in range(int(rng.integers(1, 4))):
            builder.add(boxes([[centre, -0.3 - 0.3 * step, 0.08 + 0.16 * (2 - step) / 2]],
                              [[1.8, 0.6, 0.16 * (3 - step)]]))
    return builder
