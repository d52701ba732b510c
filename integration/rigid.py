"""Rigid bodies owned by pybullet: shape, mode (fixed / dynamic / kinematic) and pose."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pybullet as p

from softbody.errors import InvalidInputError

# A kinematic pose script: t [s] -> (position (3,), quaternion xyzw (4,)) or just a position.
PoseScript = Callable[[float], object]

SHAPES = ("sphere", "box", "plane", "mesh")


@dataclass
class RigidBody:
    """A rigid body in the pybullet world.

    id: pybullet body id; shape: one of SHAPES; params: the shape's size (radius, half_extents,
    normal, or vertices/faces of a mesh in the body frame); mass: 0 for fixed and kinematic bodies;
    motion: pose script for kinematic bodies; name: for logs and recordings.
    """

    id: int
    client: int
    shape: str
    params: dict
    mass: float
    motion: PoseScript | None = None
    name: str = ""
    friction: float | None = None
    concave: bool = False
    _trimesh: object = field(default=None, repr=False)

    @property
    def mode(self) -> str:
        return "kinematic" if self.motion is not None else ("dynamic" if self.mass > 0 else "fixed")

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Current position (3,) [m] and orientation quaternion (x, y, z, w)."""
        pos, orn = p.getBasePositionAndOrientation(self.id, physicsClientId=self.client)
        return np.array(pos), np.array(orn)

    def rotation(self) -> np.ndarray:
        _, q = self.pose()
        return np.array(p.getMatrixFromQuaternion(q.tolist())).reshape(3, 3)

    def velocity(self) -> tuple[np.ndarray, np.ndarray]:
        """Linear velocity of the centre of mass (3,) [m/s] and angular velocity (3,) [rad/s]."""
        v, w = p.getBaseVelocity(self.id, physicsClientId=self.client)
        return np.array(v), np.array(w)

    def point_velocity(self, points: np.ndarray) -> np.ndarray:
        """Velocity (m, 3) of material points of the body at world positions (m, 3)."""
        v, w = self.velocity()
        c, _ = self.pose()
        return v + np.cross(w, np.asarray(points) - c)

    def to_world(self, local: np.ndarray) -> np.ndarray:
        c, _ = self.pose()
        return local @ self.rotation().T + c

    def to_local(self, world: np.ndarray) -> np.ndarray:
        c, _ = self.pose()
        return (world - c) @ self.rotation()

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
        lo, hi = p.getAABB(self.id, physicsClientId=self.client)
        return np.array(lo), np.array(hi)

    def bounding_radius(self) -> float:
        """Radius [m] of a sphere about the body's origin that holds the whole shape (inf for a plane).

        The origin is ``pose()``'s position: the World creates every body with pybullet's default
        inertial frame (no offset), in which the shape's parameters and mesh vertices are given."""
        if self.shape == "sphere":
            return float(self.params["radius"])
        if self.shape == "box":
            return float(np.linalg.norm(self.params["half_extents"]))
        if self.shape == "mesh":
            if "_bounding_radius" not in self.__dict__:
                self._bounding_radius = float(np.linalg.norm(np.asarray(self.params["vertices"]), axis=1).max())
            return self._bounding_radius
        return float("inf")

    def surface_vertices(self) -> np.ndarray:
        """World positions of the shape's sharp vertices (box corners, mesh vertices); (0, 3) for smooth shapes."""
        if self.shape == "box":
            h = np.asarray(self.params["half_extents"])
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
            return self.to_world(corners)
        if self.shape == "mesh":
            return self.to_world(np.asarray(self.params["vertices"]))
        return np.zeros((0, 3))


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
