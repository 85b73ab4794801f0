"""Streets (centre line, cross-section, kerbs, sidewalks, junction mouths) and the terrain around them.

A `Street` is a centre line sampled every STEP_M metres with an elevation profile and a cross-section per side
(index 0: right, 1: left, looking along the street): road half width, kerb height and the width of the outer
strip (a raised sidewalk in towns, a shoulder at road level in the country). `Ground` is the 0.5 m grid that
carries the terrain heights, the class of each node (road / sidewalk / free) and which cells objects took.
"""

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from mapsqueeze.data.simulator.shapes import Material, MeshBuilder, Semantic, grid_surface, quads

STEP_M = 0.5
"""Centre-line sampling step (metres)."""

ROAD, SIDEWALK, FREE = 0, 1, 2
"""Ground classes of `Ground.classes`."""

SIDEWALK_SLOPE = 0.01
"""Sidewalks rise by 1 cm per metre away from the kerb (drainage)."""


@dataclass
class Street:
    """A street: centre line, elevation, cross-section per side (0 right, 1 left) and sidewalk gaps."""

    xy: np.ndarray  # (K, 2) centre line, STEP_M apart
    z: np.ndarray  # (K,) road-centre elevation (metres)
    half_width: np.ndarray  # (2,) road half width per side (metres)
    kerb_height: float  # metres (0: no kerb, the outer strip is a shoulder at road level)
    sidewalk: np.ndarray  # (2,) width of the outer strip per side (metres)
    parking: np.ndarray = field(default_factory=lambda: np.zeros(2))  # (2,) parking-lane width within the road
    camber: float = 0.02  # cross slope of the road (fraction), down towards the kerbs
    bumps: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (amplitude m, k_s, k_t, phase) waves
    gaps: list[tuple[int, float, float]] = field(default_factory=list)  # (side, s0, s1): no kerb / sidewalk

    def __post_init__(self) -> None:
        delta = np.gradient(self.xy, axis=0)
        self.heading = np.arctan2(delta[:, 1], delta[:, 0])
        self.tangent = np.column_stack([np.cos(self.heading), np.sin(self.heading)])
        self.normal = np.column_stack([-self.tangent[:, 1], self.tangent[:, 0]])  # to the left
        self.s = np.arange(len(self.xy)) * STEP_M
        self._tree = cKDTree(self.xy)

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def corridor(self, side: int) -> float:
        """Distance (metres) from the centre line to the outer edge of the sidewalk / shoulder on `side`."""
        return float(self.half_width[side] + self.sidewalk[side])

    def at(self, s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xy (..., 2), heading (...), road-centre z (...)) at arc length `s` metres (clipped to the street)."""
        index = np.clip(np.asarray(s) / STEP_M, 0, len(self.xy) - 1)
        low = np.floor(index).astype(int)
        high = np.minimum(low + 1, len(self.xy) - 1)
        w = index - low
        xy = self.xy[low] * (1 - w)[..., None] + self.xy[high] * w[..., None]
        z = self.z[low] * (1 - w) + self.z[high] * w
        return xy, self.heading[np.round(index).astype(int)], z

    def point(self, s: np.ndarray | float, t: np.ndarray | float) -> np.ndarray:
        """World xy of the point `t` metres left of the centre line (negative: right) at arc length `s`."""
        xy, heading, _ = self.at(s)
        t = np.asarray(t)
        return xy + t[..., None] * np.stack([-np.sin(heading), np.cos(heading)], -1)

    def surface_z(self, s: np.ndarray | float, t: np.ndarray | float) -> np.ndarray:
        """Ground height (metres) across the street: cambered, uneven road, then sidewalk level beyond the kerb."""
        _, _, z = self.at(s)
        t = np.asarray(t, dtype=np.float64)
        side = (t > 0).astype(int)
        half = self.half_width[side]
        road = z - self.camber * np.minimum(np.abs(t), half) + self.unevenness(s, np.clip(t, -half, half))
        beyond = np.abs(t) - half
        raised = (beyond > 0) & ~self.in_gap(np.asarray(s), t)
        return road + np.where(raised, self.kerb_height + SIDEWALK_SLOPE * np.minimum(beyond, self.sidewalk[side]), 0.0)

    def edge_z(self, s: np.ndarray | float, side: int) -> np.ndarray:
        """Height (metres) of the outer edge of the sidewalk or shoulder on `side`, where the terrain starts."""
        sign = 1.0 if side == 1 else -1.0
        return self.surface_z(s, sign * (self.corridor(side) - 1e-6) * np.ones_like(np.asarray(s, dtype=float)))

    def unevenness(self, s: np.ndarray | float, t: np.ndarray | float) -> np.ndarray:
        """Small height deviations of the pavement (metres): a sum of random plane waves (`bumps`)."""
        s, t = np.asarray(s, dtype=np.float64), np.asarray(t, dtype=np.float64)
        total = np.zeros(np.broadcast(s, t).shape)
        for amplitude, k_s, k_t, phase in self.bumps:
            total += amplitude * np.sin(k_s * s + k_t * t + phase)
        return total

    def in_gap(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Whether each (s, t) lies beside a junction mouth, where the kerb and sidewalk are left out."""
        gap = np.zeros(np.broadcast(s, t).shape, dtype=bool)
        for side, s0, s1 in self.gaps:
            gap |= ((t > 0) == bool(side)) & (s >= s0) & (s <= s1)
        return gap

    def project(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arc length s, signed lateral offset t (left +) and whether each (N, 2) point lies beside the street
        (not beyond its ends)."""
        _, index = self._tree.query(xy)
        offset = xy - self.xy[index]
        along = np.einsum("ij,ij->i", offset, self.tangent[index])
        t = np.einsum("ij,ij->i", offset, self.normal[index])
        beside = np.ones(len(xy), dtype=bool)
        beside &= ~((index == 0) & (along < 0))
        beside &= ~((index == len(self.xy) - 1) & (along > 0))
        return self.s[index] + along, t, beside

    def mesh(self) -> MeshBuilder:
        """Road surface (cambered; parking-lane quads labelled parking), kerb faces, sidewalks / shoulders (grass:
        terrain), and kerb ends at the junction gaps."""
        builder = MeshBuilder(Semantic.SIDEWALK)
        k = len(self.xy)
        t_road = np.unique(np.r_[np.linspace(-self.half_width[0], 0.0, int(self.half_width[0]) + 2),
                                 np.linspace(0.0, self.half_width[1], int(self.half_width[1]) + 2)])
        road_xy = self.xy[:, None, :] + t_road[None, :, None] * self.normal[:, None, :]
        road_z = (self.z[:, None] - self.camber * np.abs(t_road)[None, :]
                  + self.unevenness(self.s[:, None], t_road[None, :]))
        road = np.concatenate([road_xy, road_z[..., None]], -1)
        middle = (t_road[:-1] + t_road[1:]) / 2
        side = (middle > 0).astype(int)
        parking = (self.parking[side] > 0) & (np.abs(middle) > self.half_width[side] - self.parking[side])
        column = np.where(parking, Semantic.PARKING, Semantic.ROAD).astype(np.uint16)  # one class per quad column
        builder.add(_strip(road), Material.SOLID, np.repeat(np.tile(column, k - 1), 2))
        for side, sign in ((0, -1.0), (1, 1.0)):
            if self.sidewalk[side] <= 0:
                continue
            keep = np.ones(k - 1, dtype=bool)
            for gap_side, s0, s1 in self.gaps:
                if gap_side == side:
                    keep &= (self.s[1:] <= s0) | (self.s[:-1] >= s1)
            half = self.half_width[side]
            edge_z = self.z - self.camber * half + self.unevenness(self.s, sign * half)
            inner = self.xy + sign * half * self.normal
            outer = self.xy + sign * self.corridor(side) * self.normal
            low = np.column_stack([inner, edge_z])
            top_inner = np.column_stack([inner, edge_z + self.kerb_height])
            top_outer = np.column_stack([outer, edge_z + self.kerb_height + SIDEWALK_SLOPE * self.sidewalk[side]])
            material = Material.SOLID if self.kerb_height > 0 else Material.GRASS
            builder.add(_strip(np.stack([top_inner, top_outer], 1), keep), material,
                        Semantic.SIDEWALK if self.kerb_height > 0 else Semantic.TERRAIN)
            if self.kerb_height > 0:
                builder.add(_strip(np.stack([low, top_inner], 1), keep))
                ends = np.flatnonzero(np.diff(np.r_[0, keep.astype(int), 0]))  # segment boundaries
                caps = []
                for boundary in ends:
                    i = min(boundary, k - 1)
                    caps.append([low[i], top_inner[i], top_outer[i], [*outer[i], edge_z[i]]])
                builder.add(quads(np.array(caps)))
        return builder


def random_bumps(rng: np.random.Generator, amplitude_m: float, waves: int = 10) -> np.ndarray:
    """(waves, 4) random plane waves for `Street.bumps`: wavelengths 1.5-25 m, total ~`amplitude_m` (1 sigma)."""
    wavelength = np.exp(rng.uniform(np.log(1.5), np.log(25.0), waves))
    direction = rng.uniform(0.0, 2 * np.pi, waves)
    k = 2 * np.pi / wavelength
    amplitude = amplitude_m * np.sqrt(2.0 / waves) * np.sqrt(wavelength / wavelength.mean())
    return np.column_stack([amplitude, k * np.cos(direction), k * np.sin(direction), rng.uniform(0, 2 * np.pi, waves)])


def _strip(rows: np.ndarray, keep: np.ndarray | None = None):
    """Quads between consecutive rows of an (K, M, 3) grid of points along a street; `keep` (K-1,) selects."""
    k, m = rows.shape[:2]
    corners = np.stack([rows[:-1, :-1], rows[1:, :-1], rows[1:, 1:], rows[:-1, 1:]], 2)  # (K-1, M-1, 4, 3)
    if keep is not None:
        corners = corners[keep]
    return quads(corners.reshape(-1, 4, 3))


@dataclass
class SideProfile:
    """How the ground leaves a street on one side: a ditch and/or a slope up (cut) or down (embankment)."""

    ditch_depth: float = 0.0
    ditch_offset: float = 2.0
    ditch_width: float = 2.0
    slope: float = 0.0  # rise per metre beyond `slope_start` (negative: falls away)
    slope_start: float = 3.0
    slope_limit: float = 5.0  # metres of rise or fall at most

    def height(self, distance: np.ndarray) -> np.ndarray:
        """Height (metres) relative to the sidewalk edge, `distance` metres beyond it."""
        d = np.maximum(distance, 0.0)
        ditch = -self.ditch_depth * np.exp(-(((d - self.ditch_offset) / (self.ditch_width / 2)) ** 2))
        ramp = np.clip((d - self.slope_start) * self.slope, -self.slope_limit, self.slope_limit)
        return ditch + np.where(d > self.slope_start, ramp, 0.0)


class Ground:
    """Terrain height field on a GRID_M grid around the route, with ground classes and taken cells.

    Heights: beside a street, the sidewalk (or shoulder) edge height plus the side profile, plus smooth relief
    that fades in away from the street and a few centimetres of roughness. Nodes inside a street corridor hold
    the street's own surface; cells whose four nodes are inside a corridor are left out of the mesh (the street
    mesh covers them), as are cells farther than `reach_m` from the route.
    """

    GRID_M = 0.5

    def __init__(self, streets: list[Street], profiles: list[tuple[SideProfile, SideProfile]], route: np.ndarray,
                 rng: np.random.Generator, relief_m: float, roughness_m: float, reach_m: float = 28.0):
        low = route.min(axis=0) - reach_m - 2
        high = route.max(axis=0) + reach_m + 2
        self.x = np.arange(low[0], high[0], self.GRID_M)
        self.y = np.arange(low[1], high[1], self.GRID_M)
        gx, gy = np.meshgrid(self.x, self.y)
        nodes = np.column_stack([gx.ravel(), gy.ravel()])
        near_route = cKDTree(route).query(nodes, distance_upper_bound=reach_m + 2)[0] < np.inf
        best_excess = np.full(len(nodes), np.inf)
        height = np.zeros(len(nodes))
        classes = np.full(len(nodes), FREE, dtype=np.int8)
        for street, (right, left) in zip(streets, profiles):
            s, t, beside = street.project(nodes)
            side = (t > 0).astype(int)
            corridor = np.where(side == 1, street.corridor(1), street.corridor(0))
            excess = np.abs(t) - corridor
            better = beside & (excess < best_excess)
            edge = np.where(side == 1, street.edge_z(s, 1), street.edge_z(s, 0))
            beyond = np.where(side == 1, left.height(excess), right.height(excess))
            inside = excess < 0
            height = np.where(better, np.where(inside, street.surface_z(s, t) - 0.02, edge + beyond), height)
            half = street.half_width[side]
            node_class = np.where(np.abs(t) <= half, ROAD, np.where(inside, SIDEWALK, FREE))
            node_class = np.where(street.in_gap(s, t) & inside, ROAD, node_class)
            classes = np.where(better & inside, node_class, classes)
            best_excess = np.where(better, excess, best_excess)
        shape = (len(self.y), len(self.x))
        fade = np.clip((best_excess - 1.0) / 8.0, 0.0, 1.0)
        relief = gaussian_filter(rng.normal(size=shape), sigma=12.0 / self.GRID_M, mode="nearest")
        relief *= relief_m / max(relief.std(), 1e-9)
        rough = gaussian_filter(rng.normal(size=shape), sigma=1.0, mode="nearest")
        rough *= roughness_m / max(rough.std(), 1e-9)
        outside = np.isfinite(best_excess) & (best_excess > 0)
        height = height + (relief.ravel() * fade + rough.ravel()) * outside
        self.z = height.reshape(shape)
        self.classes = classes.reshape(shape)
        inside = (best_excess < 0).reshape(shape)
        near = near_route.reshape(shape)
        self._keep = ~(inside[:-1, :-1] & inside[1:, :-1] & inside[:-1, 1:] & inside[1:, 1:])
        self._keep &= near[:-1, :-1] | near[1:, 1:]
        self.taken = np.zeros(shape, dtype=bool)

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Bilinearly interpolated terrain height (metres) at (N, 2) points."""
        xy = np.atleast_2d(xy)
        fx = np.clip((xy[:, 0] - self.x[0]) / self.GRID_M, 0, len(self.x) - 1.001)
        fy = np.clip((xy[:, 1] - self.y[0]) / self.GRID_M, 0, len(self.y) - 1.001)
        ix, iy = fx.astype(int), fy.astype(int)
        wx, wy = fx - ix, fy - iy
        z = self.z
        return ((z[iy, ix] * (1 - wx) + z[iy, ix + 1] * wx) * (1 - wy)
                + (z[iy + 1, ix] * (1 - wx) + z[iy + 1, ix + 1] * wx) * wy)

    def _cells(self, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Grid node indices (rows, cols) inside a convex polygon (K, 2) given counter-clockwise or clockwise."""
        low = np.floor((corners.min(axis=0) - [self.x[0], self.y[0]]) / self.GRID_M).astype(int)
        high = np.ceil((corners.max(axis=0) - [self.x[0], self.y[0]]) / self.GRID_M).astype(int)
        low = np.maximum(low, 0)
        high = np.minimum(high, [len(self.x) - 1, len(self.y) - 1])
        if (high < low).any():
            return np.empty(0, int), np.empty(0, int)
        cols, rows = np.meshgrid(np.arange(low[0], high[0] + 1), np.arange(low[1], high[1] + 1))
        points = np.column_stack([self.x[cols.ravel()], self.y[rows.ravel()]])
        edges = np.roll(corners, -1, axis=0) - corners
        cross = edges[None, :, 0] * (points[:, None, 1] - corners[None, :, 1]) - edges[None, :, 1] * (
            points[:, None, 0] - corners[None, :, 0])
        inside = (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)
        return rows.ravel()[inside], cols.ravel()[inside]

    def claim(self, corners: np.ndarray, allowed: tuple[int, ...] = (FREE,)) -> bool:
        """Take the ground under a convex footprint (K, 2) if all of it is free and of an allowed class."""
        rows, cols = self._cells(corners)
        if len(rows) == 0:  # a footprint smaller than a cell: its nearest node
            centre = corners.mean(axis=0)
            rows = np.array([int(np.clip(np.rint((centre[1] - self.y[0]) / self.GRID_M), 0, len(self.y) - 1))])
            cols = np.array([int(np.clip(np.rint((centre[0] - self.x[0]) / self.GRID_M), 0, len(self.x) - 1))])
        if self.taken[rows, cols].any() or not np.isin(self.classes[rows, cols], allowed).all():
            return False
        self.taken[rows, cols] = True
        return True

    def mesh(self) -> MeshBuilder:
        builder = MeshBuilder(Semantic.TERRAIN)
        builder.add(grid_surface(self.x, self.y, self.z, self._keep), Material.GRASS)
        return builder
