"""Placing objects along streets: object frames at (arc length, offset), ground claims, the route's reach."""

import numpy as np
from scipy.spatial import cKDTree

from mapsqueeze.data.simulator.presets import Preset
from mapsqueeze.data.simulator.shapes import MeshBuilder, rotation_z
from mapsqueeze.data.simulator.streets import FREE, Ground, Street

REACH_M = 28.0
"""Objects farther than this from the driven route are not built (they are beyond the 20 m mapping range)."""


class Layout:
    """Places objects along streets and collects them into one mesh; each placed object gets its own id."""

    def __init__(self, rng: np.random.Generator, preset: Preset, ground: Ground, route: np.ndarray):
        self.rng = rng
        self.preset = preset
        self.ground = ground
        self.builder = MeshBuilder()
        self._route = cKDTree(route)
        self._objects = 0

    def new_object(self, countable: bool) -> int:
        """A fresh object id: positive for countable objects (their instance id), negative for the others."""
        self._objects += 1
        return self._objects if countable else -self._objects

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
        self.builder.extend(part, rotation @ turn, origin + rotation @ np.asarray(shift),
                            self.new_object(part.countable))
        return True
