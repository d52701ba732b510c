"""Rigid shape kinds as small objects: sphere, box, capsule, cylinder, plane and triangle mesh.

Each holds its size [m] in its own frame (a capsule's and a cylinder's axis is z, centred; a plane passes
through the origin) and knows: its ``kind`` name and ``code`` (its number in the compiled closed forms,
integration.kernels._shape), how pybullet makes it (:meth:`RigidShape.pybullet_args`) and reports it
(:func:`from_pybullet`, the one table ``BY_GEOM`` keyed by pybullet's GEOM_* constant), its closed-form signed
distance (distance.py), its bounding radius, its contact features (corners, round support points), a closed
triangulated surface and the sag of chords over it (for the check after the step) and its drawing in rerun.
A RigidLink (rigid.py) places shapes in its inertial frame as parts (shape, rotation, position).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import ClassVar

import numpy as np
import pybullet as p

from softbody.errors import InvalidInputError

from . import distance

#: the eight corners (8, 3) of the box [-1, 1]^3
CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
_NO_CORNERS = (np.zeros((0, 3)), np.zeros(3))


def _closed(tm) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """RigidShape.closed_surface of a trimesh.Trimesh (None if it is not watertight)."""
    if not tm.is_watertight:
        return None
    return np.asarray(tm.vertices, float), np.asarray(tm.faces, np.int64), np.asarray(tm.edges_unique, np.int64)


def _round_sags(radius: float, lengths: np.ndarray) -> np.ndarray:
    """RigidShape.chord_sags on a surface of curvature ``radius`` [m]: R - sqrt(R^2 - L^2 / 4), NaN for a chord
    longer than the diameter (it cannot rest on it by both ends)."""
    L = np.asarray(lengths, float)
    with np.errstate(invalid="ignore"):
        return np.where(L <= 2.0 * radius, radius - np.sqrt(radius ** 2 - 0.25 * L ** 2), np.nan)


#: two faces of a mesh meeting at less than this angle [rad] are one flat face (no sharp edge between them)
FEATURE_ANGLE = 1e-3
_NO_EDGES = (np.zeros((0, 2, 3)), np.zeros((0, 3)), np.zeros(0))


def _planes(tm) -> tuple[np.ndarray, np.ndarray]:
    """The face planes of a convex trimesh.Trimesh: outward unit normals (f, 3) and offsets (f,) [m] (n . x <= offset
    inside)."""
    normals = np.asarray(tm.face_normals)
    return normals, np.einsum("ij,ij->i", normals, np.asarray(tm.vertices)[np.asarray(tm.faces)[:, 0]])


def _feature_edges(tm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RigidShape.feature_edges of a trimesh.Trimesh: its convex edges between faces more than FEATURE_ANGLE apart
    (a valley between two faces cannot poke into anything); of an open mesh (pybullet's triangle soup is two-sided)
    also its valleys as ridges seen from behind (their cone between the faces' back normals), and its rim's edges
    (bounding one face: their cone the half space beyond the rim, both sides of the face)."""
    import trimesh

    if not len(tm.faces):
        return _NO_EDGES
    v, normals = np.asarray(tm.vertices), np.asarray(tm.face_normals)
    angles = np.asarray(tm.face_adjacency_angles)
    convex = np.asarray(tm.face_adjacency_convex, bool)
    pairs, shared = np.asarray(tm.face_adjacency), np.asarray(tm.face_adjacency_edges)
    open_mesh = not tm.is_watertight
    sides = [(convex, 1.0), (~convex, -1.0)] if open_mesh else [(convex, 1.0)]  # (which edges, their faces' side)
    ends, middles, cosines = [], [], []
    for which, sign in sides:
        sharp = (angles > FEATURE_ANGLE) & which
        n1, n2 = sign * normals[pairs[sharp, 0]], sign * normals[pairs[sharp, 1]]
        middle = n1 + n2
        length = np.linalg.norm(middle, axis=1)
        ok = length > 1e-9  # faces back to back (a flat sliver) have no cone between them
        middle = middle[ok] / length[ok, None]
        ends.append(v[shared[sharp][ok]])
        middles.append(middle)
        cosines.append(np.einsum("ij,ij->i", middle, n1[ok]))
    rim = trimesh.grouping.group_rows(tm.edges_sorted, require_count=1) if open_mesh else []
    if len(rim):  # an open mesh: the rim's edges, their cone the half space beyond the face's edge
        edge, face = np.asarray(tm.edges_sorted)[rim], np.asarray(tm.edges_face)[rim]
        a, b = v[edge[:, 0]], v[edge[:, 1]]
        away = np.cross(b - a, normals[face])
        away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-300)
        inward = v[tm.faces[face]].mean(axis=1) - a  # towards the face's centre
        away *= np.where(np.einsum("ij,ij->i", away, inward) > 0, -1.0, 1.0)[:, None]
        ends.append(np.stack([a, b], axis=1))
        middles.append(away)
        cosines.append(np.zeros(len(rim)))
    return np.concatenate(ends), np.concatenate(middles), np.concatenate(cosines)


