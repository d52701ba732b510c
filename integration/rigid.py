"""Rigid links owned by pybullet: a body's base (link -1) or one of its links, with its shapes, mode
(fixed / dynamic / kinematic) and pose.

A World made of its own primitives (add_sphere, add_box, ...) has one link per body, the base; a
URDF robot in the user's client has one per link that carries a collision shape.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from softbody.errors import InvalidInputError

from . import kernels
from .bullet import BASE, BulletAdapter, Shape, quat_matrix
from .distance import cross
from .shapes import RigidShape, load_trimesh, of_kind  # noqa: F401  (load_trimesh: imported from here too)

# A kinematic pose script: t [s] -> (position (3,), quaternion xyzw (4,)) or just a position.
PoseScript = Callable[[float], object]

SHAPES = ("sphere", "box", "plane", "mesh", "urdf")
# [m] how far outside a sharp edge RigidLink.edge_rounding probes pybullet's surface (beyond any collision margin)
PROBE_CLEARANCE = 0.01
# ... from up to this many of a part's sharp edges
PROBES = 8


class Part(NamedTuple):
    """One shape of a link: the shape, its rotation (3, 3) (shape frame -> link frame) and position (3,) [m] in
    the link's inertial frame."""

    shape: RigidShape
    rotation: np.ndarray
    position: np.ndarray


