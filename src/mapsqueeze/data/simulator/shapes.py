"""Vectorised triangle-mesh primitives for the simulator's scenes, and the builder that collects them.

Every primitive returns `(vertices (V, 3) float64, faces (F, 3) int64)` in metres; batch versions build many
shapes at once (thousands of pickets or leaves cost one numpy call). `MeshBuilder` concatenates the parts and
keeps per face a material code (see `Material`), which the ray caster uses for returns on glass and foliage, a
semantic class (`Semantic`) and the id of the object the face belongs to.
"""

from enum import IntEnum

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]

_CUBE_VERTICES = np.array(
    [[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], dtype=np.float64
)
_CUBE_FACES = np.array(
    [
        [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # x- / x+
        [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # y- / y+
        [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],  # z- / z+
    ],
    dtype=np.int64,
)


class Material(IntEnum):
    """What a face is made of; decides how a laser return behaves there (see `raycast.MATERIAL_RESPONSE`)."""

    SOLID = 0  # walls, cars, poles, road: an ordinary diffuse return
    VEGETATION = 1  # leaves and needles: porous, some rays pass on, noisier range
    GLASS = 2  # windows and windscreens: few returns, many rays pass through or are lost
    GRASS = 3  # grass and rough ground: returns scattered a few centimetres above the surface
    MESH = 4  # chain-link and wire-mesh fences: most rays pass through


class Semantic(IntEnum):
    """Semantic class of a face: SemanticKITTI's raw label ids (its `label` field, low 16 bits of a .label entry)."""

    UNLABELED = 0
    CAR = 10
    BICYCLE = 11
    TRUCK = 18
    PERSON = 30
    ROAD = 40
    PARKING = 44
    SIDEWALK = 48
    BUILDING = 50
    FENCE = 51
    OTHER_STRUCTURE = 52
    LANE_MARKING = 60
    VEGETATION = 70
    TRUNK = 71
    TERRAIN = 72
    POLE = 80
    TRAFFIC_SIGN = 81
    OTHER_OBJECT = 99

    @property
    def label_name(self) -> str:
        """SemanticKITTI's name of the class (e.g. "traffic-sign")."""
        return self.name.lower().replace("_", "-")


def rotation_z(yaw: np.ndarray | float) -> np.ndarray:
    """(..., 3, 3) rotation matrices about +z by `yaw` radians."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    zero, one = np.zeros_like(yaw), np.ones_like(yaw)
    return np.stack([np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)], -2)


def boxes(centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray | float = 0.0) -> Mesh:
    """Boxes with the given centres (N, 3), edge lengths (N, 3) and rotations about z (radians)."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    n = len(centers)
    sizes = np.broadcast_to(np.asarray(sizes, dtype=np.float64), (n, 3))
    rotations = np.broadcast_to(rotation_z(yaws), (n, 3, 3))
    local = _CUBE_VERTICES[None] * sizes[:, None, :]
    vertices = np.einsum("nij,nvj->nvi", rotations, local) + centers[:, None, :]
    faces = _CUBE_FACES[None] + 8 * np.arange(n)[:, None, None]
    return vertices.reshape(-1, 3), faces.reshape(-1, 3)


def _perpendicular_frames(axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to each unit axis (N, 3) and to each other."""
    helper = np.where(np.abs(axes[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    first = np.cross(axes, helper)
    first /= np.linalg.norm(first, axis=1, keepdims=True)
    return first, np.cross(axes, first)


def tubes(starts: np.ndarray, ends: np.ndarray, radii: np.ndarray | float, sections: int = 6,
          end_radii: np.ndarray | float | None = None) -> Mesh:
    """Closed prisms of `sections` sides from each start (N, 3) to end (N, 3): poles, bars, wires, branches.

    `end_radii` tapers the tube (trunks); default: the same radius at both ends.
    """
    starts = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
    ends = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
    n = len(starts)
    radii = np.broadcast_to(np.asarray(radii, dtype=np.float64), (n,))
    end_radii = radii if end_radii is None else np.broadcast_to(np.asarray(end_radii, dtype=np.float64), (n,))
    axes = ends - starts
    axes = axes / np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-12)
    u, v = _perpendicular_frames(axes)
    angles = np.linspace(0.0, 2 * np.pi, sections, endpoint=False)
    ring = np.cos(angles)[None, :, None] * u[:, None, :] + np.sin(angles)[None, :, None] * v[:, None, :]
    bottom = starts[:, None, :] + radii[:, None, None] * ring
    top = ends[:, None, :] + end_radii[:, None, None] * ring
    vertices = np.concatenate([bottom, top, starts[:, None, :], ends[:, None, :]], axis=1)  # 2 * sections + 2
    k = np.arange(sections)
    k1 = (k + 1) % sections
    side = np.concatenate([np.stack([k, k1, sections + k1], 1), np.stack([k, sections + k1, sections + k], 1)])
    caps = np.concatenate([
        np.stack([np.full(sections, 2 * sections), k1, k], 1),
        np.stack([np.full(sections, 2 * sections + 1), sections + k, sections + k1], 1),
    ])
    template = np.concatenate([side, caps])
    faces = template[None] + (2 * sections + 2) * np.arange(n)[:, None, None]
    return vertices.reshape(-1, 3), faces.reshape(-1, 3)


def quads(corners: np.ndarray) -> Mesh:
    """Planar quads from (N, 4, 3) corners in order around the quad, two triangles each."""
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 4, 3)
    faces = np.array([[0, 1, 2], [0, 2, 3]])[None] + 4 * np.arange(len(corners))[:, None, None]
    return corners.reshape(-1, 3), faces.reshape(-1, 3)


def prism(outline: np.ndarray, width: float) -> Mesh:
    """A convex 2-D outline (K, 2) in the x-z plane, counter-clockwise, extruded over y in [-width/2, width/2]."""
    outline = np.asarray(outline, dtype=np.float64)
    k = len(outline)
    near = np.column_stack([outline[:, 0], np.full(k, -width / 2), outline[:, 1]])
    far = near + [0.0, width, 0.0]
    vertices = np.concatenate([near, far])
    i = np.arange(k)
    j = (i + 1) % k
    side = np.concatenate([np.stack([i, j, k + j], 1), np.stack([i, k + j, k + i], 1)])
    fan = np.arange(1, k - 1)
    caps = np.concatenate([np.stack([np.zeros(k - 2, int), fan, fan + 1], 1),
                           np.stack([np.full(k - 2, k), k + fan + 1, k + fan], 1)])
    return vertices, np.concatenate([side, caps])


def random_triangles(centers: np.ndarray, sizes: np.ndarray | float, rng: np.random.Generator) -> Mesh:
    """One randomly oriented triangle of about `sizes` metres across around each centre (N, 3): leaves, litter."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    n = len(centers)
    sizes = np.broadcast_to(np.asarray(sizes, dtype=np.float64), (n,))
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    u, v = _perpendicular_frames(normal)
    angles = rng.uniform(0, 2 * np.pi, n)[:, None] + np.array([0.0, 2.1, 4.2])[None, :]
    offsets = np.cos(angles)[..., None] * u[:, None, :] + np.sin(angles)[..., None] * v[:, None, :]
    vertices = centers[:, None, :] + 0.5 * sizes[:, None, None] * offsets
    return vertices.reshape(-1, 3), np.arange(3 * n).reshape(n, 3)


def grid_surface(x: np.ndarray, y: np.ndarray, z: np.ndarray, keep: np.ndarray | None = None) -> Mesh:
    """A height field: nodes (x[j], y[i], z[i, j]); cells where `keep` (ny-1, nx-1) is False are left out."""
    ny, nx = z.shape
    gx, gy = np.meshgrid(x, y)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])
    index = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, 1:], index[1:, :-1]
    cells = np.ones((ny - 1, nx - 1), dtype=bool) if keep is None else keep
    a, b, c, d = a[cells], b[cells], c[cells], d[cells]
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, faces


def transformed(mesh: Mesh, rotation: np.ndarray, translation: np.ndarray) -> Mesh:
    """The mesh rotated by a 3 x 3 matrix, then moved by `translation` (metres)."""
    vertices, faces = mesh
    return vertices @ np.asarray(rotation).T + np.asarray(translation, dtype=np.float64), faces


class MeshBuilder:
    """Collects mesh parts with one material each; `build()` concatenates them into one indexed mesh.

    `label` is the semantic class of parts added without one; `countable` marks an object whose placed copies
    are instances (cars, trees, poles: `objects` ids > 0) rather than stuff (buildings, fences: ids < 0).
    """

    def __init__(self, label: Semantic = Semantic.UNLABELED, countable: bool = False) -> None:
        self.label = label
        self.countable = countable
        # (vertices, faces, material, labels (F,) uint16, object ids (F,) int32)
        self._parts: list[tuple[np.ndarray, np.ndarray, Material, np.ndarray, np.ndarray]] = []

    def add(self, mesh: Mesh, material: Material = Material.SOLID, label: Semantic | np.ndarray | None = None,
            object_id: int = 0) -> None:
        """Add a part; `label`: its class, or one class per face (default the builder's `label`)."""
        vertices, faces = mesh
        if len(faces):
            labels = np.broadcast_to(np.asarray(self.label if label is None else label, dtype=np.uint16), len(faces))
            self._parts.append((np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), material,
                                labels, np.full(len(faces), object_id, np.int32)))

    def extend(self, other: "MeshBuilder", rotation: np.ndarray, translation: np.ndarray, object_id: int = 0) -> None:
        """Add every part of `other`, rotated then translated (an object built in its own frame); a non-zero
        `object_id` becomes the object id of all its faces."""
        for vertices, faces, material, labels, objects in other._parts:
            vertices, faces = transformed((vertices, faces), rotation, translation)
            self._parts.append((vertices, faces, material, labels, np.full_like(objects, object_id) if object_id
                                else objects))

    @property
    def n_faces(self) -> int:
        return sum(len(part[1]) for part in self._parts)

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(vertices (V, 3) float64, faces (F, 3) int64, materials (F,) int8, labels (F,) uint16 `Semantic`,
        object ids (F,) int32: > 0 countable objects, < 0 other objects, 0 none)."""
        if not self._parts:
            return (np.empty((0, 3)), np.empty((0, 3), dtype=np.int64), np.empty(0, dtype=np.int8),
                    np.empty(0, dtype=np.uint16), np.empty(0, dtype=np.int32))
        offsets = np.cumsum([0] + [len(part[0]) for part in self._parts[:-1]])
        vertices = np.concatenate([part[0] for part in self._parts])
        faces = np.concatenate([part[1] + offset for part, offset in zip(self._parts, offsets)])
        materials = np.concatenate([np.full(len(part[1]), int(part[2]), np.int8) for part in self._parts])
        labels = np.concatenate([part[3] for part in self._parts])
        objects = np.concatenate([part[4] for part in self._parts])
        return vertices, faces, materials, labels, objects
