"""The pybullet side of a World, behind one adapter: the client, its bodies and links, their poses,
velocities and shapes, their generalized masses and Jacobians, and velocity changes handed back.

Everything else in ``integration`` talks to pybullet through :class:`BulletAdapter` (the collision
probe in collision.py being the one other caller). Conventions:

- A *link* is ``(body id, link index)``; the base is link -1. A link's pose is that of its inertial
  (centre-of-mass) frame, as pybullet reports it (``getBasePositionAndOrientation`` for the base,
  ``getLinkState(...)[0:2]`` for links); its velocity is the centre of mass's linear velocity and the
  angular velocity, both in world coordinates.
- A body's *generalized velocity* u (n,) in world coordinates: for a free base ``(omega, v_com)`` of the
  base (6), then the velocities of its revolute and prismatic joints in joint order; a fixed base
  (pybullet reports mass 0 for it) contributes nothing. Its mass matrix M (n, n) gives the kinetic
  energy u^T M u / 2, and the point Jacobian J (3, n) of a material point gives its velocity J u.
  pybullet's ``calculateJacobian`` and ``calculateMassMatrix`` express a free base in the base's own
  frame (and take the Jacobian's point in the URDF link frame); this module converts to the world
  convention above, and the tests check J u and u^T M u against pybullet's own link velocities.
"""
from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pybullet as p

from softbody.errors import InvalidInputError

from .shapes import BY_GEOM, RigidShape, from_pybullet

BASE = -1
MOVABLE_JOINTS = (p.JOINT_REVOLUTE, p.JOINT_PRISMATIC)
GEOMETRY = {geom: cls.kind for geom, cls in BY_GEOM.items()}  # pybullet's GEOM_* -> kind name (shapes.BY_GEOM)


def quat_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q.tolist() if isinstance(q, np.ndarray) else (float(c) for c in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product a * b of quaternions (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz])


def quat_from_euler(angles) -> np.ndarray:
    """Quaternion (x, y, z, w) of Euler angles (3,) [rad] in pybullet's convention."""
    return np.array(p.getQuaternionFromEuler(list(angles)))


def quat_difference(q0, q1) -> np.ndarray:
    """The rotation (x, y, z, w) that takes orientation q0 to q1."""
    return np.array(p.getDifferenceQuaternion(list(q0), list(q1)))