@dataclass
class RigidLink:
    """One rigid link in the pybullet world.

    id: pybullet body id; link: link index (-1: the base); shape: one of SHAPES ("urdf": a link of a body
    the World did not create, with ``shapes`` from pybullet); params: a primitive's size (radius,
    half_extents, normal, or vertices/faces of a mesh in the body frame); mass [kg] (0: fixed or
    kinematic); motion: pose script of a kinematic body; name: for logs and recordings; friction: the
    Coulomb coefficient against soft bodies (None: the soft body's own); movable: pybullet integrates the
    link's body (a free base or movable joints), so it takes part in the coupled solve; geometry: a World's
    own body's shape (integration.shapes; made from ``shape`` and ``params`` if not given), None for "urdf".
    """

    id: int
    adapter: BulletAdapter
    shape: str
    params: dict
    mass: float
    motion: PoseScript | None = None
    name: str = ""
    friction: float | None = None
    concave: bool = False
    _trimesh: object = field(default=None, repr=False)
    link: int = BASE
    movable: bool = False
    shapes: list[Shape] = field(default_factory=list)
    geometry: RigidShape | None = None

    def __post_init__(self) -> None:
        if self.geometry is None and self.shape != "urdf":
            self.geometry = of_kind(self.shape).from_params(self.params, self.concave)

    @property
    def parts(self) -> list[Part]:
        """The link's shapes in its inertial frame: a World body's one shape, or a URDF link's collision shapes."""
        if "_parts" not in self.__dict__:
            if self.geometry is not None:
                self._parts = [Part(self.geometry, np.eye(3), np.zeros(3))]
            else:
                self._parts = [Part(sh.geometry, quat_matrix(sh.quaternion), np.asarray(sh.position, float))
                               for sh in self.shapes]
        return self._parts

    @property
    def key(self) -> tuple[int, int]:
        return (self.id, self.link)

    @property
    def client(self) -> int:
        return self.adapter.client

    @property
    def mode(self) -> str:
        if self.motion is not None:
            return "kinematic"
        return "dynamic" if self.movable else "fixed"

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Current position (3,) [m] of the link's centre of mass and orientation (x, y, z, w)."""
        return self.adapter.pose(self.id, self.link)

    def rotation(self) -> np.ndarray:
        return quat_matrix(self.pose()[1])

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """Linear velocity of the centre of mass (3,) [m/s] and angular velocity (3,) [rad/s]."""
        return self.adapter.velocity(self.id, self.link)

    def point_velocity(self, points: np.ndarray) -> np.ndarray:
        """Velocity (m, 3) of material points of the link at world positions (m, 3)."""
        c, _, v, w = self.adapter.state(self.id, self.link)
        points = np.asarray(points, dtype=float)
        if not w.any():  # not spinning (most obstacles): the same velocity everywhere
            out = np.empty(points.shape)
            out[...] = v
            return out
        return v + cross(w, points - c)

    def to_world(self, local: np.ndarray) -> np.ndarray:
        c, q = self.pose()
        return local @ quat_matrix(q).T + c

    def to_local(self, world: np.ndarray) -> np.ndarray:
        c, q = self.pose()
        return (world - c) @ quat_matrix(q)

    def scripted_pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Pose of a kinematic body at time t from its script."""
        out = self.motion(t)
        if isinstance(out, tuple) and len(out) == 2:
            pos, orn = np.asarray(out[0], float), np.asarray(out[1], float)
        else:
            pos, orn = np.asarray(out, float), np.array([0.0, 0.0, 0.0, 1.0])
        if pos.shape != (3,) or orn.shape != (4,) or not (np.isfinite(pos).all() and np.isfinite(orn).all()):
            raise InvalidInputError(f"motion of rigid body {self.name!r} must return a position (3,) "
                                    f"or (position, quaternion xyzw); got {out!r} at t={t}")
        return pos, orn / np.linalg.norm(orn)

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        return self.adapter.aabb(self.id, self.link)

    def bounding_radius(self) -> float:
        """Radius [m] of a sphere about the link's centre of mass that holds all its shapes (inf for a plane).

        A World's own primitives are created with pybullet's default inertial frame (no offset), in which
        the shape's parameters and mesh vertices are given; a URDF link's radius comes from its shapes,
        or from its axis-aligned box when a shape's extent is unknown (a mesh)."""
        if "_bounding_radius" in self.__dict__:
            return self._bounding_radius
        if not all(part.shape.bounded for part in self.parts):  # a plane
            r = math.inf
        else:
            r = float(max((np.linalg.norm(part.position) + part.shape.bounding_radius() for part in self.parts),
                          default=math.inf))
            if not math.isfinite(r):  # a mesh: bound it by the box pybullet keeps around the link
                lo, hi = self.aabb()
                c, _ = self.pose()
                r = float(np.linalg.norm(0.5 * (lo + hi) - c) + 0.5 * np.linalg.norm(hi - lo))
        self._bounding_radius = r
        return r

    def convex_parts(self) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]]:
        """The link's convex shapes in its inertial frame: (kind, size, rotation (3, 3), position (3,),
        vertices (k, 3) of a convex mesh or None). Planes and concave meshes are not convex parts."""
        if "_convex_parts" in self.__dict__:
            return self._convex_parts
        parts = []
        for shape, R, pos in self.parts:
            convex = shape.convex_part()
            if convex is not None:
                parts.append((shape.kind, convex[0], R, pos, convex[1]))
        self._convex_parts = parts
        return parts

    def primitive_parts(self) -> list[Part] | None:
        """The link's parts (:attr:`parts`) if all have closed-form distances (distance.py); None if any shape is
        a mesh (pybullet's query then)."""
        if "_primitives" in self.__dict__:
            return self._primitives
        parts = None
        if self.parts and all(part.shape.closed_form for part in self.parts):
            parts = self.parts
        self._primitives = parts
        return parts

    def primitive_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`primitive_parts` as arrays for the compiled distances (kernels.part_arrays), made once."""
        if "_primitive_arrays" not in self.__dict__:
            self._primitive_arrays = kernels.part_arrays(self.primitive_parts())
        return self._primitive_arrays

    def round_parts(self) -> np.ndarray:
        """(S,) bool per point of :meth:`support_points`: True where it lies on a smooth surface (sphere,
        capsule), False on a rim (cylinder)."""
        if "_round" not in self.__dict__:
            self._round = np.array([flag for part in self.parts for flag in part.shape.round], dtype=bool)
        return self._round

    def round_part_arrays(self, pose: tuple[np.ndarray, np.ndarray] | None = None
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The round parts (those of :meth:`support_points`) in the world, for kernels.face_contacts_possible:
        kinds (P,) as RigidShape.code, sizes (P, 3) (radius, length, 0; a sphere's length 0), part-to-world rotations
        (P, 3, 3) and centres (P, 3) [m] at the link's current pose; ``pose``: that pose as (centre (3,), rotation
        matrix (3, 3)), if at hand."""
        if "_round_local" not in self.__dict__:  # the parts in the link's frame (kernels.part_arrays), made once
            self._round_local = kernels.part_arrays([part for part in self.parts if part.shape.round])
        kinds, sizes, R, pos = self._round_local
        if pose is None:
            c, q = self.pose()
            pose = (c, quat_matrix(q))
        c, Rl = pose
        return kinds, sizes, Rl @ R, c + pos @ Rl.T

    def support_points(self, directions: np.ndarray) -> np.ndarray:
        """For each world direction (T, 3) (unit vectors), the points (T, S, 3) of the link's round parts
        furthest along it: a sphere's, and each end's of a capsule (its two hemispheres) or of a cylinder
        (the rim of each cap, or the cap's centre for an axial direction), so that a part lying flat offers
        both ends. These are the deepest points of the part into a plane facing ``-direction``. Boxes and
        meshes offer their corners instead (:meth:`corner_points`)."""
        d = np.asarray(directions, float).reshape(-1, 3)
        parts = [part for part in self.parts if part.shape.round]
        if not parts:
            return np.zeros((len(d), 0, 3))
        c, q = self.pose()
        Rl = quat_matrix(q)
        out = []
        for shape, R, pos in parts:  # part frame -> world: Rl @ R
            out += shape.support_points(d, Rl @ R, c + Rl @ pos)
        return np.stack(out, axis=1)

    def corner_points(self) -> tuple[np.ndarray, np.ndarray]:
        """World positions (k, 3) of the link's corners (box corners, the vertices of convex and concave
        meshes) and the centres (k, 3) of the convex parts they belong to (NaN for a concave mesh's)."""
        if "_corners_local" not in self.__dict__:
            local, centre, part = [], [], []
            for k, (shape, R, pos) in enumerate(self.parts):
                corners, middle = shape.corners()
                if len(corners):
                    local.append(corners @ R.T + pos)
                    centre.append(np.broadcast_to(middle @ R.T + pos, local[-1].shape))
                    part.append(np.full(len(corners), k))
            self._corners_local = np.concatenate(local) if local else np.zeros((0, 3))
            self._corner_centres = np.concatenate(centre) if centre else np.zeros((0, 3))
            self._corner_part = np.concatenate(part) if part else np.zeros(0, np.int64)
        if not len(self._corners_local):
            return np.zeros((0, 3)), np.zeros((0, 3))
        return self.to_world(self._corners_local), self.to_world(self._corner_centres)

    def feature_edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sharp edges of the link's parts in its frame (RigidShape.feature_edges: ends (k, 2, 3) [m], cone
        middles (k, 3), cone half angles' cosines (k,)), made once; none for a link of primitive parts only (a soft
        edge meets those in collision.edge_contacts)."""
        if "_feature_edges" not in self.__dict__:
            ends, middles, cosines = [np.zeros((0, 2, 3))], [np.zeros((0, 3))], [np.zeros(0)]
            part = [np.zeros(0, np.int64)]
            if self.primitive_parts() is None:
                for k, (shape, R, pos) in enumerate(self.parts):
                    e, m, c = shape.feature_edges()
                    ends.append(e @ R.T + pos)
                    middles.append(m @ R.T)
                    cosines.append(c)
                    part.append(np.full(len(c), k))
            self._feature_edges = (np.concatenate(ends), np.concatenate(middles), np.concatenate(cosines))
            self._feature_part = np.concatenate(part)
        return self._feature_edges

    def edge_part_planes(self) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """Per part of the link, the planes of its convex shape in the link's frame (RigidShape.hull_planes: normals
        (f, 3), offsets (f,) [m]; None for a concave mesh or a round part), made once (:attr:`edge_part`: which part
        each sharp edge belongs to)."""
        if "_edge_part_planes" not in self.__dict__:
            planes = []
            for shape, R, pos in self.parts:
                hp = shape.hull_planes()
                planes.append(None if hp is None else (hp[0] @ R.T, hp[1] + hp[0] @ R.T @ pos))
            self._edge_part_planes = planes
        return self._edge_part_planes

    @property
    def edge_part(self) -> np.ndarray:
        """(k,) the part (index into :attr:`parts`) of each sharp edge of :meth:`feature_edges`."""
        self.feature_edges()
        return self._feature_part

    def part_rounding(self) -> np.ndarray:
        """(P,) [m] per part: how far outside its sharp edges and corners pybullet's own surface lies, the collision
        margin pybullet keeps around a convex mesh (where its distance query, and so the node contacts, find the
        surface; ~1 mm) and 0 for a box (its margin lies inside its edges) or a part without sharp edges. Probed once
        per part with pybullet's distance query from points just outside the middles of up to PROBES of its sharp
        edges, along their cones' middles (the edge's point is the nearest there, unless another part of the link is
        nearer: the least over the probes), rounded to 1e-9 m (the same in any pose: a restored World steps alike)."""
        if "_part_rounding" not in self.__dict__:
            ends, middles, _ = self.feature_edges()
            out = np.zeros(len(self.parts))
            if len(ends):
                part = self._feature_part
                clear = PROBE_CLEARANCE
                for k in np.unique(part).tolist():
                    mine = np.flatnonzero(part == k)
                    mine = mine[np.linspace(0, len(mine) - 1, min(PROBES, len(mine))).round().astype(int)]
                    probe = self.to_world(0.5 * (ends[mine, 0] + ends[mine, 1]) + clear * middles[mine])
                    d = self.adapter.point_distances(self.id, self.link, probe, 2.0 * clear)
                    margin = np.clip(clear - d[np.isfinite(d)], 0.0, clear)
                    out[k] = round(float(margin.min()), 9) if len(margin) else 0.0
            self._part_rounding = out
        return self._part_rounding

    def edge_rounding(self) -> np.ndarray:
        """(k,) [m] :meth:`part_rounding` per sharp edge (:meth:`feature_edges`)."""
        return self.part_rounding()[self.edge_part]

    def corner_rounding(self) -> np.ndarray:
        """(k,) [m] :meth:`part_rounding` per corner (:meth:`corner_points`); zeros for a link of primitive parts."""
        if "_corner_rounding" not in self.__dict__:
            self.corner_points()
            self._corner_rounding = (np.zeros(len(self._corner_part)) if self.primitive_parts() is not None
                                     else self.part_rounding()[self._corner_part])
        return self._corner_rounding

    def support_centres(self) -> np.ndarray:
        """World centres (S, 3) of the round parts, one per point of :meth:`support_points`."""
        if "_support_local" not in self.__dict__:  # the parts' centres in the link's frame, one per point
            local = [pos for shape, _, pos in self.parts for _ in shape.round]
            self._support_local = np.array(local, dtype=float).reshape(-1, 3)
        c, q = self.pose()
        return c + self._support_local @ quat_matrix(q).T

RigidBody = RigidLink  # the name of a World's own single-link bodies