def _pose(pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(position (3,), quaternion xyzw (4,), rotation (3, 3)) of a pose (position, quaternion) or None (identity)."""
    from .bullet import quat_matrix  # bullet.py builds on this module

    pos, quat = (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0])) if pose is None else pose
    return pos, quat, quat_matrix(quat)


@dataclass(frozen=True, eq=False)
class RigidShape:
    """A rigid shape in its own frame (the base of the kinds below)."""

    kind: ClassVar[str]
    code: ClassVar[int | None] = None  # its number in the compiled closed forms (kernels._shape); None: no closed form
    geom: ClassVar[int]  # pybullet's GEOM_* constant
    closed_form: ClassVar[bool] = True  # distance.py has its signed distance
    bounded: ClassVar[bool] = True  # False: infinite (a plane)
    #: one flag per support point (:meth:`support_points`): True on a smooth surface, False on a rim; () where the
    #: shape offers corners instead
    round: ClassVar[tuple[bool, ...]] = ()
    #: a soft edge can meet it between its nodes (collision.edge_contacts): not a plane (a straight edge is
    #: deepest at an end) nor a sphere (the sag of a chord between two nodes resting on it is the discretisation:
    #: held, a coarse sheet balanced on its facets' edges and slid off), nor a mesh (no closed form)
    between_nodes: ClassVar[bool] = False
    # Mesh's fields (not annotated here, so that they keep their place in Mesh's constructor)
    concave = False  # a static triangle soup
    file = ""  # the mesh's file ("" if made from vertices)

    @property
    def size(self) -> np.ndarray:
        """The size as the compiled closed forms take it (kernels.part_arrays, distance.shape_distance)."""
        raise NotImplementedError

    def extent(self) -> np.ndarray:
        """(3,) half extents [m] of its box in its own frame (the shapes that meet soft edges between nodes)."""
        raise NotImplementedError

    def linear_between(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(m,) bool: where the signed distance is linear along the segments a-b (m, 3 each, the shape's frame), so
        deepest at an end (collision.edge_contacts skips them); none known by default."""
        return np.zeros(len(a), dtype=bool)

    def face_span(self, a: np.ndarray, b: np.ndarray, points: np.ndarray, facing: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Where segments a + t (b - a) (m, 3 each, the shape's frame) lie across one of its flat faces: the face near
        ``points`` (m, 3) on them whose outward normal faces the segments' outward normals ``facing`` (m, 3) (an
        edge lying across a face rests on the face, not on the side it may be as near to at a rim). Returns
        (span (m, 2): the parameters where each segment enters and leaves the region over that face, NaN for none;
        normal (m, 3): the face's outward unit normal; offset (m,): its plane's distance from the centre), or None
        for a shape without flat faces."""
        return None

    @classmethod
    def from_size(cls, size) -> RigidShape:
        """The shape of a :attr:`size`."""
        raise NotImplementedError

    @classmethod
    def from_pybullet(cls, dims, file: str) -> RigidShape:
        """The shape of pybullet's getCollisionShapeData / getVisualShapeData dimensions (and mesh file)."""
        return cls.from_size(dims)

    def params(self) -> dict:
        """The size as RigidLink.params holds it (a World's own bodies)."""
        raise NotImplementedError

    @classmethod
    def from_params(cls, params: dict, concave: bool = False) -> RigidShape:
        """The inverse of :meth:`params`."""
        raise NotImplementedError

    def pybullet_args(self, visual: bool = False) -> dict:
        """Keyword arguments of pybullet's createCollisionShape (createVisualShape if ``visual``)."""
        raise NotImplementedError

    def distance(self, x: np.ndarray) -> distance.Result:
        """Closest points (m, 3), outward unit normals (m, 3) and signed distances (m,) [m] of points x (m, 3) in
        the shape's frame."""
        raise ValueError(f"no closed-form distance for shape {self.kind!r}")

    def bounding_radius(self) -> float:
        """Radius [m] of a ball about the shape's origin that holds it (inf: unbounded or unknown extent)."""
        raise NotImplementedError

    def convex_part(self) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(size, vertices (k, 3) of a convex mesh or None) as a convex part of a link; None if not convex."""
        return self.size, None

    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        """Corners (k, 3) in the shape's frame (box corners, mesh vertices) and the centre (3,) of the convex part
        they belong to (NaN: none, a concave mesh)."""
        return _NO_CORNERS

    def support_points(self, directions: np.ndarray, rotation: np.ndarray, centre: np.ndarray) -> list[np.ndarray]:
        """For unit world directions (T, 3), the shape's points (T, 3) furthest along each, one array per flag of
        :attr:`round`, with the shape at ``centre`` (3,) [m] turned by ``rotation`` (3, 3) (shape to world)."""
        return []

    def feature_edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Its sharp edges in its own frame, for a soft edge meeting one between the ends of both
        (collision.mesh_edge_contacts: meshes, and boxes on a link with a mesh part; a link of primitive parts only
        has collision.edge_contacts): ends (k, 2, 3) [m], the unit middle (k, 3) of each edge's cone of outward
        normals (between the normals of the faces it joins) and the cosine (k,) of the cone's half angle; none (empty
        arrays) by default."""
        return _NO_EDGES

    def hull_planes(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The planes of a convex shape with sharp edges (a box, a convex mesh) in its own frame: outward unit normals
        (f, 3) and offsets (f,) [m], n . x <= offset inside; None for others (a concave mesh, round shapes)."""
        return None

    @cached_property
    def closed_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """A closed triangulated surface of the shape in its own frame, for the check after the step
        (intersection.py): vertices (k, 3) [m], outward triangles (t, 3), edges (e, 2); round shapes inscribed
        (a sag of at most ~1% of the radius). None where there is none: a plane, a mesh that is not closed."""
        return None

    def chord_sags(self, lengths: np.ndarray) -> np.ndarray:
        """(m,) the deepest [m] straight chords of ``lengths`` (m,) [m] lie inside the shape with both ends on its
        surface: what a soft surface of such edges resting on it sags through it by discretisation (not
        modelled, docs/contact.md); 0 for flat-faced shapes, NaN for a chord that cannot rest on it by both
        ends."""
        return np.zeros(len(lengths))

    def draw(self, color, pose: tuple | None = None, plane_size: float | None = None, subdivisions: int = 3):
        """A rerun archetype of the shape at ``pose`` (position (3,), quaternion xyzw (4,)) in its link's frame
        (None: the link frame itself, no transform logged), or None if it cannot be drawn. ``plane_size`` [m]:
        edge of the square drawn for a plane (None: planes are not drawn); ``subdivisions``: a sphere's icosphere."""
        return None


@dataclass(frozen=True, eq=False)
class Sphere(RigidShape):
    """A sphere of ``radius`` [m] about the origin."""

    radius: float
    kind: ClassVar[str] = "sphere"
    code: ClassVar[int] = 0
    geom: ClassVar[int] = p.GEOM_SPHERE
    round: ClassVar[tuple[bool, ...]] = (True,)

    @property
    def size(self) -> np.ndarray:
        return np.array([self.radius], float)

    @classmethod
    def from_size(cls, size) -> Sphere:
        return cls(float(size[0]))

    def params(self) -> dict:
        return {"radius": self.radius}

    @classmethod
    def from_params(cls, params: dict, concave: bool = False) -> Sphere:
        return cls(float(params["radius"]))

    def pybullet_args(self, visual: bool = False) -> dict:
        return {"shapeType": self.geom, "radius": self.radius}

    def distance(self, x: np.ndarray) -> distance.Result:
        return distance.sphere(x, self.radius)

    def bounding_radius(self) -> float:
        return float(self.radius)

    def support_points(self, directions: np.ndarray, rotation: np.ndarray, centre: np.ndarray) -> list[np.ndarray]:
        return [centre + self.radius * directions]  # no frame needed

    @cached_property
    def closed_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import trimesh

        return _closed(trimesh.creation.icosphere(subdivisions=3, radius=float(self.radius)))

    def chord_sags(self, lengths: np.ndarray) -> np.ndarray:
        return _round_sags(self.radius, lengths)

    def draw(self, color, pose: tuple | None = None, plane_size: float | None = None, subdivisions: int = 3):
        import rerun as rr
        import trimesh

        # a smooth mesh with normals (rerun's ellipsoid is visibly faceted)
        ball = trimesh.creation.icosphere(subdivisions=subdivisions, radius=float(self.radius))
        verts = ball.vertices if pose is None else ball.vertices + pose[0]
        return rr.Mesh3D(vertex_positions=verts, triangle_indices=ball.faces, vertex_normals=ball.vertex_normals,
                         albedo_factor=color)


#: a box face counts as facing a soft edge whose outward normal makes a dot product below this with its own
#: (collision.FACING's rule)
FACING_FACES = -0.1


@dataclass(frozen=True, eq=False)
class Box(RigidShape):
    """A box of ``half_extents`` (3,) [m] about the origin."""

    half_extents: np.ndarray
    kind: ClassVar[str] = "box"
    code: ClassVar[int] = 1
    geom: ClassVar[int] = p.GEOM_BOX
    between_nodes: ClassVar[bool] = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "half_extents", np.asarray(self.half_extents, float))

    @property
    def size(self) -> np.ndarray:
        return self.half_extents

    @classmethod
    def from_size(cls, size) -> Box:
        return cls(np.asarray(size, float))

    @classmethod
    def from_pybullet(cls, dims, file: str) -> Box:
        return cls(np.array([0.5 * float(d) for d in dims[:3]]))  # pybullet reports full extents

    def params(self) -> dict:
        return {"half_extents": self.half_extents}

    @classmethod
    def from_params(cls, params: dict, concave: bool = False) -> Box:
        return cls(params["half_extents"])

    def pybullet_args(self, visual: bool = False) -> dict:
        return {"shapeType": self.geom, "halfExtents": self.half_extents.tolist()}

    def distance(self, x: np.ndarray) -> distance.Result:
        return distance.box(x, self.half_extents)

    def bounding_radius(self) -> float:
        return float(np.linalg.norm(self.half_extents))

    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        return CORNERS * self.half_extents, np.zeros(3)

    def extent(self) -> np.ndarray:
        return self.half_extents

    def face_span(self, a: np.ndarray, b: np.ndarray, points: np.ndarray, facing: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The face nearest to ``points`` (where they stand out furthest beyond the half extents, or lie least deep
        inside) among those facing ``facing``, and the stretch of each segment over it: within the face's extents
        along the other two axes."""
        e = self.half_extents
        m = len(a)
        rows = np.arange(m)
        side = np.where(points >= 0.0, 1.0, -1.0)  # the faces on the points' sides
        faces = side * facing < FACING_FACES  # ... whose normals face the segments
        beyond = np.where(faces, np.abs(points) - e, -np.inf)
        axis = np.argmax(beyond, axis=1)
        d = b - a
        lo, hi = np.zeros(m), np.ones(m)
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                other = axis != k  # the slab |x_k| <= e_k, for the two axes across the face
                t1, t2 = (-e[k] - a[:, k]) / d[:, k], (e[k] - a[:, k]) / d[:, k]
                parallel = d[:, k] == 0
                inside = np.abs(a[:, k]) <= e[k]
                enter = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
                leave = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
                lo = np.where(other, np.maximum(lo, enter), lo)
                hi = np.where(other, np.minimum(hi, leave), hi)
        ok = (lo <= hi) & np.isfinite(beyond[rows, axis])
        normal = np.zeros((m, 3))
        normal[rows, axis] = side[rows, axis]
        return np.where(ok[:, None], np.column_stack([lo, hi]), np.nan), normal, e[axis]

    def linear_between(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Both ends in one face's region (over that face, or inside nearest to it: a convex region where the
        distance is that face's)."""
        qa, qb = np.abs(a) - self.half_extents, np.abs(b) - self.half_extents
        axis = np.argmax(qa, axis=1)
        rows = np.arange(len(a))
        same = (np.argmax(qb, axis=1) == axis) & (np.sign(a[rows, axis]) == np.sign(b[rows, axis]))
        qa[rows, axis] = qb[rows, axis] = -np.inf  # the other two axes: within the face's extents
        return same & (qa.max(axis=1) <= 0.0) & (qb.max(axis=1) <= 0.0)

    def feature_edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Its twelve edges, each the cone of quarter turn between its two faces."""
        if "_edges" not in self.__dict__:
            import trimesh

            object.__setattr__(self, "_edges", _feature_edges(trimesh.creation.box(extents=2.0 * self.half_extents)))
        return self._edges

    def hull_planes(self) -> tuple[np.ndarray, np.ndarray]:
        eye = np.eye(3)
        return np.concatenate([eye, -eye]), np.concatenate([self.half_extents, self.half_extents])

    @cached_property
    def closed_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import trimesh

        return _closed(trimesh.creation.box(extents=2.0 * self.half_extents))

    def draw(self, color, pose: tuple | None = None, plane_size: float | None = None, subdivisions: int = 3):
        import rerun as rr

        placed = {} if pose is None else {"centers": [pose[0]], "quaternions": [rr.Quaternion(xyzw=pose[1])]}
        return rr.Boxes3D(half_sizes=[self.half_extents], **placed, colors=color, fill_mode="solid")


@dataclass(frozen=True, eq=False)
class _Axial(RigidShape):
    """A shape of ``radius`` [m] about the z axis, ``length`` [m] long, centred (capsule, cylinder)."""

    radius: float
    length: float
    between_nodes: ClassVar[bool] = True

    @property
    def size(self) -> np.ndarray:
        return np.array([self.radius, self.length], float)

    def extent(self) -> np.ndarray:
        return np.array([self.radius, self.radius, 0.5 * self.length + (self.radius if self.round[0] else 0.0)])

    @classmethod
    def from_size(cls, size) -> _Axial:
        return cls(float(size[0]), float(size[1]))

    @classmethod
    def from_pybullet(cls, dims, file: str) -> _Axial:
        return cls(float(dims[1]), float(dims[0]))  # pybullet reports (length, radius)

    def params(self) -> dict:
        return {"radius": self.radius, "length": self.length}

    @classmethod
    def from_params(cls, params: dict, concave: bool = False) -> _Axial:
        return cls(float(params["radius"]), float(params["length"]))

    def pybullet_args(self, visual: bool = False) -> dict:
        return {"shapeType": self.geom, "radius": self.radius, ("length" if visual else "height"): self.length}

    def chord_sags(self, lengths: np.ndarray) -> np.ndarray:
        """Its side's (and a capsule's caps'): a chord across the axis sags as on a sphere of its radius."""
        return _round_sags(self.radius, lengths)

    def _rim(self, local: np.ndarray) -> np.ndarray:
        """Offsets (T, 3) from an end's centre of the support points along directions (T, 3) in the shape's frame."""
        raise NotImplementedError

    def support_points(self, directions: np.ndarray, rotation: np.ndarray, centre: np.ndarray) -> list[np.ndarray]:
        """Each end's point (so that a part lying flat offers both ends)."""
        rim = self._rim(directions @ rotation)  # the directions in the shape's frame
        return [centre + (rim + np.array([0.0, 0.0, end])) @ rotation.T
                for end in (0.5 * self.length, -0.5 * self.length)]


@dataclass(frozen=True, eq=False)
class Capsule(_Axial):
    """A capsule: two hemispheres of ``radius`` [m] whose centres lie ``length`` [m] apart on z, centred."""

    kind: ClassVar[str] = "capsule"
    code: ClassVar[int] = 2
    geom: ClassVar[int] = p.GEOM_CAPSULE
    round: ClassVar[tuple[bool, ...]] = (True, True)

    def distance(self, x: np.ndarray) -> distance.Result:
        return distance.capsule(x, self.radius, self.length)

    def bounding_radius(self) -> float:
        return float(math.hypot(self.radius, 0.5 * self.length) + self.radius)

    def _rim(self, local: np.ndarray) -> np.ndarray:
        return self.radius * local  # on the end's hemisphere

    @cached_property
    def closed_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import trimesh

        return _closed(trimesh.creation.capsule(height=float(self.length), radius=float(self.radius), count=[32, 32]))

    def draw(self, color, pose: tuple | None = None, plane_size: float | None = None, subdivisions: int = 3):
        import rerun as rr

        pos, quat, R = _pose(pose)  # rerun's capsule runs from its origin along +z: start it half a length down
        return rr.Capsules3D(lengths=[self.length], radii=[self.radius],
                             translations=[pos - 0.5 * self.length * R[:, 2]], quaternions=[rr.Quaternion(xyzw=quat)],
                             colors=color)


@dataclass(frozen=True, eq=False)
class Cylinder(_Axial):
    """A cylinder of ``radius`` [m] and ``length`` [m] along z, centred."""

    kind: ClassVar[str] = "cylinder"
    code: ClassVar[int] = 3
    geom: ClassVar[int] = p.GEOM_CYLINDER
    round: ClassVar[tuple[bool, ...]] = (False, False)  # its support points lie on the caps' rims

    def distance(self, x: np.ndarray) -> distance.Result:
        return distance.cylinder(x, self.radius, self.length)

    def bounding_radius(self) -> float:
        return float(math.hypot(self.radius, 0.5 * self.length))

    def _rim(self, local: np.ndarray) -> np.ndarray:
        radial = local.copy()  # the cap's rim, or its centre for an axial direction
        radial[:, 2] = 0.0
        norm = np.linalg.norm(radial, axis=1, keepdims=True)
        return np.where(norm > 1e-12, self.radius * radial / np.maximum(norm, 1e-300), 0.0)

    @cached_property
    def closed_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import trimesh

        return _closed(trimesh.creation.cylinder(radius=float(self.radius), height=float(self.length), sections=32))

    def draw(self, color, pose: tuple | None = None, plane_size: float | None = None, subdivisions: int = 3):
        import rerun as rr

        pos, quat, _ = _pose(pose)
        return rr.Cylinders3D(lengths=[self.length], radii=[self.radius], centers=[pos],
                              quaternions=[rr.Quaternion(xyzw=quat)], colors=color, fill_mode="solid")


@dataclass(frozen=True, eq=False)
class Plane(RigidShape):
    """An infinite plane through the origin with outward unit ``normal`` (3,); below it is inside."""

    normal: np.ndarray
    kind: ClassVar[str] = "plane"
    code: ClassVar[int] = 4
    geom: ClassVar[int] = p.GEOM_PLANE
    bounded: ClassVar[bool] = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "normal", np.asarray(self.normal, float))

    @property
    def size(self) -> np.ndarray:
        return self.normal

    @classmethod
    def from_size(cls, size) -> Plane:
        return cls(np.asarray(size, float))

    @classmethod
    def from_pybullet(cls, dims, file: str) -> Plane:
        return cls(np.array([float(d) for d in dims[:3]]))

    def params(self) -> dict:
        return {"normal": self.normal}

    @classmethod
    def from_params(cls, params: dict, concave: bool = False) -> Plane:
        return cls(params["normal"])

    def pybullet_args(self, visual: bool = False) -> dict:
        return {"shapeType": self.geom, "planeNormal": self.normal.tolist()}

    def distance(self, x: np.ndarray) -> distance.Result:
        return distance.plane(x, self.normal)

    def bounding_radius(self) -> float:
        return math.inf

    def convex_part(self) -> None:
        return None

    def draw(self, color, pose: tuple | None = None, plane_size: float | None = None, subdivisions: int = 3):
        if plane_size is None:
            return None
        import rerun as rr

        pos, _, R = _pose(pose)
        n = R @ self.normal if pose is not None else self.normal
        helper = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
        t1 = np.cross(n, helper)
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        quad = np.array([-t1 - t2, t1 - t2, t1 + t2, -t1 + t2]) * (0.5 * plane_size)
        return rr.Mesh3D(vertex_positions=quad if pose is None else quad + pos, triangle_indices=[[0, 1, 2], [0, 2, 3]],
                         vertex_normals=np.tile(n, (4, 1)), albedo_factor=color)


@dataclass(frozen=True, eq=False)
class Mesh(RigidShape):
    """A triangle mesh: ``vertices`` (k, 3) [m] (scaled) and ``faces`` (f, 3), or a ``file`` trimesh reads
    times ``scale`` (3,); ``concave``: a static triangle soup (else pybullet uses its convex hull)."""

    vertices: np.ndarray | None = None
    faces: np.ndarray | None = None
    file: str = ""
    scale: np.ndarray = (1.0, 1.0, 1.0)
    concave: bool = False
    kind: ClassVar[str] = "mesh"
    geom: ClassVar[int] = p.GEOM_MESH
    closed_form: ClassVar[bool] = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "scale", np.asarray(self.scale, float))

    @property
    def size(self) -> np.ndarray:
        return self.scale

    @classmethod
    def from_size(cls, size) -> Mesh:
        return cls(scale=np.asarray(size, float))

    @classmethod
    def from_pybullet(cls, dims, file) -> Mesh:
        name = file.decode() if isinstance(file, bytes) else str(file)
        return cls(file="" if name == "unknown_file" else name, scale=np.array([float(d) for d in dims[:3]]))

    def params(self) -> dict:
        return {"vertices": self.vertices, "faces": self.faces}

    @classmethod
    def from_params(cls, params: dict, concave: bool = False) -> Mesh:
        return cls(np.asarray(params["vertices"]), np.asarray(params["faces"]), concave=concave)

    def pybullet_args(self, visual: bool = False) -> dict:
        if self.vertices is None:
            args = {"shapeType": self.geom, "fileName": self.file, "meshScale": self.scale.tolist()}
            if self.concave and not visual:
                args["flags"] = p.GEOM_FORCE_CONCAVE_TRIMESH
            return args
        args = {"shapeType": self.geom, "vertices": np.asarray(self.vertices).tolist()}
        if self.concave or visual:
            args["indices"] = np.asarray(self.faces).ravel().astype(int).tolist()
        return args

    def bounding_radius(self) -> float:
        """From the vertices; inf for a file's mesh (its extent unknown here: a link bounds it by its box)."""
        if self.vertices is None:
            return math.inf
        return float(np.linalg.norm(np.asarray(self.vertices), axis=1).max())

    @cached_property
    def hull(self) -> np.ndarray | None:
        """Vertices (k, 3) [m] of the convex shape pybullet collides with (the vertices, or the convex hull of the
        file's mesh, scaled); None for a concave mesh or a file that does not exist."""
        if self.concave:
            return None
        if self.vertices is not None:
            return np.asarray(self.vertices, float)
        if self.file and Path(self.file).exists():
            return np.asarray(load_trimesh(self.file).convex_hull.vertices) * np.asarray(self.scale)
        return None

    def convex_part(self) -> tuple[np.ndarray, np.ndarray] | None:
        return None if self.hull is None else (np.ones(3), self.hull)  # the vertices are scaled already

    def corners(self) -> tuple[np.ndarray, np.ndarray]:
        if self.concave:  # every vertex, of no convex part
            return np.asarray(self.vertices, float), np.full(3, np.nan)
        if self.hull is None:
            return _NO_CORNERS
        return self.hull, self.hull.mean(axis=0)

    def feature_edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sharp edges of the convex hull pybullet collides with, or of a concave mesh's own triangles (its
        convex edges and, open, its valleys from behind and its rim); none for a concave mesh's file that cannot be
        read (a convex one's unreadable file raises InvalidInputError, as :attr:`hull` does)."""
        if "_edges" not in self.__dict__:
            import trimesh

            tm = None
            if self.hull is not None:
                tm = trimesh.convex.convex_hull(self.hull)
            elif self.vertices is not None:
                tm = trimesh.Trimesh(np.asarray(self.vertices, float), np.asarray(self.faces), process=True)
            elif self.file and Path(self.file).exists():
                try:
                    tm = load_trimesh(self.file)
                    tm = trimesh.Trimesh(np.asarray(tm.vertices) * self.scale, tm.faces, process=True)
                except InvalidInputError:
                    tm = None
            object.__setattr__(self, "_edges", _NO_EDGES if tm is None else _feature_edges(tm))
        return self._edges

    def hull_planes(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The convex hull's planes (None for a concave mesh)."""
        if self.hull is None:
            return None
        if "_planes" not in self.__dict__:
            import trimesh

            object.__setattr__(self, "_planes", _planes(trimesh.convex.convex_hull(self.hull)))
        return self._planes

    @cached_property
    def closed_surface(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The convex hull pybullet collides with; a concave mesh's own triangles if they close."""
        import trimesh

        if self.hull is not None:
            return _closed(trimesh.convex.convex_hull(self.hull))
        if self.vertices is not None:
            return _closed(trimesh.Trimesh(np.asarray(self.vertices, float), np.asarray(self.faces), process=True))
        if self.file and Path(self.file).exists():
            try:
                tm = load_trimesh(self.file)
            except InvalidInputError:
                return None
            return _closed(trimesh.Trimesh(np.asarray(tm.vertices) * self.scale, tm.faces, process=True))
        return None

    def draw(self, color, pose: tuple | None = None, plane_size: float | None = None, subdivisions: int = 3):
        import rerun as rr
        import trimesh

        if self.vertices is not None:
            verts, faces = np.asarray(self.vertices), np.asarray(self.faces)
        elif self.file:
            try:
                tm = trimesh.load(self.file, force="mesh")
                verts, faces = np.asarray(tm.vertices) * np.asarray(self.scale), np.asarray(tm.faces)
            except Exception:  # a file trimesh cannot read: not drawn
                return None
        else:
            return None
        if pose is not None:
            pos, _, R = _pose(pose)
            verts = verts @ R.T + pos
        tm = trimesh.Trimesh(verts, faces, process=False)
        return rr.Mesh3D(vertex_positions=tm.vertices, triangle_indices=tm.faces, vertex_normals=tm.vertex_normals,
                         albedo_factor=color)


CLASSES: tuple[type[RigidShape], ...] = (Sphere, Box, Capsule, Cylinder, Plane, Mesh)
#: the one table of pybullet's shape types: GEOM_* -> class (any other type is read as a mesh)
BY_GEOM: dict[int, type[RigidShape]] = {cls.geom: cls for cls in CLASSES}
BY_KIND: dict[str, type[RigidShape]] = {cls.kind: cls for cls in CLASSES}


def from_pybullet(geom: int, dims, file: bytes | str = "") -> RigidShape:
    """The shape pybullet reports (getCollisionShapeData / getVisualShapeData: type, dimensions, mesh file)."""
    return BY_GEOM.get(geom, Mesh).from_pybullet(tuple(float(d) for d in dims), file)


def of_kind(kind: str) -> type[RigidShape]:
    """The class of a kind name; ValueError for an unknown one."""
    try:
        return BY_KIND[kind]
    except KeyError:
        raise ValueError(f"unknown rigid shape {kind!r}; known: {sorted(BY_KIND)}") from None


def load_trimesh(mesh) -> "object":
    """A trimesh.Trimesh from a Trimesh or a file path trimesh can read; clear error otherwise."""
    import trimesh

    if isinstance(mesh, trimesh.Trimesh):
        tm = mesh
    elif isinstance(mesh, (str, Path)):
        path = Path(mesh)
        if not path.exists():
            raise InvalidInputError(f"mesh file {str(path)!r} does not exist")
        try:
            tm = trimesh.load(str(path), force="mesh")
        except Exception as exc:
            raise InvalidInputError(f"trimesh cannot read {str(path)!r}: {exc}") from exc
    else:
        raise InvalidInputError(f"mesh must be a trimesh.Trimesh or a file path, got {type(mesh).__name__}")
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise InvalidInputError(f"{mesh!r} holds no triangles")
    return tm