def rotation_quat(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation vector (3,) [rad]."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.array([0.5 * rotvec[0], 0.5 * rotvec[1], 0.5 * rotvec[2], 1.0]) / math.sqrt(1 + 0.25 * angle ** 2)
    s = math.sin(0.5 * angle) / angle
    return np.array([rotvec[0] * s, rotvec[1] * s, rotvec[2] * s, math.cos(0.5 * angle)])


def skew(r: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors r (..., 3): skew(r) y = r x y."""
    out = np.zeros((*r.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -r[..., 2], r[..., 1]
    out[..., 1, 0], out[..., 1, 2] = r[..., 2], -r[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -r[..., 1], r[..., 0]
    return out


@dataclass(frozen=True)
class Shape:
    """One collision (or visual) shape of a link, in the link's inertial frame: its ``geometry``
    (integration.shapes), position (3,) and quaternion (4,) in the link's inertial frame, rgba: colour
    (visual shapes)."""

    geometry: RigidShape
    position: tuple
    quaternion: tuple
    rgba: tuple = (0.67, 0.67, 0.67, 1.0)

    @property
    def kind(self) -> str:
        """sphere, box, capsule, cylinder, plane or mesh."""
        return self.geometry.kind

    @property
    def size(self) -> tuple:
        """(radius,) (sphere), half extents (box), (radius, length) (capsule, cylinder), normal (plane), scale
        (mesh)."""
        return tuple(float(v) for v in self.geometry.size)

    @property
    def mesh_file(self) -> str:
        """A mesh's file ("" if pybullet made the mesh itself, or not a mesh)."""
        return self.geometry.file

    def bounding_radius(self) -> float:
        """Radius [m] about the shape's own origin that holds the shape (inf for planes and meshes of
        unknown extent)."""
        return self.geometry.bounding_radius()


def _shape_from_pybullet(kind_id: int, dims, mesh_file: bytes | str, pos, orn, rgba=None) -> Shape:
    return Shape(from_pybullet(kind_id, dims, mesh_file), tuple(float(c) for c in pos), tuple(float(c) for c in orn),
                 tuple(float(c) for c in rgba) if rgba is not None else Shape.rgba)


@dataclass
class BodyDynamics:
    """A movable pybullet body's generalized coordinates at the start of a step (world convention, see the
    module doc): ``joints`` the movable joint indices, ``q`` their positions, ``u`` (n,) the generalized
    velocity, ``M`` (n, n) the mass matrix, ``free_base`` whether u starts with the base's 6 components;
    ``frames`` per link: (origin of the URDF link frame (3,), linear Jacobian of that origin (3, n),
    angular Jacobian (3, n)), filled on demand by :meth:`BulletAdapter.point_jacobians`."""

    body: int
    joints: list[int]
    q: np.ndarray
    u: np.ndarray
    M: np.ndarray
    free_base: bool
    frames: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return len(self.u)


class BulletAdapter:
    """One pybullet physics client, opened here (``client=None``) or the user's own (joined, never
    disconnected by :meth:`close`)."""

    def __init__(self, client: int | None = None, gui: bool = False):
        if client is None:
            self.client = p.connect(p.GUI if gui else p.DIRECT)
            self.owned = True
        else:
            if not isinstance(client, (int, np.integer)) or not p.isConnected(int(client)):
                raise InvalidInputError(f"client must be the id of a connected pybullet client "
                                        f"(p.connect(...)), got {client!r}")
            self.client = int(client)
            self.owned = False
        self._joint_info: dict[int, tuple[list[int], list[int]]] = {}  # body -> (movable joints, unsupported joints)
        self._limits: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # body -> its movable joints' (lower, upper)
        self._shapes: dict[tuple[int, int], list[Shape]] = {}
        # (what, body, link) -> state, kept while ``caching`` (a World's step: nothing else moves bodies then)
        self._cache: dict[tuple, tuple] = {}
        self.caching = False

    # ------------------------------------------------------------------ client
    def close(self) -> None:
        """Disconnect a client this adapter opened; leave a joined one connected."""
        if self.owned and self.client is not None and p.isConnected(self.client):
            p.disconnect(self.client)
        self.client = None

    @property
    def connected(self) -> bool:
        return self.client is not None and p.isConnected(self.client)

    def parameters(self) -> tuple[float, np.ndarray]:
        """The client's time step [s] and gravity (3,) [m/s^2]."""
        prm = p.getPhysicsEngineParameters(physicsClientId=self.client)
        return float(prm["fixedTimeStep"]), np.array([prm["gravityAccelerationX"], prm["gravityAccelerationY"],
                                                      prm["gravityAccelerationZ"]])

    def set_parameters(self, dt: float | None = None, gravity: np.ndarray | None = None) -> None:
        if dt is not None:
            p.setTimeStep(dt, physicsClientId=self.client)
        if gravity is not None:
            p.setGravity(*np.asarray(gravity, float).tolist(), physicsClientId=self.client)

    def invalidate(self) -> None:
        """Forget the cached poses, velocities and boxes (call when something else may have moved bodies)."""
        self._cache.clear()

    def step(self) -> None:
        self._cache.clear()
        p.stepSimulation(physicsClientId=self.client)

    def save(self) -> int:
        """Save the client's state in memory (for :meth:`restore`)."""
        return p.saveState(physicsClientId=self.client)

    def restore(self, state: int) -> None:
        self._cache.clear()
        p.restoreState(stateId=state, physicsClientId=self.client)

    def discard(self, state: int) -> None:
        p.removeState(state, physicsClientId=self.client)

    # ------------------------------------------------------------------ bodies and links
    def body_ids(self) -> list[int]:
        """Ids of every body in the client now."""
        c = self.client
        return [p.getBodyUniqueId(i, physicsClientId=c) for i in range(p.getNumBodies(physicsClientId=c))]

    def body_name(self, body: int) -> str:
        base, name = p.getBodyInfo(body, physicsClientId=self.client)
        return (name or base).decode(errors="replace")

    def link_name(self, body: int, link: int) -> str:
        if link == BASE:
            return p.getBodyInfo(body, physicsClientId=self.client)[0].decode(errors="replace")
        return p.getJointInfo(body, link, physicsClientId=self.client)[12].decode(errors="replace")

    def num_links(self, body: int) -> int:
        return p.getNumJoints(body, physicsClientId=self.client)

    def joints(self, body: int) -> tuple[list[int], list[int]]:
        """(movable joints: revolute and prismatic, unsupported joints: spherical and planar) of a body."""
        if body not in self._joint_info:
            movable, other = [], []
            for j in range(self.num_links(body)):
                kind = p.getJointInfo(body, j, physicsClientId=self.client)[2]
                if kind in MOVABLE_JOINTS:
                    movable.append(j)
                elif kind != p.JOINT_FIXED:
                    other.append(j)
            self._joint_info[body] = (movable, other)
        return self._joint_info[body]

    def joint_limits(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        """(lower (j,), upper (j,)) of the body's movable joints (:meth:`joints`), as the URDF gives them: a joint with
        lower >= upper has no limit (pybullet's rule)."""
        if body not in self._limits:
            movable, _ = self.joints(body)
            info = [p.getJointInfo(body, j, physicsClientId=self.client) for j in movable]
            self._limits[body] = (np.array([i[8] for i in info], float), np.array([i[9] for i in info], float))
        return self._limits[body]

    def set_motor(self, motor) -> None:
        """Run a motor (joints.Motor) in pybullet's step, as the user set it."""
        mode, kw = motor.pybullet_args(p)
        p.setJointMotorControl2(motor.body, motor.joint, mode, physicsClientId=self.client, **kw)

    def motor_torques(self, body: int, joints: list[int]) -> np.ndarray:
        """The force or torque each joint's pybullet motor applied in the last step [N or N m]."""
        return np.array([s[3] for s in p.getJointStates(body, joints, physicsClientId=self.client)], float)

    def mass(self, body: int, link: int = BASE) -> float:
        return float(p.getDynamicsInfo(body, link, physicsClientId=self.client)[0])

    def free_base(self, body: int) -> bool:
        """Whether the base moves freely (pybullet reports mass 0 for a fixed or static base)."""
        return self.mass(body, BASE) > 0

    def movable(self, body: int) -> bool:
        """Whether the body has any degree of freedom pybullet integrates (a free base or a movable joint
        that carries mass)."""
        movable, _ = self.joints(body)
        return self.free_base(body) or any(self.mass(body, j) > 0 for j in movable)

    def collision_shapes(self, body: int, link: int) -> list[Shape]:
        """The collision shapes of a link, in its inertial frame (cached: shapes do not change)."""
        key = (body, link)
        if key not in self._shapes:
            data = p.getCollisionShapeData(body, link, physicsClientId=self.client)
            self._shapes[key] = [_shape_from_pybullet(d[2], d[3], d[4], d[5], d[6]) for d in data]
        return self._shapes[key]

    def visual_shapes(self, body: int) -> dict[int, list[Shape]]:
        """The visual shapes of a body per link, in each link's inertial frame."""
        out: dict[int, list[Shape]] = {}
        for d in p.getVisualShapeData(body, physicsClientId=self.client):
            link = d[1]
            # the visual frame is given in the URDF link frame: move it into the inertial frame
            ipos, iorn = self.inertial_frame(body, link)
            pos, orn = p.multiplyTransforms(*p.invertTransform(ipos, iorn), d[5], d[6])
            out.setdefault(link, []).append(_shape_from_pybullet(d[2], d[3], d[4], pos, orn, d[7]))
        return out

    def inertial_frame(self, body: int, link: int) -> tuple[tuple, tuple]:
        """Pose of a link's inertial frame in its URDF link frame."""
        info = p.getDynamicsInfo(body, link, physicsClientId=self.client)
        return info[3], info[4]

    # ------------------------------------------------------------------ state
    def pose(self, body: int, link: int = BASE) -> tuple[np.ndarray, np.ndarray]:
        """Position (3,) of the link's centre of mass and orientation (x, y, z, w) of its inertial frame."""
        c, q, _, _ = self.state(body, link)
        return c, q

    def velocity(self, body: int, link: int = BASE) -> tuple[np.ndarray, np.ndarray]:
        """Linear velocity (3,) of the link's centre of mass and its angular velocity (3,)."""
        _, _, v, w = self.state(body, link)
        return v, w

    def state(self, body: int, link: int = BASE) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pose and velocity in one query: (com (3,), quaternion (4,), v (3,), omega (3,)) (read-only arrays);
        while ``caching``, kept until the client steps or a body is reset through this adapter."""
        key = ("state", body, link)
        hit = self._cache.get(key) if self.caching else None
        if hit is not None:
            return hit
        if link == BASE:
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
            v, w = p.getBaseVelocity(body, physicsClientId=self.client)
        else:
            s = p.getLinkState(body, link, computeLinkVelocity=1, computeForwardKinematics=1,
                               physicsClientId=self.client)
            pos, orn, v, w = s[0], s[1], s[6], s[7]
        out = tuple(np.array(a) for a in (pos, orn, v, w))
        for a in out:
            a.flags.writeable = False
        if self.caching:
            self._cache[key] = out
        return out

    def aabb(self, body: int, link: int = BASE) -> tuple[np.ndarray, np.ndarray]:
        """The link's axis-aligned bounding box (lo (3,), hi (3,)) [m], cached like :meth:`state`."""
        key = ("aabb", body, link)
        hit = self._cache.get(key) if self.caching else None
        if hit is None:
            lo, hi = p.getAABB(body, link, physicsClientId=self.client)
            hit = (np.array(lo), np.array(hi))
            for a in hit:
                a.flags.writeable = False
            if self.caching:
                self._cache[key] = hit
        return hit

    def point_distances(self, body: int, link: int, points: np.ndarray, reach: float) -> np.ndarray:
        """pybullet's signed distances (m,) [m] of world points (m, 3) to a link's collision shapes (their collision
        margin included), inf where none lies within ``reach`` [m]: one query per point, for probes, not for a
        step's contacts."""
        if "_probe" not in self.__dict__:
            self._probe = p.createCollisionShape(p.GEOM_SPHERE, radius=1e-9, physicsClientId=self.client)
        out = np.full(len(points), np.inf)
        for i, x in enumerate(np.asarray(points, float).tolist()):
            res = p.getClosestPoints(-1, body, reach, linkIndexB=link, collisionShapeA=self._probe,
                                     collisionShapePositionA=x, physicsClientId=self.client)
            if res:
                out[i] = min(r[8] for r in res) + 1e-9
        return out

    def reset_pose(self, body: int, position, orientation) -> None:
        self._cache.clear()
        p.resetBasePositionAndOrientation(body, list(position), list(orientation), physicsClientId=self.client)

    def reset_velocity(self, body: int, linear, angular) -> None:
        self._cache.clear()
        p.resetBaseVelocity(body, list(linear), list(angular), physicsClientId=self.client)

    # ------------------------------------------------------------------ bodies the World creates
    def create_body(self, shape: RigidShape, position, orientation, mass: float) -> int:
        """A single-link body of one collision shape (integration.shapes) at a pose; a dynamic one (mass > 0)
        keeps its momentum (pybullet's default damping switched off)."""
        col = p.createCollisionShape(physicsClientId=self.client, **shape.pybullet_args())
        bid = p.createMultiBody(mass, col, basePosition=list(position), baseOrientation=list(orientation),
                                physicsClientId=self.client)
        if mass > 0:
            p.changeDynamics(bid, BASE, linearDamping=0.0, angularDamping=0.0, physicsClientId=self.client)
        self._cache.clear()
        return bid

    def inertia(self, body: int, link: int = BASE) -> tuple[float, np.ndarray]:
        """Mass [kg] and the principal moments (3,) [kg m^2] of a link (in its inertial frame)."""
        info = p.getDynamicsInfo(body, link, physicsClientId=self.client)
        return float(info[0]), np.asarray(info[2], float)

    def user_constraints(self) -> list:
        """The user's pybullet constraints (createConstraint), as constraints.UserConstraint."""
        from .constraints import UserConstraint

        c = self.client
        ids = [p.getConstraintUniqueId(i, physicsClientId=c) for i in range(p.getNumConstraints(physicsClientId=c))]
        return [UserConstraint.of(cid, p.getConstraintInfo(cid, physicsClientId=c)) for cid in ids]

    def constraint_forces(self, cid: int) -> tuple[float, ...]:
        """The forces (and torques) [N, N m] constraint ``cid`` applied on its child in pybullet's last step, world
        axes (getConstraintState)."""
        return tuple(p.getConstraintState(cid, physicsClientId=self.client))

    def angular_jacobian(self, dyn: BodyDynamics, link: int) -> np.ndarray:
        """The angular velocity (3, n) of ``link`` per unit generalized velocity, at the configuration ``dyn`` was taken
        in (call before the client steps)."""
        if link not in dyn.frames:
            dyn.frames[link] = self._frame_jacobian(dyn, link)
        return dyn.frames[link][2]

    def save_world(self) -> bytes:
        """pybullet's whole world (its saveBullet: bodies, poses, velocities, contact points) as bytes."""
        fd, name = tempfile.mkstemp(suffix=".bullet")
        os.close(fd)
        try:
            p.saveBullet(name, physicsClientId=self.client)
            return Path(name).read_bytes()
        finally:
            os.unlink(name)

    def restore_world(self, data: bytes, fresh: bool) -> None:
        """Put the world back to ``data`` of :meth:`save_world` (the same bodies must exist). ``fresh``: the client never
        stepped, so pybullet has no contact pairs yet for the saved contact points to go into: a collision pass makes
        them first (without it, boxes stacked on a plane restored in a new process drifted 0.6 mm from the original
        in 1 s). Raises InvalidInputError when pybullet refuses (its bodies differ from the saved ones)."""
        self._cache.clear()
        fd, name = tempfile.mkstemp(suffix=".bullet")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            if fresh:
                p.performCollisionDetection(physicsClientId=self.client)
            try:
                p.restoreState(fileName=name, physicsClientId=self.client)
            except p.error as exc:
                raise InvalidInputError(f"pybullet could not restore the saved world ({exc}): its bodies differ from "
                                        "this client's") from None
        finally:
            os.unlink(name)

    def snapshot(self, bodies) -> list[tuple]:
        """The state (base pose and velocity, joint positions and velocities) of ``bodies``, for
        :meth:`restore_snapshot` (cheaper than pybullet's saveState, which serialises the whole world)."""
        c, out = self.client, []
        for b in bodies:
            joints, _ = self.joints(b)
            pos, orn = p.getBasePositionAndOrientation(b, physicsClientId=c)
            vel = p.getBaseVelocity(b, physicsClientId=c)
            js = p.getJointStates(b, joints, physicsClientId=c) if joints else []
            out.append((b, pos, orn, vel, joints, [(s[0], s[1]) for s in js]))
        return out

    def restore_snapshot(self, snapshot: list[tuple]) -> None:
        c = self.client
        self._cache.clear()
        for b, pos, orn, vel, joints, js in snapshot:
            p.resetBasePositionAndOrientation(b, pos, orn, physicsClientId=c)
            p.resetBaseVelocity(b, vel[0], vel[1], physicsClientId=c)
            for j, (q, qd) in zip(joints, js):
                p.resetJointState(b, j, q, qd, physicsClientId=c)

    def apply_force(self, body: int, link: int, force: np.ndarray, point: np.ndarray) -> None:
        """A force (3,) [N] at a world point (3,) over the next step."""
        p.applyExternalForce(body, link, force.tolist(), point.tolist(), p.WORLD_FRAME, physicsClientId=self.client)

    def apply_torque(self, body: int, link: int, torque: np.ndarray) -> None:
        p.applyExternalTorque(body, link, torque.tolist(), p.WORLD_FRAME, physicsClientId=self.client)

    # ------------------------------------------------------------------ generalized coordinates
    def dynamics(self, body: int) -> BodyDynamics:
        """Generalized velocity and mass matrix of a movable body, now (see the module doc)."""
        c = self.client
        joints, _ = self.joints(body)
        free = self.free_base(body)
        if joints:
            states = p.getJointStates(body, joints, physicsClientId=c)
            q = np.array([s[0] for s in states])
            qd = np.array([s[1] for s in states])
        else:
            q = qd = np.zeros(0)
        if joints:
            M = np.array(p.calculateMassMatrix(body, q.tolist(), physicsClientId=c))
        else:  # a single rigid body: pybullet's mass matrix call needs joints; the inertia is all there is
            M = np.zeros((6, 6))
            info = p.getDynamicsInfo(body, BASE, physicsClientId=c)
            _, orn = p.getBasePositionAndOrientation(body, physicsClientId=c)
            R = quat_matrix(orn)  # orientation of the inertial frame, whose axes are the principal axes
            M[:3, :3] = (R * np.asarray(info[2])) @ R.T
            M[3:, 3:] = info[0] * np.eye(3)
            v, w = p.getBaseVelocity(body, physicsClientId=c)
            return BodyDynamics(body, [], q, np.r_[w, v], M, True)
        if free:
            v, w = p.getBaseVelocity(body, physicsClientId=c)
            _, orn = p.getBasePositionAndOrientation(body, physicsClientId=c)
            R = quat_matrix(orn)
            T = np.eye(len(M))  # u_local = T u_world: the base's (omega, v) in the base frame
            T[:3, :3] = T[3:6, 3:6] = R.T
            M = T.T @ M @ T
            u = np.r_[w, v, qd]
        else:
            u = qd
        return BodyDynamics(body, joints, q, u, 0.5 * (M + M.T), free)

    def generalized_velocity(self, dyn: BodyDynamics) -> np.ndarray:
        """The body's generalized velocity now, in the layout of ``dyn``."""
        c = self.client
        qd = (np.array([s[1] for s in p.getJointStates(dyn.body, dyn.joints, physicsClientId=c)])
              if dyn.joints else np.zeros(0))
        if dyn.free_base:
            v, w = p.getBaseVelocity(dyn.body, physicsClientId=c)
            return np.r_[w, v, qd]
        return qd

    def point_jacobians(self, dyn: BodyDynamics, link: int, points: np.ndarray) -> np.ndarray:
        """Jacobians (m, 3, n) of material points of ``link`` at world positions (m, 3), at the
        configuration ``dyn`` was taken in (call before the client steps)."""
        points = np.asarray(points, float).reshape(-1, 3)
        if link not in dyn.frames:
            dyn.frames[link] = self._frame_jacobian(dyn, link)
        origin, Jv, Jw = dyn.frames[link]
        # J_p = J_origin - skew(p - origin) J_w  (v_p = v_o + w x (p - o))
        return Jv[None] - skew(points - origin) @ Jw[None]

    def _frame_jacobian(self, dyn: BodyDynamics, link: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c, n = self.client, dyn.n
        if link == BASE:
            com, _ = p.getBasePositionAndOrientation(dyn.body, physicsClientId=c)
            Jv, Jw = np.zeros((3, n)), np.zeros((3, n))
            if dyn.free_base:
                Jw[:, :3] = np.eye(3)
                Jv[:, 3:6] = np.eye(3)
            return np.array(com), Jv, Jw
        zeros = [0.0] * len(dyn.joints)
        # the Jacobian of the URDF link frame's origin (pybullet takes localPosition in that frame)
        Jl, Ja = p.calculateJacobian(dyn.body, link, [0.0, 0.0, 0.0], dyn.q.tolist(), zeros, zeros,
                                     physicsClientId=c)
        Jv, Jw = np.array(Jl), np.array(Ja)
        origin = np.array(p.getLinkState(dyn.body, link, computeForwardKinematics=1, physicsClientId=c)[4])
        if dyn.free_base:  # pybullet: base (omega, v) and the result in the base frame -> world
            _, orn = p.getBasePositionAndOrientation(dyn.body, physicsClientId=c)
            R = quat_matrix(orn)
            Jv, Jw = R @ Jv, R @ Jw
            Jv[:, :6] = Jv[:, :6] @ np.kron(np.eye(2), R.T)
            Jw[:, :6] = Jw[:, :6] @ np.kron(np.eye(2), R.T)
        return origin, Jv, Jw

    def change_velocity(self, dyn: BodyDynamics, du: np.ndarray, h: float) -> None:
        """Add du (n,) to the body's generalized velocity and h du to its configuration: the step pybullet
        just took (symplectic Euler, x' = x + h u') then equals the step with the corrected velocity."""
        c = self.client
        self._cache.clear()
        u = self.generalized_velocity(dyn) + du
        k = 0
        if dyn.free_base:
            pos, orn = p.getBasePositionAndOrientation(dyn.body, physicsClientId=c)
            dw, dv = du[:3], du[3:6]
            new_orn = quat_multiply(rotation_quat(h * dw), orn)
            p.resetBasePositionAndOrientation(dyn.body, (np.array(pos) + h * dv).tolist(),
                                              (new_orn / np.linalg.norm(new_orn)).tolist(), physicsClientId=c)
            p.resetBaseVelocity(dyn.body, u[3:6].tolist(), u[:3].tolist(), physicsClientId=c)
            k = 6
        if dyn.joints:
            q = np.array([s[0] for s in p.getJointStates(dyn.body, dyn.joints, physicsClientId=c)])
            q = q + h * du[k:]
            for j, qj, uj in zip(dyn.joints, q.tolist(), u[k:].tolist()):
                p.resetJointState(dyn.body, j, qj, uj, physicsClientId=c)
