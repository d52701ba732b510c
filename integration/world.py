"""World: a pybullet connection for the rigid side, a softbody.Simulation for the soft side,
and the coupling between them (contacts, attachments, reaction forces).

One step of length h, in order:
  1. kinematic rigid bodies get their scripted velocity over [t, t + h];
  2. soft surface nodes near rigid bodies are queried against them (collision.py);
  3. each soft body takes one implicit step with its supports, attachments and contacts (contact.py);
  4. the contact reactions act on dynamic rigid bodies, equal and opposite, and pybullet steps;
  5. kinematic bodies are moved to their scripted pose at t + h.
A scene without rigid bodies costs no pybullet work; a soft body far from every rigid AABB costs
no collision query.
"""
from __future__ import annotations

import math
import time
from collections import defaultdict
from typing import Callable

import numpy as np
import pybullet as p

from softbody import FemBody, Simulation
from softbody.simulation import run_steps
from softbody.errors import InvalidInputError, finite_number
from softbody.integrator import Constraints, LinearSystem

from .collision import CollisionDetector, Contacts
from .contact import ContactResult, ContactSolver, NodeContacts
from .rigid import PoseScript, RigidBody, load_trimesh


def _quat(orientation) -> list[float]:
    q = np.asarray(orientation if orientation is not None else (0, 0, 0, 1), dtype=float)
    if q.shape == (3,):  # Euler angles
        return list(p.getQuaternionFromEuler(q.tolist()))
    if q.shape != (4,) or not np.isfinite(q).all() or np.linalg.norm(q) == 0:
        raise InvalidInputError(f"orientation must be a quaternion (x, y, z, w) or Euler angles (3,), got {orientation!r}")
    return (q / np.linalg.norm(q)).tolist()


def _vec3(v, name: str) -> list[float]:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise InvalidInputError(f"{name} must be three finite numbers, got {v!r}")
    return a.tolist()


def _positive(v, name: str) -> float:
    return finite_number(v, name, 0.0)


class World:
    """Soft bodies (softbody.FemBody) in a pybullet rigid-body scene.

    dt: step [s]; gravity [m/s^2]; gui: open pybullet's GUI instead of DIRECT; solver: linear solver
    backend of the soft bodies; contact_margin [m]: nodes closer than this to a rigid body become
    contact candidates (grown automatically with the surface speed).
    """

    def __init__(self, dt: float = 0.01, gravity=(0.0, 0.0, -9.81), gui: bool = False,
                 solver: str = "auto", contact_margin: float = 0.005):
        self.sim = Simulation([], dt, gravity, solver=solver)
        self.dt = self.sim.dt
        self.gravity = self.sim.gravity
        self.client = p.connect(p.GUI if gui else p.DIRECT)
        p.setGravity(*self.gravity.tolist(), physicsClientId=self.client)
        p.setTimeStep(self.dt, physicsClientId=self.client)
        self.contact_margin = _positive(contact_margin, "contact_margin")
        self.rigids: dict[int, RigidBody] = {}
        self.friction: dict[int, float] = {}  # id(body) -> mu
        self.attachments: list[tuple[FemBody, np.ndarray, RigidBody]] = []
        self.detector = CollisionDetector(self.client)
        self.contact_solver = ContactSolver()
        self.contacts: Contacts = Contacts.empty()  # candidates of the last step
        self.contact_results: dict[int, tuple[NodeContacts, ContactResult]] = {}
        # seconds spent in the last step, by disjoint phase: collision (queries), the core's rotations,
        # forces, assembly, factorize, solve (linear algebra), contact (the contact loop's own work),
        # other (rest of the FEM step), rigid (pybullet); "total" is their sum
        self.timings: dict[str, float] = defaultdict(float)
        self._surface: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._kin_velocity: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.sim.velocity_solver = self._solve_velocities

    # ------------------------------------------------------------------ properties
    @property
    def t(self) -> float:
        return self.sim.t

    @property
    def bodies(self) -> list[FemBody]:
        return self.sim.bodies

    def close(self) -> None:
        if self.client is not None and p.isConnected(self.client):
            p.disconnect(self.client)
        self.client = None

    def __enter__(self) -> "World":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ rigid bodies
    def _add(self, shape: str, col: int, params: dict, position, orientation, mass: float,
             motion: PoseScript | None, name: str, friction: float | None, concave: bool = False,
             tm=None) -> RigidBody:
        mass = float(mass)
        if not math.isfinite(mass) or mass < 0:
            raise InvalidInputError(f"mass must be >= 0 (0: fixed or kinematic), got {mass!r}")
        if motion is not None and mass > 0:
            raise InvalidInputError("a kinematic body (with a motion script) must have mass 0")
        if motion is not None and not callable(motion):
            raise InvalidInputError("motion must be a function of time returning a pose")
        if friction is not None and not (isinstance(friction, (int, float, np.number))
                                         and math.isfinite(friction) and friction >= 0):
            raise InvalidInputError(f"friction must be >= 0, got {friction!r}")
        bid = p.createMultiBody(mass, col, basePosition=_vec3(position, "position"),
                                baseOrientation=_quat(orientation), physicsClientId=self.client)
        if mass > 0:  # pybullet damps velocities by default (0.04); physical bodies keep their momentum
            p.changeDynamics(bid, -1, linearDamping=0.0, angularDamping=0.0, physicsClientId=self.client)
        body = RigidBody(bid, self.client, shape, params, mass, motion, name or f"{shape}{bid}",
                         friction, concave, tm)
        if motion is not None:
            pos, orn = body.scripted_pose(self.t)
            p.resetBasePositionAndOrientation(bid, pos.tolist(), orn.tolist(), physicsClientId=self.client)
        self.rigids[bid] = body
        return body

    def add_sphere(self, radius: float, position=(0, 0, 0), mass: float = 0.0, motion: PoseScript | None = None,
                   name: str = "", friction: float | None = None) -> RigidBody:
        """A sphere of ``radius`` [m]: fixed (mass 0), dynamic (mass > 0 [kg]) or kinematic (motion script)."""
        r = _positive(radius, "radius")
        col = p.createCollisionShape(p.GEOM_SPHERE, radius=r, physicsClientId=self.client)
        return self._add("sphere", col, {"radius": r}, position, None, mass, motion, name, friction)

    def add_box(self, half_extents, position=(0, 0, 0), orientation=None, mass: float = 0.0,
                motion: PoseScript | None = None, name: str = "", friction: float | None = None) -> RigidBody:
        """A box with ``half_extents`` (3,) [m]."""
        he = np.asarray(half_extents, dtype=float)
        if he.shape != (3,) or not np.isfinite(he).all() or (he <= 0).any():
            raise InvalidInputError(f"half_extents must be three positive lengths, got {half_extents!r}")
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=he.tolist(), physicsClientId=self.client)
        return self._add("box", col, {"half_extents": he}, position, orientation, mass, motion, name, friction)

    def add_plane(self, normal=(0, 0, 1), point=(0, 0, 0), name: str = "", friction: float | None = None,
                  motion: PoseScript | None = None) -> RigidBody:
        """An infinite fixed plane through ``point`` with outward ``normal``."""
        nrm = np.asarray(_vec3(normal, "normal"))
        if np.linalg.norm(nrm) == 0:
            raise InvalidInputError("plane normal must be non-zero")
        nrm = nrm / np.linalg.norm(nrm)
        col = p.createCollisionShape(p.GEOM_PLANE, planeNormal=nrm.tolist(), physicsClientId=self.client)
        return self._add("plane", col, {"normal": nrm}, point, None, 0.0, motion, name, friction)

    def add_mesh(self, mesh, position=(0, 0, 0), orientation=None, mass: float = 0.0, scale: float = 1.0,
                 motion: PoseScript | None = None, name: str = "", friction: float | None = None,
                 convex: bool | None = None) -> RigidBody:
        """A triangle mesh (a trimesh.Trimesh or a file trimesh reads), in the body frame.

        convex: None decides from the mesh (trimesh's is_convex). A concave mesh is exact but must be
        static (mass 0, or kinematic); a dynamic body uses the convex hull.
        """
        tm = load_trimesh(mesh).copy()
        tm.apply_scale(_positive(scale, "scale"))
        if convex is None:
            convex = bool(tm.is_convex)
        if not convex and mass > 0:
            raise InvalidInputError("a concave mesh cannot be dynamic in pybullet; pass convex=True "
                                    "(convex hull) or mass=0")
        if convex:
            hull = tm.convex_hull
            col = p.createCollisionShape(p.GEOM_MESH, vertices=hull.vertices.tolist(), physicsClientId=self.client)
            tm = hull
        else:
            col = p.createCollisionShape(p.GEOM_MESH, vertices=tm.vertices.tolist(),
                                         indices=tm.faces.ravel().astype(int).tolist(), physicsClientId=self.client)
        return self._add("mesh", col, {"vertices": np.asarray(tm.vertices), "faces": np.asarray(tm.faces)},
                         position, orientation, mass, motion, name, friction, concave=not convex, tm=tm)

    def rigid(self, body_id: int) -> RigidBody:
        if body_id not in self.rigids:
            raise InvalidInputError(f"unknown rigid body id {body_id!r}; known ids: {sorted(self.rigids)}")
        return self.rigids[body_id]

    # ------------------------------------------------------------------ soft bodies
    def add_soft(self, body: FemBody, friction: float = 0.0) -> FemBody:
        """Add a soft body; ``friction`` is its Coulomb coefficient against rigid bodies (>= 0)."""
        if not isinstance(body, FemBody):
            raise InvalidInputError(f"add_soft needs a softbody.FemBody, got {type(body).__name__}")
        friction = finite_number(friction, "friction", 0.0, strict=False)
        if any(b is body for b in self.sim.bodies):
            raise InvalidInputError("this soft body is already in the world")
        self.sim.bodies.append(body)
        self.friction[id(body)] = friction
        tris = body.mesh.surface_triangles()
        self._surface[id(body)] = (np.unique(tris), tris)
        return body

    def attach(self, body: FemBody, node_ids, rigid: RigidBody | int) -> None:
        """Make nodes of a soft body follow a rigid body's pose exactly (rigidly attached)."""
        if not any(b is body for b in self.sim.bodies):
            raise InvalidInputError("attach: add the soft body to the world first (add_soft)")
        rb = self.rigid(rigid.id if isinstance(rigid, RigidBody) else rigid)
        ids = body._node_ids(node_ids, "attach")
        local = rb.to_local(body.positions[ids])

        def motion(t: float) -> np.ndarray:
            if rb.motion is not None:
                pos, orn = rb.scripted_pose(t)
                R = np.array(p.getMatrixFromQuaternion(orn.tolist())).reshape(3, 3)
                return local @ R.T + pos
            if rb.mass > 0:  # dynamic: extrapolate the current motion over the step
                c, _ = rb.pose()
                v, w = rb.velocity()
                dt = t - self.t
                return rb.to_world(local) + v * dt + np.cross(w, rb.to_world(local) - c) * dt
            return rb.to_world(local)

        body.prescribe(ids, motion)
        self.attachments.append((body, ids, rb))

    # ------------------------------------------------------------------ stepping
    def _rigid_point_velocity(self, rb: RigidBody, points: np.ndarray) -> np.ndarray:
        if rb.id in self._kin_velocity:
            v, w = self._kin_velocity[rb.id]
            c, _ = rb.pose()
            return v + np.cross(w, points - c)
        return rb.point_velocity(points)

    def _detect(self, i: int, body: FemBody) -> NodeContacts | None:
        surface, tris = self._surface[id(body)]
        surface = surface[~body.supported()[surface]]  # supports win over contact: no query for them
        if not len(surface):
            return None
        x = body.positions
        xs = x[surface]
        speed = float(np.sqrt((body.velocities[surface] ** 2).sum(axis=1).max(initial=0.0)))
        margin = self.contact_margin + 2.0 * speed * self.dt
        lo, hi = xs.min(axis=0) - margin, xs.max(axis=0) + margin
        parts, vparts = [], []
        for rb in self.rigids.values():
            rlo, rhi = rb.aabb()
            if np.any(rlo > hi) or np.any(rhi < lo):
                continue  # broad phase: far apart, no query at all
            parts.append(self.detector.node_contacts(i, x, surface, rb, margin))
            if rb.shape in ("box", "mesh"):
                q, ti, bary, d = self.detector.vertex_contacts(i, x, tris, rb, margin)
                if len(q):
                    # a sharp rigid vertex inside a soft triangle pushes the triangle's nodes along -n_tri
                    xt = x[tris[ti]]
                    n_tri = np.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])
                    n_tri /= np.linalg.norm(n_tri, axis=1, keepdims=True)
                    nodes = tris[ti].ravel()
                    vparts.append(Contacts(np.full(len(nodes), i), nodes, np.full(len(nodes), rb.id),
                                           np.repeat(q, 3, axis=0), np.repeat(-n_tri, 3, axis=0),
                                           np.repeat(d, 3)))
        found = Contacts.concat(parts + vparts)
        self._found.append(found)
        if not len(found):
            return None
        # one contact per node: the deepest
        order = np.lexsort((found.distance, found.node))
        found = found.select(order)
        first = np.r_[True, found.node[1:] != found.node[:-1]]
        found = found.select(first)
        mu_body = self.friction[id(body)]
        vr = np.zeros((len(found), 3))
        mu = np.full(len(found), mu_body)
        for rid in np.unique(found.rigid):
            sel = found.rigid == rid
            rb = self.rigids[int(rid)]
            vr[sel] = self._rigid_point_velocity(rb, found.point[sel])
            if rb.friction is not None:  # a rigid body's own coefficient overrides the soft body's
                mu[sel] = rb.friction
        return NodeContacts(found.node, found.normal, found.distance, vr, mu, found.rigid, found.point)

    def _solve_velocities(self, body: FemBody, system: LinearSystem, supports: Constraints, t_next: float):
        c = self._pending.get(id(body))
        core0 = sum(self.sim.timings.values())  # core phases (factorize, solve, ...) run inside this call
        t0 = time.perf_counter()
        if c is None:
            v, _ = system.solve(supports)
        else:
            v, res = self.contact_solver.solve(system, supports, c, self.dt)
            self.contact_results[id(body)] = (c, res)
        self.timings["velocity_solve"] += time.perf_counter() - t0 - (sum(self.sim.timings.values()) - core0)
        return v

    def step(self) -> None:
        """Advance the whole scene by dt."""
        h, t = self.dt, self.t
        self.timings = defaultdict(float)
        tic = time.perf_counter()
        for rb in self.rigids.values():
            if rb.motion is not None:
                p0, q0 = rb.scripted_pose(t)
                p1, q1 = rb.scripted_pose(t + h)
                dq = np.array(p.getDifferenceQuaternion(q0.tolist(), q1.tolist()))
                angle = 2 * math.atan2(np.linalg.norm(dq[:3]), dq[3])
                axis = dq[:3] / max(np.linalg.norm(dq[:3]), 1e-300)
                self._kin_velocity[rb.id] = ((p1 - p0) / h, axis * angle / h)
        self._pending: dict[int, NodeContacts] = {}
        self._found: list[Contacts] = []
        self.contact_results = {}
        self.detector.last_candidates = 0
        if self.rigids:
            for i, body in enumerate(self.bodies):
                c = self._detect(i, body)
                if c is not None:
                    self._pending[id(body)] = c
        self.contacts = Contacts.concat(self._found)
        self.timings["collision"] = time.perf_counter() - tic
        tic = time.perf_counter()
        self.sim.step()
        fem = time.perf_counter() - tic
        core = dict(self.sim.timings)
        contact = self.timings.pop("velocity_solve", 0.0)  # outside the core phases
        self.timings.update(core)
        self.timings["contact"] = max(contact, 0.0) if self._pending else 0.0
        self.timings["other"] = max(fem - sum(core.values()) - self.timings["contact"], 0.0)
        tic = time.perf_counter()
        if self.rigids:
            self._apply_reactions()
            p.stepSimulation(physicsClientId=self.client)
            for rb in self.rigids.values():
                if rb.motion is not None:
                    pos, orn = rb.scripted_pose(self.t)
                    p.resetBasePositionAndOrientation(rb.id, pos.tolist(), orn.tolist(), physicsClientId=self.client)
        self.timings["rigid"] = time.perf_counter() - tic
        self.timings["total"] = sum(self.timings.values())

    def _apply_reactions(self) -> None:
        """Equal and opposite contact forces on dynamic rigid bodies (force at the centre + torque)."""
        for c, res in self.contact_results.values():
            for rid in np.unique(c.rigid[res.active]):
                rb = self.rigids[int(rid)]
                if rb.mass <= 0:
                    continue
                sel = res.active & (c.rigid == rid)
                f = -res.force[sel]
                com, _ = rb.pose()
                torque = np.cross(c.point[sel] - com, f).sum(axis=0)
                p.applyExternalForce(rb.id, -1, f.sum(axis=0).tolist(), com.tolist(), p.WORLD_FRAME,
                                     physicsClientId=self.client)
                p.applyExternalTorque(rb.id, -1, torque.tolist(), p.WORLD_FRAME, physicsClientId=self.client)

    def run(self, duration: float, callback: Callable[["World"], object] | None = None,
            progress: bool = False) -> None:
        """Step for ``duration`` [s], calling ``callback(world)`` after each step; progress bar on request."""
        run_steps(self.step, self.dt, duration, None if callback is None else lambda: callback(self), progress)

    # ------------------------------------------------------------------ diagnostics
    def max_penetration(self) -> float:
        """Deepest penetration [m] of any soft surface node into any rigid body at the current positions."""
        worst = 0.0
        for i, body in enumerate(self.bodies):
            surface, _ = self._surface[id(body)]
            surface = surface[~body.supported()[surface]]
            for rb in self.rigids.values():
                c = self.detector.node_contacts(i, body.positions, surface, rb, 1e-3)
                if len(c):
                    worst = max(worst, float(-c.distance.min()))
        return worst
