"""World: soft bodies (a softbody.Simulation) in a pybullet rigid-body scene, the coupling between them.

A World opens a pybullet client of its own, or joins the user's (``World(client=cid)``): then every
body in that client, loaded before or after, is a rigid obstacle, link by link, and the user's own
calls between steps (motor commands, constraints, forces) keep working.

One step of length h reads top to bottom in ``World._step`` (its data in one integration.step.StepRecord):
  1. sync: new or removed pybullet bodies are picked up; kinematic bodies get their scripted velocity;
  2. collide: soft surface nodes and faces near rigid links are queried against them (collision.py), soft
     bodies against each other (softcontact.py), at the start pose;
  3. build the contact problem: movable rigid bodies in contact with (or attached to) a soft body give their
     mass matrix and the Jacobians of the contact points (bullet.py), at the start configuration;
  4. pybullet steps once (``stepSimulation``): the rigid bodies' free motion over the step, with the
     user's motors, forces and rigid contacts;
  5. the Simulation prepares every soft body's implicit step and hands the systems to the contact solve, which
     solves them with their supports, attachments and contacts, together with the rigid bodies' velocity change
     du (contact.py, convex.py), and again with contacts the end of the step reveals;
  6. commit: du goes back to pybullet (velocity and position of the step just taken), the soft states are
     committed, kinematic bodies are moved to their scripted pose at t + h; checks; the step publishes its
     report (``World.report``: contacts, results, forces, timings).
A divergence (non-finite state, or energy above ``max_energy``) raises SimulationDiverged before 6
and leaves soft and rigid bodies as they were before the step.

Each soft body added has a SoftEntry (integration.entries: its friction, what it ignores, self-contact, surface,
place in a stack, contact group), each stepped body a SteppedEntry; both are reached by handle (an index).
"""
from __future__ import annotations

import copy
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from softbody import FemBody, Simulation
from softbody.errors import InvalidInputError, SimulationDiverged, finite_number
from softbody.integrator import Constraints, LinearSystem, timed
from softbody.simulation import run_steps
from softbody.stack import BodyStack, stack_key
from softbody.state import not_copyable, read_state

from .bullet import BASE, BodyDynamics, BulletAdapter, quat_difference, quat_from_euler, quat_matrix
from .collision import CollisionDetector, Contacts, FaceHits, Sweep, primitive_distances, run_starts
from .coupling import RigidCoupling, RigidWarmStart
from .contact import (Attachments, BodyStep, ContactResult, ContactSolver, FaceContacts, NodeContacts,
                      PairContacts)
from .distance import cross
from .rigid import PoseScript, RigidLink, load_trimesh
from .shapes import Box, Mesh, Plane, RigidShape, Sphere
from .intersection import intersection_depth
from .constraints import applied_impulses as constraint_impulses, constraint_rows
from .convex import JointRows
from .joints import Motor, Motors, applied_impulses, at_free_motion, joint_rows
from .softcontact import EdgeHits, EdgePass, FirstPass, SoftHits, SoftLayout, SoftSurface, edge_contacts, soft_contacts
from .entries import SoftEntry, SteppedEntry
from .state import WorldState
from .step import StepRecord, StepReport


# a node touches a rigid link (for the face contacts of its triangles) when it is within this fraction of
# the contact margin of it: resting on it, not merely near it (collision.CollisionDetector.detect)
TOUCH = 0.1
# soft contacts reach this many contact margins into the other body (an overlap caught late is undone)
SOFT_DEPTH = 5.0
# soft edge-edge contacts, this many: an edge's crossing is caught within the margin and the step's closing, and
# a deeper one lies beside node contacts that undo it; reaching 5 margins deep, a stack of 12 cubes' search paired
# 235,000 edges for none
EDGE_DEPTH = 1.0
# a fast rigid body found this deep [m] in a soft body after a step was missed within it (World._check_missed)
MISSED = 1e-3
# two soft surfaces found crossing deeper than this [m] after a step are said to intersect (a resting contact
# leaves up to contact.SOFT_SLOP)
INTERSECTING = 5e-4
# ... tested every step where the contact search saw that deep a crossing, and every this many steps for all pairs
CHECK_EVERY = 10
# a node the solved step carries this deep [m] into a moving rigid link's end pose gets a contact there, and
# the step is solved again, up to END_ROUNDS times (World._end_contacts)
END_TOL = 1e-4
END_ROUNDS = 2
# the soft bodies' schemes the coupled step takes (softbody.schemes): the backward Euler ones
WORLD_SCHEMES = ("warped", "newton")


def _concat_contacts(a: NodeContacts, b: NodeContacts) -> NodeContacts:
    """The node contacts of a, then b (same fields, Jacobians both or neither)."""
    return NodeContacts(*(None if getattr(a, f) is None else np.concatenate([getattr(a, f), getattr(b, f)])
                          for f in NodeContacts.__dataclass_fields__))


def _quat(orientation) -> list[float]:
    q = np.asarray(orientation if orientation is not None else (0, 0, 0, 1), dtype=float)
    if q.shape == (3,):  # Euler angles
        return quat_from_euler(q).tolist()
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


def _friction(value, name: str = "friction") -> float:
    if not (isinstance(value, (int, float, np.number)) and not isinstance(value, bool)
            and math.isfinite(value) and value >= 0):
        raise InvalidInputError(f"{name} must be a finite number >= 0, got {value!r}")
    return float(value)


@dataclass
class Attachment:
    """Nodes of a soft body held to a rigid link: ``local`` (m, 3) their positions in the link's frame;
    coupled: the link is movable and the attachment is solved two-way (else the nodes are prescribed); handle: its
    index in ``World.attachments``."""

    body: FemBody
    nodes: np.ndarray
    rigid: RigidLink
    local: np.ndarray
    coupled: bool
    handle: int = -1


class World:
    """Soft bodies (softbody.FemBody) in a pybullet rigid-body scene.

    dt: step [s]; gravity [m/s^2]: both default to the joined client's (see ``client``), else 0.01 s and
    (0, 0, -9.81); given explicitly they are also set on the client. gui: open pybullet's GUI instead of
    DIRECT (own client only); solver: linear solver backend of the soft bodies; contact_margin [m]:
    nodes closer than this to a rigid link become contact candidates (grown with the speeds);
    client: the id of the user's pybullet client to join (its bodies become rigid obstacles, link by
    link; :meth:`close` leaves it connected); max_energy [J]: bound on the scene's total energy
    (kinetic and elastic energy of the soft bodies, kinetic energy of the movable rigid bodies, and the
    gravitational potential of both, zero at the world origin), above which a step raises
    SimulationDiverged with the state kept at the last good step; method: the soft bodies' linear
    solve ("auto", "direct", "iterative"); soft_contact: contact between the soft bodies (on by default:
    it costs nothing while they are apart; self-contact is per body, see :meth:`add_soft`); push_speed
    [m/s]: the fastest a penetration is undone (a soft body placed partly inside a rigid or another soft
    body is pushed out over several steps, with a warning; placed deeper than half its size inside, it is
    refused at its first step); scheme, newton_tol, newton_max_iter: the soft bodies' step, "warped" (the
    paper's) or "newton" (the nonlinear backward Euler step, contacts and coupling solved in every
    iteration; see softbody.Simulation and softbody.newton); stack: step soft bodies that agree in element
    kind, material, damping, friction and what they ignore as one block-diagonal system (softbody.stack:
    one assembly, factorisation and collision pass for all of them, so that ten small bodies cost about
    what one of their total size does; the same answer as stepping each alone, to the solver's tolerance);
    movable_edges: rows where a box's edge or a capsule's side that the coupled solve moves lies across soft faces
    between their nodes (collision.edge_contacts; on by default: without them such an edge digs in, 0.4 mm for a
    2 kg box on a soft block, 2.3 mm for a 1 kg capsule across a slab, in 1/3 to 1/6 of the time per step,
    benchmarks/movable_edges.py). ``bodies`` are the soft bodies as added; ``sim.bodies`` the ones stepped (stacks
    and single bodies).
    """

    def __init__(self, dt: float | None = None, gravity=None, gui: bool = False, solver: str = "auto",
                 contact_margin: float = 0.005, client: int | None = None, max_energy: float | None = None,
                 method: str = "auto", soft_contact: bool = True, push_speed: float = 0.5, scheme: str = "warped",
                 newton_tol: float = 1e-5, newton_max_iter: int = 25, stack: bool = True,
                 movable_edges: bool = True):
        if client is not None and gui:
            raise InvalidInputError("gui=True opens a client of the World's own; it cannot be combined with client=")
        if scheme not in WORLD_SCHEMES:
            raise InvalidInputError(
                f"World steps soft bodies with scheme 'warped' or 'newton', got {scheme!r}"
                + (": the coupled contact solve is a backward Euler solve over dt (one impulse over the step, rigid "
                   "bodies stepped by pybullet over dt), which BDF2's step of 2 dt / 3 from two past states does not "
                   "match; softbody.Simulation(..., scheme='bdf2') steps bodies without contact"
                   if scheme == "bdf2" else ""))
        self.adapter = BulletAdapter(client, gui)
        try:
            if client is not None:
                dt0, g0 = self.adapter.parameters()
                dt = dt0 if dt is None else dt
                gravity = g0 if gravity is None else gravity
            self.sim = Simulation([], 0.01 if dt is None else dt, (0.0, 0.0, -9.81) if gravity is None else gravity,
                                  solver=solver, max_energy=max_energy, method=method, scheme=scheme,
                                  newton_tol=newton_tol, newton_max_iter=newton_max_iter)
            self.dt = self.sim.dt
            self.gravity = self.sim.gravity
            self.adapter.set_parameters(self.dt, self.gravity)
            self.contact_margin = _positive(contact_margin, "contact_margin")
        except Exception:
            self.adapter.close()
            raise
        self.max_energy = self.sim.max_energy
        self.sim.max_energy = None  # the World checks the whole scene's energy, rigid bodies included
        self.rigids: dict[tuple[int, int], RigidLink] = {}
        self.attachments: list[Attachment] = []
        self.detector = CollisionDetector(self.client)
        self.contact_solver = ContactSolver(push_speed=_positive(push_speed, "push_speed"))
        self._rigid_warm = RigidWarmStart()  # the coupled solve's last du, where the next one starts
        self._entries: list[SoftEntry] = []  # the soft bodies as added (World.bodies), by handle
        self._stepped: list[SteppedEntry] = []  # the stepped bodies (sim.bodies), by index
        self._stack = bool(stack)
        self._restack_due = False  # members added or their grouping changed since the last step
        self._pairs_memo = None  # (key, pairs, skipped pairs) of _soft_pairs
        self._soft_layout = None  # (that key, softcontact.SoftLayout of the pairs) for the soft search
        self._first_pass = FirstPass()  # the soft search's first-pass candidates, kept while they serve
        self._edge_pass = EdgePass()  # the edge search's candidate pairs, kept while they serve
        self._pairs_version = 0  # counts the changes of what the bodies ignore
        self.report = StepReport()  # what the last step found and solved (integration.step)
        self.soft_contact = bool(soft_contact)
        self.movable_edges = bool(movable_edges)
        self._kin_velocity: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._known: set[int] = set()
        self._one_way: set[int] = set()  # bodies pybullet moves but the coupled solve cannot (unsupported joints)
        self._warned: set = set()
        self._lagged: list[tuple[int, int, np.ndarray, np.ndarray]] = []  # (body, link, force, point) for the next step
        self.motors = Motors()  # the joint motors registered with set_motor: rows of the coupled problem
        self._sync()

    # ------------------------------------------------------------------ properties
    @property
    def client(self) -> int | None:
        return self.adapter.client

    @property
    def t(self) -> float:
        return self.sim.t

    # the last step's findings and results, as it published them (self.report)
    @property
    def contacts(self) -> Contacts:
        """The rigid contact candidates of the last step (node against rigid link)."""
        return self.report.candidates

    @property
    def face_hits(self) -> FaceHits:
        """The face contact candidates of the last step (rigid point against soft triangle)."""
        return self.report.face_hits

    @property
    def soft_hits(self) -> SoftHits:
        """The soft contact candidates of the last step: node against face (a, b index ``sim.bodies``)."""
        return self.report.soft_hits

    @property
    def edge_hits(self) -> EdgeHits:
        """... and soft edge against edge."""
        return self.report.edge_hits

    @property
    def contact_results(self) -> dict[int, tuple[NodeContacts, ContactResult]]:
        """Node contacts with rigid links solved in the last step: index in ``sim.bodies`` -> (contacts, result)."""
        return self.report.contact_results

    @property
    def face_results(self) -> dict[int, tuple[FaceContacts, ContactResult]]:
        """Face contacts with rigid links solved in the last step: index in ``sim.bodies`` -> (contacts, result)."""
        return self.report.face_results

    @property
    def pair_results(self) -> list[tuple[PairContacts, ContactResult]]:
        """Soft contacts solved in the last step: [(contacts, result)]."""
        return self.report.pair_results

    @property
    def attachment_forces(self) -> list[tuple[Attachment, np.ndarray]]:
        """Forces [N] (m, 3) on the attached nodes in the last step: [(attachment, forces)]."""
        return [(self.attachments[k], f) for k, f in self.report.attachment_forces]

    @property
    def timings(self) -> dict[str, float]:
        """Seconds of the last step by disjoint phase: collision (queries), rigid (pybullet and the coupling's rigid
        side), the core's rotations, forces, assembly, factorize, solve (linear algebra), contact (the contact solve's
        own work), other (the rest of the FEM step); "total" is their sum."""
        return self.report.timings

    @property
    def bodies(self) -> list[FemBody]:
        """The soft bodies, in the order they were added (the stepped ones, stacks among them, are
        ``sim.bodies``)."""
        return self._members

    @property
    def _members(self) -> list[FemBody]:
        return [e.body for e in self._entries]

    def _handle(self, body: FemBody, what: str) -> int:
        """The handle (index in ``bodies``) of soft body ``body``; InvalidInputError naming ``what`` otherwise."""
        for k, e in enumerate(self._entries):
            if e.body is body:
                return k
        raise InvalidInputError(f"{what}: not a soft body of this World (add it with add_soft)")

    def entry(self, body: FemBody) -> SoftEntry:
        """What the World keeps for soft body ``body`` (integration.entries.SoftEntry: friction, what it ignores,
        self-contact, surface, its place in a stack, its contact group)."""
        return self._entries[self._handle(body, "entry")]

    def close(self) -> None:
        """Disconnect the World's own pybullet client; a joined client stays connected."""
        self.adapter.close()

    def __enter__(self) -> "World":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ rigid bodies
    def _warn_once(self, key, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            warnings.warn(message, stacklevel=3)

    def _sync(self) -> None:
        """Pick up the client's bodies that appeared since the last step (each link with a collision shape
        becomes a rigid link) and drop the removed ones."""
        ids = self.adapter.body_ids()
        current = set(ids)
        if current == self._known:
            return
        for gone in self._known - current:
            for key in [k for k in self.rigids if k[0] == gone]:
                del self.rigids[key]
            self._one_way.discard(gone)
            self.motors.forget(gone)
        for b in ids:
            if b not in self._known:
                self._register(b)
        self._known = current

    def _register(self, b: int) -> None:
        """Make every link of pybullet body b that has a collision shape a rigid link."""
        ad = self.adapter
        _, unsupported = ad.joints(b)
        movable = ad.movable(b)
        if movable and unsupported:
            self._warn_once(("joints", b), f"body {b} ({ad.body_name(b)!r}) has spherical or planar joints "
                            f"{unsupported}: the coupled solve handles revolute and prismatic joints only, so the "
                            "soft bodies' reactions reach this body one step late (as forces)")
            movable = False
        for link in range(BASE, ad.num_links(b)):
            if (b, link) in self.rigids:
                continue
            shapes = ad.collision_shapes(b, link)
            if not shapes:
                continue
            name = ad.body_name(b) if link == BASE else f"{ad.body_name(b)}/{ad.link_name(b, link)}"
            self.rigids[(b, link)] = RigidLink(b, ad, "urdf", {}, ad.mass(b, link), name=name, link=link,
                                               movable=movable, shapes=shapes)
        if ad.movable(b) and unsupported:
            self._one_way.add(b)

    def _add(self, shape: RigidShape, position, orientation, mass: float, motion: PoseScript | None, name: str,
             friction: float | None, tm=None) -> RigidLink:
        mass = float(mass)
        if not math.isfinite(mass) or mass < 0:
            raise InvalidInputError(f"mass must be >= 0 (0: fixed or kinematic), got {mass!r}")
        if motion is not None and mass > 0:
            raise InvalidInputError("a kinematic body (with a motion script) must have mass 0")
        if motion is not None and not callable(motion):
            raise InvalidInputError("motion must be a function of time returning a pose")
        if friction is not None:
            friction = _friction(friction)
        bid = self.adapter.create_body(shape, _vec3(position, "position"), _quat(orientation), mass)
        body = RigidLink(bid, self.adapter, shape.kind, shape.params(), mass, motion, name or f"{shape.kind}{bid}",
                         friction, shape.concave, tm, movable=mass > 0, shapes=self.adapter.collision_shapes(bid, BASE),
                         geometry=shape)
        if motion is not None:
            pos, orn = body.scripted_pose(self.t)
            self.adapter.reset_pose(bid, pos.tolist(), orn.tolist())
        self.rigids[(bid, BASE)] = body
        self._known.add(bid)
        return body

    def add_sphere(self, radius: float, position=(0, 0, 0), mass: float = 0.0, motion: PoseScript | None = None,
                   name: str = "", friction: float | None = None) -> RigidLink:
        """A sphere of ``radius`` [m]: fixed (mass 0), dynamic (mass > 0 [kg]) or kinematic (motion script)."""
        r = _positive(radius, "radius")
        return self._add(Sphere(r), position, None, mass, motion, name, friction)

    def add_box(self, half_extents, position=(0, 0, 0), orientation=None, mass: float = 0.0,
                motion: PoseScript | None = None, name: str = "", friction: float | None = None) -> RigidLink:
        """A box with ``half_extents`` (3,) [m]."""
        he = np.asarray(half_extents, dtype=float)
        if he.shape != (3,) or not np.isfinite(he).all() or (he <= 0).any():
            raise InvalidInputError(f"half_extents must be three positive lengths, got {half_extents!r}")
        return self._add(Box(he), position, orientation, mass, motion, name, friction)

    def add_plane(self, normal=(0, 0, 1), point=(0, 0, 0), name: str = "", friction: float | None = None,
                  motion: PoseScript | None = None) -> RigidLink:
        """An infinite fixed plane through ``point`` with outward ``normal``."""
        nrm = np.asarray(_vec3(normal, "normal"))
        if np.linalg.norm(nrm) == 0:
            raise InvalidInputError("plane normal must be non-zero")
        nrm = nrm / np.linalg.norm(nrm)
        return self._add(Plane(nrm), point, None, 0.0, motion, name, friction)

    def add_mesh(self, mesh, position=(0, 0, 0), orientation=None, mass: float = 0.0, scale: float = 1.0,
                 motion: PoseScript | None = None, name: str = "", friction: float | None = None,
                 convex: bool | None = None) -> RigidLink:
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
            tm = tm.convex_hull
        return self._add(Mesh(np.asarray(tm.vertices), np.asarray(tm.faces), concave=not convex), position,
                         orientation, mass, motion, name, friction, tm=tm)

    def rigid(self, body_id: int, link: int = BASE) -> RigidLink:
        """The rigid link ``link`` (-1: the base) of pybullet body ``body_id``."""
        self._sync()
        if (body_id, link) not in self.rigids:
            known = sorted({k[0] for k in self.rigids})
            if body_id in known:
                links = sorted(k[1] for k in self.rigids if k[0] == body_id)
                raise InvalidInputError(f"rigid body {body_id} has no link {link!r} with a collision shape; "
                                        f"its links: {links}")
            raise InvalidInputError(f"unknown rigid body id {body_id!r}; known ids: {known}")
        return self.rigids[(body_id, link)]

    def _link_of(self, rigid, link: int | None) -> RigidLink:
        if isinstance(rigid, RigidLink):
            if link is not None and link != rigid.link:
                return self.rigid(rigid.id, link)
            return rigid
        return self.rigid(rigid, BASE if link is None else link)

    def set_friction(self, rigid, mu: float | None, link: int | None = None) -> None:
        """Coulomb coefficient of a rigid body (all its links, or one ``link``) against soft bodies; None:
        the soft body's own."""
        mu = None if mu is None else _friction(mu)
        bid = rigid.id if isinstance(rigid, RigidLink) else rigid
        if link is not None or not any(k[0] == bid for k in self.rigids):
            self.rigid(bid, BASE if link is None else link)  # a clear error for an unknown body or link
        for key, rb in self.rigids.items():
            if key[0] == bid and (link is None or key[1] == link):
                rb.friction = mu

    # ------------------------------------------------------------------ soft bodies
    def set_motor(self, body: int, joint: int, mode: str | int = "position", target_position: float = 0.0,
                  target_velocity: float = 0.0, force: float = 100000.0, position_gain: float = 0.1,
                  velocity_gain: float = 1.0, max_velocity: float | None = None) -> Motor:
        """Drive joint ``joint`` of pybullet body ``body`` by a motor, as ``pybullet.setJointMotorControl2`` would
        (the same arguments and defaults; ``mode`` "position" or "velocity", or pybullet's POSITION_CONTROL and
        VELOCITY_CONTROL), and keep it in the coupled step: while the body is in the coupled problem (in contact with
        a soft body, or attached to one) the motor is a row of that problem with its force limit (integration.joints),
        so that it pushes through a soft body with at most ``force`` [N or N m] at any dt, as it does against a rigid
        body in plain pybullet. Elsewhere pybullet runs it in its own step. Set again to change it; ``force=0``
        leaves the joint free. Returns the Motor."""
        import pybullet as p

        self._sync()
        ids = self.adapter.body_ids()
        if body not in ids:
            raise InvalidInputError(f"set_motor: no pybullet body {body} in the World's client (bodies: {ids})")
        movable, _ = self.adapter.joints(body)
        if joint not in movable:
            raise InvalidInputError(f"set_motor: joint {joint} of body {body} is not a revolute or prismatic joint "
                                    f"(those are {movable})")
        modes = {p.POSITION_CONTROL: "position", p.VELOCITY_CONTROL: "velocity"}
        if not isinstance(mode, str):
            if mode not in modes:
                raise InvalidInputError(f"set_motor: mode must be 'position' or 'velocity' (POSITION_CONTROL, "
                                        f"VELOCITY_CONTROL); torque control acts in pybullet's step as a force, "
                                        f"with no limit to hold (got {mode!r})")
            mode = modes[mode]
        motor = Motor(int(body), int(joint), mode, finite_number(target_position, "target_position"),
                      finite_number(target_velocity, "target_velocity"), finite_number(force, "force", 0.0, False, "[N or N m]"),
                      finite_number(position_gain, "position_gain", 0.0, False),
                      finite_number(velocity_gain, "velocity_gain", 0.0, False),
                      math.inf if max_velocity is None else finite_number(max_velocity, "max_velocity", 0.0, False))
        self.motors.set(motor)
        self.adapter.set_motor(motor)
        return motor

    def set_motors(self, body: int, joints: Iterable[int], mode: str | int = "position",
                   target_positions: Iterable[float] | None = None, target_velocities: Iterable[float] | None = None,
                   forces: Iterable[float] | float = 100000.0, position_gains: Iterable[float] | float = 0.1,
                   velocity_gains: Iterable[float] | float = 1.0) -> list[Motor]:
        """:meth:`set_motor` for several joints of one body, as ``pybullet.setJointMotorControlArray``: the targets,
        forces and gains one per joint (a single number: the same for all). Returns the Motors."""
        try:
            joints = [int(j) for j in joints]
        except (TypeError, ValueError):
            raise InvalidInputError(f"set_motors: joints must be joint indices, got {joints!r}") from None
        movable, _ = self.adapter.joints(body) if body in self.adapter.body_ids() else ([], [])
        bad = [j for j in joints if j not in movable]
        if bad:  # all checked before any is set
            raise InvalidInputError(f"set_motors: joints {bad} of body {body} are not revolute or prismatic joints "
                                    f"(those are {movable})")

        def each(values, name: str, default: float) -> list[float]:
            if values is None:
                return [default] * len(joints)
            if np.ndim(values) == 0:
                return [float(values)] * len(joints)
            values = list(values)
            if len(values) != len(joints):
                raise InvalidInputError(f"set_motors: {name} needs one value per joint ({len(joints)}), got "
                                        f"{len(values)}")
            return values

        columns = zip(each(target_positions, "target_positions", 0.0), each(target_velocities, "target_velocities", 0.0),
                      each(forces, "forces", 100000.0), each(position_gains, "position_gains", 0.1),
                      each(velocity_gains, "velocity_gains", 1.0))
        return [self.set_motor(body, j, mode, q, v, f, kp, kd) for j, (q, v, f, kp, kd) in zip(joints, columns)]

    def motor_force(self, body: int, joint: int) -> float:
        """The force or torque [N or N m] the motor of joint ``joint`` of body ``body`` exerted over the last step:
        the coupled problem's where the body was in it (a registered motor, :meth:`set_motor`), else pybullet's own
        (its applied joint motor torque)."""
        key = ("motor", int(body), int(joint))
        if key in self.report.joint_forces:
            return self.report.joint_forces[key]
        return float(self.adapter.motor_torques(int(body), [int(joint)])[0])

    def add_soft(self, body: FemBody, friction: float = 0.0, ignore: Iterable = (), self_contact: bool = False
                 ) -> FemBody:
        """Add a soft body; ``friction`` is its Coulomb coefficient against rigid bodies (>= 0) and, the
        smaller of the two, against other soft bodies; ``ignore``: rigid bodies (ids or RigidLinks), (body
        id, link) pairs or soft bodies it does not collide with; ``self_contact``: keep its surface from
        passing through itself (off by default: it costs a search of the body against itself every step)."""
        if not isinstance(body, FemBody):
            raise InvalidInputError(f"add_soft needs a softbody.FemBody, got {type(body).__name__}")
        self.sim.admit(body)  # a model the world's scheme steps
        friction = finite_number(friction, "friction", 0.0, strict=False)
        if any(b is body for b in self._members):
            raise InvalidInputError("this soft body is already in the world")
        if not isinstance(self_contact, (bool, np.bool_)):
            raise InvalidInputError(f"self_contact must be True or False, got {self_contact!r}")
        skip = set()
        for item in ignore:
            if isinstance(item, FemBody):
                skip.add(("soft", item))
            elif isinstance(item, RigidLink):
                skip.add(item.key)
            elif isinstance(item, tuple) and len(item) == 2:
                skip.add((int(item[0]), int(item[1])))
            elif isinstance(item, (int, np.integer)):
                skip.add((int(item), None))
            else:
                raise InvalidInputError(f"ignore: expected rigid body ids, RigidLinks, (body id, link) pairs or "
                                        f"soft bodies (FemBody), got {item!r}")
        entry = SoftEntry(body, friction, skip, bool(self_contact), SoftSurface.of(body.rest, body.mesh.surface_triangles()),
                          place=(len(self.sim.bodies), 0))
        self._entries.append(entry)
        self.sim.bodies.append(body)  # stepped alone until the next step stacks it (_restack)
        self._stepped.append(SteppedEntry(body, [len(self._entries) - 1], friction, skip, entry.surface))
        self._restack_due = True
        self._pairs_version += 1
        return body

    def attach(self, body: FemBody, node_ids, rigid: RigidLink | int, link: int | None = None,
               collide: bool = False) -> Attachment:
        """Hold nodes of a soft body to a rigid link where they are now (rigidly attached).

        rigid: a RigidLink or a pybullet body id, with ``link`` (default: the base, -1). On a movable link
        (a dynamic body or a robot's link) the attachment is two-way: the nodes and the rigid point move
        together, the soft body's weight and inertia load the rigid body. On a fixed or kinematic one the
        nodes follow its pose. collide: keep the contacts between this soft body and that link (off by
        default: a body attached flush against a link would otherwise push against it)."""
        if not any(b is body for b in self._members):
            raise InvalidInputError("attach: add the soft body to the world first (add_soft)")
        entry = self.entry(body)
        rb = self._link_of(rigid, link)
        ids = body._node_ids(node_ids, "attach")
        local = rb.to_local(body.positions[ids])
        coupled = rb.movable and rb.motion is None
        if not coupled:
            body.prescribe(ids, self._follow(rb, local))
        if not collide:
            entry.ignore.add(rb.key)
            self._restack_due = True  # what it ignores decides its stack
            self._pairs_version += 1
        att = Attachment(body, ids, rb, local, coupled, len(self.attachments))
        self.attachments.append(att)
        return att

    def _stack_key(self, entry: SoftEntry) -> tuple | None:
        """What a soft body must share with others to be stepped in one stack with them (softbody.stack_key,
        friction, self-contact, the rigid links it ignores); None: stacking off."""
        if not self._stack:
            return None
        return (stack_key(entry.body), entry.friction, entry.self_contact, entry.rigid_ignore())

    def _restack(self) -> None:
        """Group the soft bodies into the stepped ones (sim.bodies): a BodyStack for each two or more of one
        key, the others alone; unchanged while no body was added and no grouping changed. The members of the coupled
        contact groups (:meth:`_group_dense`) of one key are a stack of their own, all groups together: they are
        solved in one convex problem anyway, which takes the stack's block pattern as its members' side by side
        (convex.GroupPattern), and one stepped body costs one step system and one search per link instead of one per
        member or group (twelve stacked tet10 cubes 22.4 -> 18.6 ms a step; thirty in the tray, settling as nine
        columns, 87 -> 76 ms with one stack instead of one per column; benchmarks/piles.py). (The former dense solve
        found each stepped body's responses to every row touching it: its members were stepped alone.)"""
        if not self._restack_due:
            return
        self._restack_due = False
        groups: dict = {}
        for k, e in enumerate(self._entries):
            key = self._stack_key(e)
            if key is not None and e.group is not None:  # the coupled contact groups' members: stepped together
                key = key + ("coupled",)
            groups.setdefault(("alone", k) if key is None else key, []).append(k)
        self._apply_layout(list(groups.values()))

    def _apply_layout(self, groups: list[list[int]]) -> None:
        """Step the soft bodies as ``groups`` (each a list of member handles: one alone, several as a BodyStack, a
        stack of the same members kept), with what each stepped body needs (friction, ignored links, surface) and
        each member's place."""
        held = {tuple(e.members): e for e in self._stepped if len(e.members) > 1}
        stepped: list[SteppedEntry] = []
        for g in groups:
            first = self._entries[g[0]]
            if len(g) == 1:
                stepped.append(SteppedEntry(first.body, list(g), first.friction, first.ignore, first.surface))
                continue
            kept = held.pop(tuple(g), None)  # a stack of the same members: kept (its solver and factor with it)
            if kept is None:
                stack = BodyStack([self._entries[k].body for k in g])
                kept = SteppedEntry(stack, list(g), first.friction, first.rigid_ignore(),
                                    SoftSurface.of(stack.rest, stack.mesh.surface_triangles()))
            else:  # what its members share now (attach may have added an ignored link to each since)
                kept.friction, kept.ignore = first.friction, first.rigid_ignore()
            stepped.append(kept)
        # stacks dissolved: their members keep their state (views of its rows)
        stepping = {e.body for e in stepped}  # what was kept for bodies no longer stepped goes (the warm starts
        for key in [k for k in self.contact_solver.previous if k[1] not in stepping and k[0] != "soft"]:  # of
            del self.contact_solver.previous[key]  # contacts restart from the contact state found in the next step)
        self.sim.solvers.retain([e.body for e in stepped])
        for i, e in enumerate(stepped):
            for k, o in zip(e.members, getattr(e.body, "offsets", [0])):
                self._entries[k].place = (i, int(o))
        self._stepped = stepped
        self.sim.bodies[:] = [e.body for e in stepped]

    def _stepped_now(self) -> list[FemBody]:
        """The stepped bodies (sim.bodies), restacked if due, the stacks holding their members' current state and
        supports (what the user changed since the last step)."""
        self._restack()
        for s in self.sim.bodies:
            if isinstance(s, BodyStack):
                s.gather()
        return self.sim.bodies

    def _group_dense(self, record: StepRecord) -> None:
        """Merge the contact groups of this step's members that need the coupled contact solve (ContactSolver.solve:
        soft contact, a movable rigid body in contact or attached, friction at face contacts): those in soft
        contact with each other or touching one movable body join one group, the others a group of their own;
        a member joining the coupled set restacks from the next step on (:meth:`_restack`; groups merging within it
        change no stack)."""
        if not self._stack or len(self._members) < 2:
            return
        member_pairs, coupling = record.member_pairs, record.coupling
        if not (len(member_pairs) or coupling.n or len(record.face_hits)):
            return  # nothing that calls for the coupled solve (no soft contact, no movable body, no face contact)
        n = len(self._members)  # each pair of members in contact once (a pile's contacts are many rows per pair)
        pairs = np.unique(member_pairs[:, 0] * n + member_pairs[:, 1]) if len(member_pairs) else np.zeros(0, np.int64)
        links: list[tuple[int, int]] = list(zip((pairs // n).tolist(), (pairs % n).tolist()))
        by_rigid: dict[int, int] = {}

        def member_of(stepped: np.ndarray, node: np.ndarray) -> np.ndarray:
            out = np.empty(len(node), dtype=np.int64)
            for i, e in enumerate(self._stepped):
                on = stepped == i
                if not on.any():
                    continue
                s = e.body
                local = s.member_of(node[on]) if isinstance(s, BodyStack) else np.zeros(int(on.sum()), np.int64)
                out[on] = np.array(e.members)[local]
            return out

        c, f = record.candidates, record.face_hits
        coupled = np.isin(c.rigid, list(coupling.dynamics)) if coupling.n else np.zeros(len(c), bool)
        f_coupled = np.isin(f.rigid, list(coupling.dynamics)) if coupling.n else np.zeros(len(f), bool)
        for who, rid in ((member_of(c.body[coupled], c.node[coupled]), c.rigid[coupled]),
                         (member_of(f.body[f_coupled], f.nodes[f_coupled, 0]), f.rigid[f_coupled])):
            for k, r in zip(who.tolist(), rid.tolist()):
                links.append((by_rigid.setdefault(r, k), k))
        for att in self.attachments:
            if att.coupled:
                k = self._handle(att.body, "attachment")
                links.append((by_rigid.setdefault(att.rigid.id, k), k))
        if len(f):  # friction at face contacts: the rigid link's coefficient, else the soft body's
            who = member_of(f.body, f.nodes[:, 0])
            mu = np.array([e.friction for e in self._entries])[who]
            links_of, at = np.unique(np.column_stack([f.rigid, f.link]), axis=0, return_inverse=True)
            for j, (r, lk) in enumerate(links_of.tolist()):
                own = self.rigids[(r, lk)].friction
                if own is not None:
                    mu[at.reshape(-1) == j] = own
            links += [(k, k) for k in np.unique(who[mu > 0]).tolist()]
        joined = False  # a member new to the coupled set restacks (groups merging within it change no stack)
        entries = self._entries
        for a, b in links:
            ea, eb = entries[a], entries[b]
            ga, gb = ea.group, eb.group
            if ga is None and gb is None:
                ea.group = eb.group = a
            elif ga is None or gb is None:
                (ea if ga is None else eb).group = gb if ga is None else ga
            elif ga != gb:
                for e in entries:
                    if e.group == gb:
                        e.group = ga
                continue
            else:
                continue
            joined = True
        if joined:
            self._restack_due = True

    def stepped(self, body: FemBody) -> FemBody:
        """The body that steps soft body ``body``: itself, or the BodyStack it is stepped in (softbody.stack)."""
        k = self._handle(body, "stepped")
        self._restack()
        return self.sim.bodies[self._entries[k].place[0]]

    def _member(self, stepped: int, node: int) -> int:
        """The index in ``bodies`` of the soft body that node ``node`` of stepped body ``stepped`` belongs to."""
        e = self._stepped[stepped]
        return e.members[int(e.body.member_of(np.array([node]))[0])] if isinstance(e.body, BodyStack) else e.members[0]

    def _follow(self, rb: RigidLink, local: np.ndarray) -> Callable[[float], np.ndarray]:
        """The positions of rigid points ``local`` (m, 3) at time t, for nodes held to a link that the
        coupled solve does not move (scripted: its pose at t; otherwise its motion extrapolated)."""
        def motion(t: float) -> np.ndarray:
            if rb.motion is not None:
                pos, orn = rb.scripted_pose(t)
                return local @ quat_matrix(orn).T + pos
            c, q, v, w = self.adapter.state(rb.id, rb.link)
            x = local @ quat_matrix(q).T + c
            dt = t - self.t
            return x + v * dt + np.cross(w, x - c) * dt
        return motion

    # ------------------------------------------------------------------ stepping
    def _rigid_point_velocity(self, rb: RigidLink, points: np.ndarray) -> np.ndarray:
        if rb.id in self._kin_velocity:
            v, w = self._kin_velocity[rb.id]
            c, _ = rb.pose()
            return v + cross(w, points - c)
        return rb.point_velocity(points)

    def _detect(self, i: int) -> tuple[Contacts, FaceHits]:
        """Contact candidates of stepped body i against every rigid link it does not ignore (collision.py)."""
        e = self._stepped[i]
        body, surf = e.body, e.surface
        links = [rb for rb in self.rigids.values() if not e.ignores(rb)]
        v = body.velocities
        speeds = np.sqrt(np.einsum("ij,ij->i", v, v))
        sweeps = [self._sweep(rb, v, speeds) for rb in links]
        return self.detector.detect(i, body.positions, surf.nodes, surf.triangles, body.supported(), links, sweeps,
                                    TOUCH * self.contact_margin, surf.incidence, (surf.edges, surf.edge_tris),
                                    self.movable_edges)

    def _sweep(self, rb: RigidLink, velocities: np.ndarray, speeds: np.ndarray | None = None) -> Sweep:
        """The motions of a link and a soft body's nodes (velocities (N, 3), speeds (N,)) over the step, for the
        contact search (collision.Sweep)."""
        if speeds is None:
            speeds = np.sqrt(np.einsum("ij,ij->i", velocities, velocities))
        if rb.id in self._kin_velocity:
            v, w = self._kin_velocity[rb.id]
        elif rb.movable or rb.id in self._one_way:
            v, w = rb.velocity()
        else:
            return Sweep(self.contact_margin, self.dt, velocities, speeds, radius=rb.bounding_radius(),
                         centre=rb.pose()[0])
        return Sweep(self.contact_margin, self.dt, velocities, speeds, v, w, rb.pose()[0], rb.bounding_radius())

    def _soft_pairs(self, skipped: list | None = None) -> list[tuple[int, int]]:
        """Index pairs (a, b) of the soft bodies to search for contact (a == b: self-contact); the pairs left
        out (soft contact off, or ignored) are appended to ``skipped`` with the reason. Kept until a body is
        added or told to ignore another."""
        key = (len(self._members), self.soft_contact, self._pairs_version)
        if self._pairs_memo is None or self._pairs_memo[0] != key:
            found: list = []
            self._pairs_memo = (key, self._find_soft_pairs(found), found)
        if skipped is not None:
            skipped.extend(self._pairs_memo[2])
        return self._pairs_memo[1]

    def _find_soft_pairs(self, skipped: list) -> list[tuple[int, int]]:
        out = []
        entries = self._entries
        for a, ea in enumerate(entries):
            if ea.self_contact:
                out.append((a, a))
            for b in range(a + 1, len(entries)):
                eb = entries[b]
                if not self.soft_contact:
                    why = "soft contact is off (World(soft_contact=False))"
                elif ea.ignores_soft(eb.body) or eb.ignores_soft(ea.body):
                    why = "they were told not to collide (add_soft(..., ignore=...))"
                else:
                    out.append((a, b))
                    continue
                skipped.append((a, b, why))
        return out

    def _detect_soft(self, record: StepRecord) -> None:
        """Contact candidates between the soft bodies, and of bodies with self-contact (softcontact.py), searched
        body by body and numbered by the stepped bodies (a, b index sim.bodies, node and nodes theirs; triangle
        stays the soft body's own surface triangle), into the record (soft_hits, edge_hits, member_pairs); a warning,
        once, when bodies left out of soft contact meet (their boxes overlap)."""
        skipped: list = []
        pairs = self._soft_pairs(skipped)
        for a, b, why in skipped:
            (la, ha), (lb, hb) = (self._box(k) for k in (a, b))
            if np.all(la <= hb) and np.all(lb <= ha):
                self._warn_once(("soft off", a, b), f"soft bodies {a} and {b} meet, but {why}: they pass through "
                                "each other")
        if not pairs:
            return
        data = [(e.body.positions, e.body.velocities, e.surface, e.body.rest) for e in self._entries]
        key = self._pairs_memo[0]  # the members' surfaces are fixed: the search's layout lasts as the pairs do
        if self._soft_layout is None or self._soft_layout[0] != key:
            self._soft_layout = (key, SoftLayout.of([sf for _, _, sf, _ in data], pairs))
        depth = SOFT_DEPTH * self.contact_margin
        hits = soft_contacts(data, pairs, self.contact_margin, self.dt, depth, self._soft_layout[1], self._first_pass)
        edges = edge_contacts(data, pairs, self.contact_margin, self.dt, EDGE_DEPTH * self.contact_margin, hits,
                              self._soft_layout[1], self._edge_pass)
        # in the members' numbering
        record.member_pairs = np.concatenate([np.column_stack([hits.a, hits.b]), np.column_stack([edges.a, edges.b])])
        if (len(hits) or len(edges)) and len(self.sim.bodies) < len(self._members):  # to the stepped bodies' numbering
            place = np.array([e.place for e in self._entries])
            hits.node = hits.node + place[hits.a, 1]
            hits.nodes = hits.nodes + place[hits.b, 1][:, None]
            hits.a, hits.b = place[hits.a, 0], place[hits.b, 0]
            edges.nodes = edges.nodes + np.column_stack([place[edges.a, 1]] * 2 + [place[edges.b, 1]] * 2)
            edges.a, edges.b = place[edges.a, 0], place[edges.b, 0]
        record.soft_hits, record.edge_hits = hits, edges

    def _box(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The box (lo (3,), hi (3,)) [m] of soft body k's surface nodes."""
        e = self._entries[k]
        x = e.body.positions[e.surface.nodes]
        return x.min(axis=0), x.max(axis=0)

    def _pair_contacts(self, hits: SoftHits, edges: EdgeHits) -> PairContacts | None:
        """The solver's form of soft contact candidates, node against face and edge against edge: rows over both
        bodies (4 slots), friction the smaller one's, the point on body b's side."""
        m = len(hits) + len(edges)
        if not m:
            return None
        a, b = np.concatenate([hits.a, edges.a]), np.concatenate([hits.b, edges.b])
        mu_of = np.array([e.friction for e in self._stepped])
        parts = np.concatenate([np.column_stack([hits.a, hits.b, hits.b, hits.b]),
                                np.column_stack([edges.a, edges.a, edges.b, edges.b])])
        nodes = np.concatenate([np.column_stack([hits.node, hits.nodes]), edges.nodes])
        weights = np.concatenate([np.column_stack([np.ones(len(hits)), -hits.weights]), edges.weights])
        point = np.zeros((m, 3))
        on_b = weights < 0  # the slots of body b: minus its weights
        for k in np.unique(b).tolist():
            on = b == k
            x = self.sim.bodies[k].positions[np.where(on_b[on], nodes[on], 0)]  # (a's slots: other bodies' nodes)
            point[on] = np.einsum("ms,msi->mi", np.where(on_b[on], -weights[on], 0.0), x)
        return PairContacts(np.concatenate([hits.key, edges.key]), np.concatenate([hits.normal, edges.normal]),
                            np.concatenate([hits.distance, edges.distance]), np.zeros((m, 3)),
                            np.minimum(mu_of[a], mu_of[b]), np.full(m, -1), point, np.full(m, -1), parts=parts,
                            nodes=nodes, weights=weights)

    def _contact_data(self, i: int, found: Contacts | FaceHits, coupling: RigidCoupling
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """For contacts with rigid links: friction (m,), the rigid points' velocities (m, 3) (for movable
        bodies filled in after pybullet's step) and the Jacobians (m, 3, n) of the coupled ones."""
        mu = np.full(len(found), self._stepped[i].friction)
        vr = np.zeros((len(found), 3))
        keys = set(zip(found.rigid.tolist(), found.link.tolist()))
        for key in keys:
            sel = slice(None) if len(keys) == 1 else (found.rigid == key[0]) & (found.link == key[1])
            rb = self.rigids[key]
            if rb.friction is not None:  # a rigid body's own coefficient overrides the soft body's
                mu[sel] = rb.friction
            if key[0] not in coupling.dynamics:
                vr[sel] = self._rigid_point_velocity(rb, found.point[sel])
        J = coupling.jacobians(self.adapter, found.rigid, found.link, found.point) if coupling.n else None
        return mu, vr, J

    def _node_contacts(self, i: int, found: Contacts, coupling: RigidCoupling, carried: bool = False
                       ) -> NodeContacts:
        """The solver's form of node contacts; carried: found at the end of the step (see NodeContacts)."""
        mu, vr, J = self._contact_data(i, found, coupling)
        return NodeContacts(found.node, found.normal, found.distance, vr, mu, found.rigid, found.point,
                            found.link, J, np.full(len(found), carried))

    def _face_contacts(self, i: int, hits: FaceHits, coupling: RigidCoupling) -> FaceContacts:
        mu, vr, J = self._contact_data(i, hits, coupling)
        return FaceContacts(hits.key, hits.normal, hits.distance, vr, mu, hits.rigid, hits.point, hits.link, J,
                            nodes=hits.nodes, weights=hits.weights, group=hits.group, primary=hits.primary,
                            edge=hits.edge)

    def _coupled_attachments(self, i: int, coupling: RigidCoupling
                             ) -> list[tuple[Attachment, np.ndarray, np.ndarray, np.ndarray]]:
        """(attachment, its nodes in stepped body i (m,), start points (m, 3), Jacobians (m, 3, n)) of that body's
        two-way attachments."""
        out = []
        for att in self.attachments:
            where, first = self.entry(att.body).place
            if where == i and att.coupled:
                pts = att.rigid.to_world(att.local)
                link = np.full(len(pts), att.rigid.link)
                J = coupling.jacobians(self.adapter, np.full(len(pts), att.rigid.id), link, pts)
                out.append((att, att.nodes + first, pts, J))
        return out

    def _body_steps(self, record: StepRecord, systems: list[LinearSystem], supports: list[Constraints],
                    u: np.ndarray) -> list[BodyStep]:
        """Each soft body's part of the contact solve: its system, supports, the record's contacts and coupled
        attachments, with the rigid points' velocities under the free motion u (n,) of the coupled bodies."""
        steps = []
        h, coupling = self.dt, record.coupling
        for i, (body, system, sup) in enumerate(zip(record.bodies, systems, supports)):
            c, f = record.contacts.get(i), record.faces.get(i)
            for cc in (c, f):
                if cc is not None and coupling.n:  # rigid velocities of the coupled points under the free motion
                    on = np.isin(cc.rigid, list(coupling.dynamics))
                    cc.rigid_velocity[on] = cc.jacobian[on] @ u
            att = None
            parts = record.attachments.get(i, [])
            if parts:
                nodes, target, J, rid, lid, pts = [], [], [], [], [], []
                for a, ids, p0, Ja in parts:
                    end = a.rigid.to_world(a.local)  # where the points went under the free motion
                    nodes.append(ids)
                    target.append((end - body.positions[ids]) / h)
                    J.append(Ja)
                    rid.append(np.full(len(a.nodes), a.rigid.id))
                    lid.append(np.full(len(a.nodes), a.rigid.link))
                    pts.append(p0)
                att = Attachments(*(np.concatenate(v) for v in (nodes, target, J, rid, lid, pts)))
            steps.append(BodyStep(system, sup, c, att, f))
        return steps

    def _end_pose(self, record: StepRecord, rb: RigidLink, du: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A moving link's pose (centre (3,), quaternion (4,)) at the end of the step: a kinematic link's
        scripted one; a dynamic one's after pybullet's step, its centre moved on by the coupled velocity change
        du (n,) of the solve (its rotation by the free motion alone)."""
        if rb.motion is not None:
            return rb.scripted_pose(record.t + self.dt)
        c1, q1 = rb.pose()
        coupling = record.coupling
        if rb.id in coupling.dynamics and len(du):
            J = coupling.jacobians(self.adapter, np.array([rb.id]), np.array([rb.link]),
                                   record.poses0[rb.key][0][None])
            c1 = c1 + self.dt * (J[0] @ du)
        return c1, q1

    def _end_contacts(self, record: StepRecord, velocities: list[np.ndarray], du: np.ndarray) -> bool:
        """Node contacts the start of the step missed: nodes that the solved velocities (N, 3) per body carry
        inside a moving rigid link (primitives) at its pose at the end of the step (:meth:`_end_pose`, with the
        solve's du) join the record's node contacts of the body, in place of a start contact of the same node; each
        is the end pose's closest point carried back to the start with the link (so the condition
        n . (x_end - p_end) >= 0 holds at the end), and only where the node moved into the link across that point's
        normal (not through it: a normal on the far side would pull it through). Returns whether any joined."""
        h, added = self.dt, False
        moving = [rb for rb in self.rigids.values() if rb.key in record.poses0 and rb.primitive_parts() is not None]
        if not moving:
            return False
        ends = {rb.key: self._end_pose(record, rb, du) for rb in moving}
        for i, (e, v) in enumerate(zip(self._stepped, velocities)):
            body = e.body
            surface = e.surface.nodes
            surface = surface[~body.supported()[surface]]
            x0 = body.positions[surface]
            x1 = x0 + h * v[surface]
            found = []
            for rb in moving:
                if e.ignores(rb):
                    continue
                c1, q1 = ends[rb.key]
                near = np.einsum("ij,ij->i", x1 - c1, x1 - c1) <= (rb.bounding_radius() + self.contact_margin) ** 2
                if not near.any():
                    continue
                point, normal, dist = primitive_distances(rb, rb.primitive_parts(), x1[near], (c1, q1))
                c0, q0 = record.poses0[rb.key]
                local = (point - c1) @ quat_matrix(q1)  # the material points, carried back to the start
                start = local @ quat_matrix(q0).T + c0
                moved_in = np.einsum("ij,ij->i", (x1[near] - x0[near]) - (point - start), normal) < 0
                inside = (dist < -END_TOL) & moved_in
                if not inside.any():
                    continue
                start = start[inside]
                nodes = surface[near][inside]
                d = np.einsum("ij,ij->i", body.positions[nodes] - start, normal[inside])
                m = len(nodes)
                found.append(Contacts(np.full(m, i), nodes, np.full(m, rb.id), start, normal[inside], d,
                                      np.full(m, rb.link)))
            found = Contacts.concat(found)
            if not len(found):
                continue
            order = np.lexsort((found.distance, found.node))  # one per node: the deepest
            found = found.select(order[run_starts(found.node[order])])
            new = self._node_contacts(i, found, record.coupling, carried=True)
            old = record.contacts.get(i)
            if old is not None:
                new = _concat_contacts(old.select(~np.isin(old.node, new.node)), new)
            record.contacts[i] = new
            added = True
        return added

    def _solve_velocities(self, record: StepRecord, systems: list[LinearSystem],
                          supports: list[Constraints]) -> list[np.ndarray]:
        """The contact and coupling solve of all soft bodies (the velocities Simulation.solve_step asks for), into
        record.solution: with the contacts found at the start, then again with those the end of the step reveals."""
        timings, coupling = record.timings, record.coupling
        with timed(timings, "contact"):
            with timed(timings, "rigid"):
                u = np.zeros(coupling.n)
                for b, o in coupling.offset.items():
                    u[o:o + coupling.dynamics[b].n] = self.adapter.generalized_velocity(coupling.dynamics[b])
                steps = self._body_steps(record, systems, supports, u)
                joints = None
                if record.joint_rows is not None:  # what pybullet's step gave the rows counts against their bounds
                    applied = (applied_impulses(record.joint_rows, self.adapter.motor_torques, self.dt)
                               + constraint_impulses(record.joint_rows, record.constraints, self.adapter,
                                                     self.adapter.constraint_forces, self.dt))
                    joints = at_free_motion(record.joint_rows, u, applied)
            M = coupling.mass_matrix() if coupling.n else None
            guess = self._rigid_warm.guess(coupling) if coupling.n else None
            sol = self.contact_solver.solve(steps, self.dt, M, record.pairs, joints, guess)
            for _ in range(END_ROUNDS):  # contacts the start of the step could not see: solve again with them
                if not self._end_contacts(record, sol.velocities, sol.du):
                    break
                with timed(timings, "rigid"):
                    steps = self._body_steps(record, systems, supports, u)
                sol = self.contact_solver.solve(steps, self.dt, M, record.pairs, joints, sol.du)
            if coupling.n:
                self._rigid_warm.keep(coupling, sol.du)
            elif self._rigid_warm.kept:  # none coupled: forgotten, a body coming back starts from 0
                self._rigid_warm.kept = {}
        record.joints = joints
        record.solution = sol
        return sol.velocities

    def step(self) -> None:
        """Advance the whole scene by dt (pybullet steps exactly once)."""
        self.adapter.invalidate()  # the user may have moved bodies since the last step
        self.adapter.caching = True  # within the step only pybullet's step and this World move them
        try:
            self._step()
        finally:
            self.adapter.caching = False
            self.adapter.invalidate()

    def _step(self) -> None:
        """One step, top to bottom: sync the rigid scene, collide, build the contact problem, let pybullet step,
        solve the soft bodies' systems with the contact problem, commit, check; then publish the report."""
        h = self.dt
        record = StepRecord(self.t, self._stepped_now(), h)
        timings = record.timings
        with timed(timings, "collision"):
            self._sync()
            self._script_velocities(record.t)
            self._collide(record)
        with timed(timings, "rigid"):
            self._build_problem(record)
            snapshot = self.adapter.snapshot({k[0] for k, rb in self.rigids.items()
                                              if rb.movable or k[0] in self._one_way})
            for b, lk, f, x in self._lagged:
                self.adapter.apply_force(b, lk, f, x)
            self.adapter.step()
            self._check_motors(record)
        try:
            with timed(timings, "other"):  # the FEM step's own phases (factorize, solve, ...) nest in it
                new = self.sim.solve_step(
                    lambda _bodies, systems, supports, _t: self._solve_velocities(record, systems, supports),
                    timings)
            with timed(timings, "rigid"):
                du = record.solution.du if record.solution is not None else np.zeros(0)
                coupling = record.coupling
                for b, dyn in coupling.dynamics.items():
                    o = coupling.offset[b]
                    if np.any(du[o:o + dyn.n]):
                        self.adapter.change_velocity(dyn, du[o:o + dyn.n], h)
                self._check_energy(new)
        except BaseException:
            self.adapter.restore_snapshot(snapshot)
            raise
        with timed(timings, "rigid"):
            self.sim.commit(new)
            for e in self._entries:
                e.started = True
            for rb in self.rigids.values():
                if rb.motion is not None:
                    pos, orn = rb.scripted_pose(self.t)
                    self.adapter.reset_pose(rb.id, pos.tolist(), orn.tolist())
            self._check_missed()
            self._check_intersections(record)
            self._check_rigid_intersections()
            self._lagged = self._one_way_reactions(record)
        if not record.in_contact:  # the contact solve's own time is the FEM step's then
            timings["other"] = timings.get("other", 0.0) + timings.pop("contact", 0.0)
        self.report = StepReport.of(record, [e.place for e in self._entries])

    def _script_velocities(self, t: float) -> None:
        """The kinematic links' velocities over the step from t, from their scripted poses."""
        h = self.dt
        for rb in self.rigids.values():
            if rb.motion is not None:
                p0, q0 = rb.scripted_pose(t)
                p1, q1 = rb.scripted_pose(t + h)
                dq = quat_difference(q0, q1)
                angle = 2 * math.atan2(np.linalg.norm(dq[:3]), dq[3])
                axis = dq[:3] / max(np.linalg.norm(dq[:3]), 1e-300)
                self._kin_velocity[rb.id] = ((p1 - p0) / h, axis * angle / h)

    def _collide(self, record: StepRecord) -> None:
        """The contact search at the start of the step, into the record: soft nodes and faces against rigid
        links, soft bodies against each other; bodies new since the last step checked for overlaps."""
        self.detector.last_candidates = 0
        record.detected = detected = [self._detect(i) for i in range(len(record.bodies))] if self.rigids else []
        record.candidates = Contacts.concat([d[0] for d in detected])
        record.face_hits = FaceHits.concat([d[1] for d in detected])
        self._detect_soft(record)
        fresh = [k for k, e in enumerate(self._entries) if not e.started]  # bodies added since the last step
        if fresh:
            self._check_overlaps(record, fresh)

    def _build_problem(self, record: StepRecord) -> None:
        """The step's contact problem, into the record: the movable rigid bodies in play (their mass matrices and
        Jacobians at the start configuration, before pybullet moves them), each body's node and face contacts and
        coupled attachments, the soft contacts, the moving links' start poses."""
        c, f = record.candidates, record.face_hits
        in_play = set(c.rigid.tolist()) | set(f.rigid.tolist()) | {a.rigid.id for a in self.attachments if a.coupled}
        movable = {k[0] for k, rb in self.rigids.items() if rb.movable} if in_play else set()
        in_play &= movable
        constraints = self.adapter.user_constraints() if in_play else []
        grown = bool(constraints)
        while grown:  # the bodies a user constraint joins to a body in play join it
            grown = False
            for uc in constraints:
                if uc.coupled and in_play & set(uc.bodies):
                    more = {b for b in uc.bodies if b not in in_play and b not in self._one_way
                            and (b in movable or self.adapter.movable(b))}
                    in_play |= more
                    grown |= bool(more)
        dynamics = {b: self.adapter.dynamics(b) for b in sorted(in_play)}
        record.coupling = coupling = RigidCoupling.of(dynamics)
        if dynamics:  # what acts on their joints and between them: rows on their velocities
            record.joint_rows = JointRows.concat([
                joint_rows(coupling, self.motors.of(dynamics), {b: self.adapter.joint_limits(b) for b in dynamics},
                           self.dt),
                constraint_rows(constraints, coupling, self.adapter, self.dt, self._one_way)], coupling.n)
            record.constraints = constraints
            self._check_constraints(dynamics, constraints)
        self._group_dense(record)
        for i, (found, hits) in enumerate(record.detected):
            if len(found):
                record.contacts[i] = self._node_contacts(i, found, coupling)
            if len(hits):
                record.faces[i] = self._face_contacts(i, hits, coupling)
        for i in range(len(record.bodies)):
            record.attachments[i] = self._coupled_attachments(i, coupling)
        record.pairs = self._pair_contacts(record.soft_hits, record.edge_hits)
        if record.bodies:  # the moving links' poses at the start, for contacts found at the end of the step
            record.poses0 = {rb.key: rb.pose() for rb in self.rigids.values() if rb.movable or rb.motion is not None}

    def _check_overlaps(self, record: StepRecord, fresh: list[int]) -> None:
        """At a soft body's first step: refuse it placed deeper than half its smallest size inside a rigid link
        (no surface to push it out through) or overlapping another soft body (two overlapping meshes have no
        trustworthy way out: the nearest faces of the one inside the other may be its sides), and warn that a
        shallower overlap with a rigid link is pushed out at ``push_speed``."""
        margin, c = self.contact_margin, record.candidates
        for i in fresh:
            entry = self._entries[i]
            body = entry.body
            extent = float(np.ptp(body.positions, axis=0).min())
            where, first = entry.place
            mine = (c.body == where) & (c.node >= first) & (c.node < first + body.n_nodes)
            sel = mine & (c.distance < -margin)
            overlaps = []
            if sel.any():
                k = np.flatnonzero(sel)[np.argmin(c.distance[sel])]
                rb = self.rigids[(int(c.rigid[k]), int(c.link[k]))]
                overlaps.append((-float(c.distance[k]), f"rigid body {rb.name!r}", 0.5 * extent))
            for a, b in self._soft_pairs():
                if i not in (a, b) or a == b or (a != i and a in fresh):  # each pair once
                    continue
                j = b if a == i else a
                other = self._entries[j]
                reach = max(extent, float(np.ptp(other.body.positions, axis=0).min()))
                data = [(x.body.positions, np.zeros_like(x.body.positions), x.surface, x.body.rest)
                        for x in (entry, other)]
                d = soft_contacts(data, [(0, 1)], margin, self.dt, reach).distance
                if len(d) and d.min() < -margin:
                    overlaps.append((-float(d.min()), f"soft body {j}", margin))
            for depth, what, limit in overlaps:
                if depth > limit + 1e-12:
                    raise InvalidInputError(
                        f"soft body {i} starts {1e3 * depth:.1f} mm inside {what}: more than can be pushed out "
                        f"({1e3 * limit:.1f} mm); place it outside (or less deep) before the first step")
                self._warn_once(("overlap", i, what), f"soft body {i} starts {1e3 * depth:.1f} mm inside "
                                f"{what}: it is pushed out at up to {self.contact_solver.push_speed} m/s (push_speed)")

    def _check_missed(self) -> None:
        """After a step: a fast rigid link that ended inside a soft body was not caught within the step (its
        contacts are linearised at the start of the step); say so once, with its speed."""
        for i, e in enumerate(self._stepped):
            body = e.body
            surface = e.surface.nodes
            surface = surface[~body.supported()[surface]]  # supports win over contact
            for rb in self.rigids.values():
                if not (rb.movable or rb.motion is not None) or e.ignores(rb):
                    continue
                sweep = self._sweep(rb, body.velocities)
                if sweep.rigid_travel() <= self.contact_margin:
                    continue  # slow: its contacts are the start's, exact to the margin
                found = self.detector.node_contacts(i, body.positions, surface, rb, self.contact_margin)
                depth = -float(found.distance.min(initial=0.0))
                if depth > MISSED:
                    k = self._member(i, int(found.node[np.argmin(found.distance)]))
                    speed = float(np.linalg.norm(sweep.v))
                    self._warn_once(("missed", k, rb.key), (
                        f"rigid body {rb.name!r} moving at {speed:.3g} m/s (spinning at {np.linalg.norm(sweep.w):.3g} "
                        f"rad/s) ended {1e3 * depth:.1f} mm inside soft body {k} at t = {self.t:.4g} s: its contact "
                        f"was not caught within the step of {self.dt} s (it travels {1e3 * speed * self.dt:.0f} mm "
                        "per step); it is pushed out over the next steps. A smaller dt catches it."))

    def _check_intersections(self, record: StepRecord) -> None:
        """After a step: two soft bodies whose surfaces cross deeper than INTERSECTING (a geometric test,
        intersection.py, apart from the contact search) were not separated by their contacts; say so once per pair,
        naming both (bodies told not to collide are said to pass through at _detect_soft). Tested: every step the
        pairs whose contact candidates reach that deep, every CHECK_EVERY steps all pairs whose boxes overlap
        (crossings the search does not see at all)."""
        pairs = set()
        if len(record.soft_hits) or len(record.edge_hits):
            deep = np.concatenate([record.soft_hits.distance, record.edge_hits.distance]) < -INTERSECTING
            if deep.any():
                found = record.member_pairs[deep]
                pairs.update(map(tuple, np.sort(found, axis=1).tolist()))
        if self.sim.steps % CHECK_EVERY == 0:
            boxes = [self._box(k) for k in range(len(self._entries))]
            pairs.update((a, b) for a, b in self._soft_pairs() if a != b and np.all(boxes[a][0] <= boxes[b][1])
                         and np.all(boxes[b][0] <= boxes[a][1]))
        for a, b in sorted(pairs):
            if a == b or ("intersect", a, b) in self._warned:
                continue
            ea, eb = self._entries[a], self._entries[b]
            sa, sb = ea.surface, eb.surface
            depth = intersection_depth(ea.body.positions, sa.triangles, sa.edges, eb.body.positions, sb.triangles,
                                       sb.edges)
            if depth > INTERSECTING:
                self._warn_once(("intersect", a, b), (
                    f"soft bodies {a} and {b} intersect {1e3 * depth:.2f} mm deep at t = {self.t:.4g} s: their "
                    "contacts did not separate them (both held or moved by supports, or a crossing deeper than the "
                    f"contact search reaches, {1e3 * SOFT_DEPTH * self.contact_margin:.1f} mm); they may pass "
                    "through each other"))

    def _check_rigid_intersections(self) -> None:
        """After every CHECK_EVERY-th step: a soft body and a rigid link (boxes overlapping, not ignored) that
        cross deeper than INTERSECTING were not separated by their contacts; say so once per pair, naming both.
        Measured apart from the contact search's rows: the exact signed distance of the soft surfaces' free nodes
        to the link's shapes (one query per link for all bodies near it), and, for shapes with a closed surface
        (RigidShape.closed_surface: all but planes and open meshes), segment against triangle both ways
        (intersection.py), so that a rigid edge through a soft face between its nodes shows too, less what the
        soft surface's chords sag through a round part they rest on by both ends (RigidShape.chord_sag: the
        mesh's discretisation, not modelled). A link holding supported nodes inside it (an embedded clamp) is
        checked by its free nodes only."""
        if self.sim.steps % CHECK_EVERY or not self.rigids or not self._members:
            return
        members = self._members
        surfs = [e.surface for e in self._entries]
        boxes = [self._box(k) for k in range(len(members))]
        lo, hi = np.array([b[0] for b in boxes]) - INTERSECTING, np.array([b[1] for b in boxes]) + INTERSECTING
        for rb in self.rigids.values():
            rlo, rhi = (np.asarray(v, float) for v in rb.aabb())
            near = [k for k in np.flatnonzero(np.all(lo <= rhi, axis=1) & np.all(hi >= rlo, axis=1)).tolist()
                    if ("rigid intersect", k, rb.key) not in self._warned and not self._entries[k].ignores(rb)]
            if not near:
                continue
            nodes = [surfs[k].nodes for k in near]
            x = np.concatenate([members[k].positions[n] for k, n in zip(near, nodes)])
            held = np.concatenate([members[k].supported()[n] for k, n in zip(near, nodes)])
            if rb.primitive_parts() is not None:
                dist = primitive_distances(rb, rb.primitive_parts(), x)[2]
            else:  # a mesh: pybullet's query, body by body
                dist = np.full(len(x), np.inf)
                at = np.cumsum([0] + [len(n) for n in nodes])
                for k, n, a in zip(near, nodes, at[:-1]):
                    found = self.detector.node_contacts(k, members[k].positions, n, rb, INTERSECTING)
                    dist[a + np.searchsorted(n, found.node)] = found.distance
            which = np.repeat(np.arange(len(near)), [len(n) for n in nodes])
            deep = np.zeros(len(near))
            np.maximum.at(deep, which[~held], -dist[~held])
            clamped = np.zeros(len(near), dtype=bool)
            clamped[which[held & (dist < -INTERSECTING)]] = True
            closed = [part for part in rb.parts if part.shape.closed_surface is not None]
            for r, k in enumerate(near):
                depth = float(deep[r])
                if depth <= INTERSECTING and closed and not clamped[r]:
                    c, q = rb.pose()
                    Rl = quat_matrix(q)
                    xk = members[k].positions
                    e = surfs[k].edges
                    gap = np.full(len(xk), np.inf)  # the surface nodes' distances to the link
                    gap[nodes[r]] = dist[which == r]
                    lengths = np.sqrt(((xk[e[:, 1]] - xk[e[:, 0]]) ** 2).sum(axis=1))
                    ends = np.maximum(gap[e[:, 0]], gap[e[:, 1]]) - self.contact_margin - INTERSECTING
                    for part in closed:
                        v, tris, edges = part.shape.closed_surface
                        xr = (v @ part.rotation.T + part.position) @ Rl.T + c
                        crossed = intersection_depth(xr, tris, edges, xk, surfs[k].triangles, e)
                        if crossed > INTERSECTING:  # less the sag of the chords whose ends are close enough to dip
                            sag = part.shape.chord_sags(lengths)
                            crossed -= float(np.max(sag[ends <= sag], initial=0.0))
                        depth = max(depth, crossed)
                if depth > INTERSECTING:
                    hint = ("; a coarse soft surface's facets dip through a round part next to the nodes resting on "
                            "it (not modelled): a finer mesh dips less" if any(any(part.shape.round) for part in
                                                                                rb.parts) else "")
                    self._warn_once(("rigid intersect", k, rb.key), (
                        f"rigid body {rb.name!r} and soft body {k} intersect {1e3 * depth:.2f} mm deep (beyond "
                        f"the mesh's sag over round parts) at t = {self.t:.4g} s: their contacts did not separate "
                        "them (a feature the contact search does not model, see docs/contact.md 'What is not "
                        f"modelled', or a body driven through the other); they may pass through each other{hint}"))

    def _check_motors(self, record: StepRecord) -> None:
        """Warn once per body when a motor the World does not know (set in pybullet directly, or pybullet's default
        velocity motor) acted on a joint of a body in the coupled problem: it ran in pybullet's step, before the
        soft contacts, which the coupled solve then adds as if the joint were free."""
        for b, dyn in record.coupling.dynamics.items():
            unknown = [j for j in dyn.joints if self.motors.get(b, j) is None]
            if not unknown or ("motor", b) in self._warned:
                continue
            torques = self.adapter.motor_torques(b, unknown)
            acting = [j for j, t in zip(unknown, torques.tolist()) if abs(t) > 1e-9]
            if acting:
                self._warn_once(("motor", b), f"body {b} ({self.adapter.body_name(b)!r}): the motors of joints "
                                f"{acting} were set in pybullet directly (or are pybullet's default velocity motors) and "
                                "act in pybullet's step, before the soft contacts: in soft contact they push with "
                                "less than their force limit (about m kp (q - q*) / dt^2 for a position motor, so "
                                "a grip depends on dt). Set them with World.set_motor to make them rows of the "
                                "coupled problem, or give them force=0 to leave the joints free")

    def _check_constraints(self, dynamics: dict[int, BodyDynamics], constraints: list) -> None:
        """Warn once when a coupled body is held by a user constraint the coupled solve does not hold (a kind other
        than point-to-point, fixed and gear, or joining a body it cannot move)."""
        for uc in constraints:
            if not any(b in dynamics for b in uc.bodies):
                continue
            if not uc.coupled:
                self._warn_once(("constraint", uc.id), f"pybullet constraint {uc.id} (joint type {uc.kind}) holds "
                                f"bodies {uc.bodies}: the coupled solve holds point-to-point, fixed and gear "
                                "constraints only, so it treats the bodies as free and pybullet enforces this one in "
                                "its next step")
            elif set(uc.bodies) & self._one_way:
                self._warn_once(("constraint", uc.id), f"pybullet constraint {uc.id} joins bodies {uc.bodies}, one of "
                                "which has spherical or planar joints the coupled solve cannot move: the constraint "
                                "stays pybullet's alone, enforced in its next step")

    def _one_way_reactions(self, record: StepRecord) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
        """Reactions on bodies the coupled solve cannot move (unsupported joints), for pybullet's next step."""
        lagged = self._one_way
        sol = record.solution
        if not lagged or sol is None:
            return []
        out = []
        solved = [(record.contacts[i], r) for i, r in enumerate(sol.contacts) if r is not None]
        solved += [(record.faces[i], r) for i, r in enumerate(sol.faces) if r is not None]
        for c, res in solved:
            for i in np.flatnonzero(res.active & np.isin(c.rigid, list(lagged))):
                out.append((int(c.rigid[i]), int(c.link[i]), -res.force[i], c.point[i]))
        return out

    # ------------------------------------------------------------------ energy and forces
    def energy(self, states: list[tuple[np.ndarray, np.ndarray]] | None = None) -> dict[str, float]:
        """The scene's energies [J]: soft kinetic, elastic and gravitational potential, rigid (movable
        bodies) kinetic and gravitational potential (zero at the world origin), and their total.

        states: the soft bodies' (positions, velocities) to evaluate (default: their current state)."""
        self._sync()
        g = self.gravity
        soft_k = soft_e = soft_p = 0.0
        stepped = self.sim.bodies if states else self._stepped_now()  # their sums are the members'
        for body, (x, v) in zip(stepped, states or [(b.positions, b.velocities) for b in stepped]):
            soft_k += body.kinetic_energy(v)
            soft_e += body.elastic_energy(x)
            soft_p += body.gravitational_energy(g, x)
        rig_k = rig_p = 0.0
        for rb in self.rigids.values():
            if not rb.movable:
                continue
            c, q, v, w = self.adapter.state(rb.id, rb.link)
            m, I = self.adapter.inertia(rb.id, rb.link)
            R = quat_matrix(q)
            rig_k += 0.5 * m * float(v @ v) + 0.5 * float(w @ ((R * I) @ R.T) @ w)
            rig_p -= m * float(c @ g)
        total = soft_k + soft_e + soft_p + rig_k + rig_p
        return {"soft_kinetic": soft_k, "elastic": soft_e, "soft_potential": soft_p, "rigid_kinetic": rig_k,
                "rigid_potential": rig_p, "total": total}

    def _check_energy(self, new: list[tuple[np.ndarray, np.ndarray]]) -> None:
        if self.max_energy is None:
            return
        e = self.energy(new)
        if e["total"] > self.max_energy:
            raise SimulationDiverged(
                f"the scene's energy {e['total']:.4g} J exceeds the bound max_energy = {self.max_energy:.4g} J at step "
                f"{self.sim.steps + 1} (t = {self.t + self.dt:.6g} s): soft kinetic {e['soft_kinetic']:.3g}, elastic "
                f"{e['elastic']:.3g}, rigid kinetic {e['rigid_kinetic']:.3g} J. State kept at t = {self.t:.6g} s; "
                "try a smaller dt or more damping.", step=self.sim.steps + 1, time=self.t + self.dt)

    def contact_force(self, body_id, link: int | None = None, soft: FemBody | None = None) -> np.ndarray:
        """The total force (3,) [N] the soft bodies exerted on rigid body ``body_id`` (a RigidLink or an id;
        all its links, or one ``link``) over the last step: contacts and attachments. ``soft``: only the
        force of that soft body (one added with :meth:`add_soft`)."""
        if isinstance(body_id, RigidLink):
            body_id, link = body_id.id, body_id.link if link is None else link
        member = next((k for k, b in enumerate(self._members) if b is soft), None)
        if soft is not None and member is None:
            raise InvalidInputError("soft must be a soft body of this World (added with add_soft)")
        total = np.zeros(3)
        results = [*self.contact_results.items(), *self.face_results.items()]
        places = self.report.places
        if soft is not None:
            if member >= len(places):  # added after the last step
                return total
            key_of, first = places[member]  # the stepped body it was in at the last step
            alone = sum(w == key_of for w, _ in places) == 1
        for key, (c, res) in results:
            if soft is not None and key != key_of:
                continue
            sel = res.active & (c.rigid == body_id)
            if soft is not None and not alone:  # a stack: the contacts on the soft body's nodes
                node = c.nodes[:, 0] if isinstance(c, FaceContacts) else c.node
                sel &= (node >= first) & (node < first + soft.n_nodes)
            if link is not None:
                sel &= c.link == link
            total -= res.force[sel].sum(axis=0)
        for att, f in self.attachment_forces:
            if att.rigid.id == body_id and (link is None or att.rigid.link == link) and soft in (None, att.body):
                total -= f.sum(axis=0)
        return total

    def run(self, duration: float, callback: Callable[["World"], object] | None = None,
            progress: bool = False) -> None:
        """Step for ``duration`` [s], calling ``callback(world)`` after each step; progress bar on request."""
        run_steps(self.step, self.dt, duration, None if callback is None else lambda: callback(self), progress)

    # ------------------------------------------------------------------ saved states
    def _layout(self) -> list[tuple[int, ...]]:
        """Each stepped body as the tuple of its members' handles (indices in ``bodies``)."""
        return [tuple(e.members) for e in self._stepped]

    def save_state(self, path: str | Path | None = None) -> WorldState:
        """Everything the next steps read, copied: the soft bodies' state and solvers' (softbody.state), pybullet's
        world (its saveBullet), the contacts' warm starts and friction states, the stacking, the reactions lagged to
        the next step and the last step's results. Continuing after :meth:`restore_state` of it is the same to the
        bit as continuing now. ``path``: also write it there (``state.write(path)`` does the same later)."""
        layout = self._layout()
        handle = {e.body: h for e, h in zip(self._stepped, layout)}  # the contact solver's keys -> handles
        members = {e.body: (k,) for k, e in enumerate(self._entries)}  # the convex islands' bodies (a stack's members)
        previous = {(kind, key if kind == "soft" else handle[key]): copy.deepcopy(value)
                    for (kind, key), value in self.contact_solver.previous.items()
                    if kind == "soft" or key in handle}
        state = WorldState(self.sim.save_state(), self._scene_summary(), len(self.attachments), layout,
                           {k: e.group for k, e in enumerate(self._entries) if e.group is not None},
                           self._restack_due, [k for k, e in enumerate(self._entries) if e.started],
                           previous, copy.deepcopy(self._lagged), copy.deepcopy(self.report), self.adapter.save_world(),
                           patterns=self.contact_solver.convex.patterns.save_state(
                               lambda b: handle.get(b, members.get(b))),
                           rigid_warm=copy.deepcopy(self._rigid_warm.kept))
        if path is not None:
            state.write(path)
        return state

    def _scene_summary(self) -> dict:
        """What a saved state must find again to restore into this World: the soft bodies' node counts, the time step
        and gravity, pybullet's bodies (ids, names, joint counts)."""
        ad = self.adapter
        return {"members": [m.n_nodes for m in self._members], "dt": self.dt, "gravity": tuple(map(float, self.gravity)),
                "rigid": [(b, ad.body_name(b), ad.num_links(b)) for b in ad.body_ids()]}

    def _check_restorable(self, state: WorldState) -> list[list[int]]:
        """Raise InvalidInputError naming what differs unless ``state`` was saved from this scene; returns the saved
        stepping as groups of members. Changes nothing."""
        have, want = self._scene_summary(), state.scene
        what = []
        if have["members"] != want["members"]:
            what.append(f"soft bodies of {want['members']} nodes saved, {have['members']} here")
        if len(self.attachments) != state.attachments:
            what.append(f"{state.attachments} attachments saved, {len(self.attachments)} here")
        if have["dt"] != want["dt"] or have["gravity"] != want["gravity"]:
            what.append(f"dt {want['dt']:g} s and gravity {want['gravity']} saved, dt {have['dt']:g} s and gravity "
                        f"{have['gravity']} here")
        if have["rigid"] != want["rigid"]:
            what.append(f"pybullet bodies (id, name, links) {want['rigid']} saved, {have['rigid']} here")
        groups = [list(h) for h in state.layout] if not what else []
        for g in groups:
            keys = {self._stack_key(self._entries[k]) for k in g}
            if len(g) > 1 and (not self._stack or len(keys) > 1):
                what.append(f"soft bodies {g} were stepped as one stack, here they "
                            "differ in what a stack shares (element kind, material, damping, friction, ignored links) "
                            "or stacking is off")
                break
        if what:
            raise InvalidInputError("the saved state is of another scene: " + "; ".join(what) + ". Build the same "
                                    "scene (the same rigid bodies loaded, the same soft bodies added in the same order, "
                                    "with the same settings) before restoring; nothing was changed")
        return groups

    def restore_state(self, state: WorldState | str | Path) -> None:
        """Go back to a state of :meth:`save_state`, or read one from its path (also in a new process, with the same
        scene built: the same rigid bodies loaded and soft bodies added in the same order). Loads, motor targets,
        constraints and settings stay as they are now (the scene, not its state). A state of another scene is refused
        with what differs, and the World is left as it was."""
        if isinstance(state, (str, Path)):
            state = read_state(state, WorldState)
        if not isinstance(state, WorldState):
            raise InvalidInputError(f"restore_state takes a WorldState or its path, got {type(state).__name__}")
        self._sync()
        groups = self._check_restorable(state)
        backup = self.save_state()
        try:
            self._apply_state(state, groups)
        except BaseException:
            self._apply_state(backup, [list(h) for h in backup.layout])
            raise

    def _apply_state(self, state: WorldState, groups: list[list[int]]) -> None:
        """Restore ``state`` (checked by :meth:`_check_restorable`, which gave ``groups``)."""
        self.adapter.restore_world(state.bullet, fresh=self.sim.steps == 0 and not any(e.started for e in self._entries))
        for k, e in enumerate(self._entries):
            e.group = state.dense_group.get(k)
            e.started = k in state.started
        self._apply_layout(groups)
        self._restack_due = state.restack_due
        self.sim.restore_state(state.sim)
        for s in self.sim.bodies:
            if isinstance(s, BodyStack):
                s.gather()
        stepped = {h: s for h, s in zip(self._layout(), self.sim.bodies)}
        self.contact_solver.previous = {(kind, key if kind == "soft" else stepped[key]): copy.deepcopy(value)
                                        for (kind, key), value in state.previous.items()}
        self.contact_solver.convex.patterns.load_state(  # a stepped body, or a stack's member (an island's unit)
            state.patterns, lambda h: stepped[h] if h in stepped else self._entries[h[0]].body)
        self._rigid_warm.kept = copy.deepcopy(getattr(state, "rigid_warm", {}))  # (none in states saved before it)
        self._lagged = copy.deepcopy(state.lagged)
        self.report = copy.deepcopy(state.results)

    __deepcopy__ = not_copyable("a pybullet client and the soft bodies' solver factorisations", "World")
    __reduce_ex__ = not_copyable("a pybullet client and the soft bodies' solver factorisations", "World")

    # ------------------------------------------------------------------ diagnostics
    def max_penetration(self) -> float:
        """Deepest penetration [m] of any soft surface node into any rigid link at the current positions."""
        worst = 0.0
        self._stepped_now()
        for i, e in enumerate(self._stepped):
            body = e.body
            surface = e.surface.nodes
            surface = surface[~body.supported()[surface]]
            for rb in self.rigids.values():
                if e.ignores(rb):
                    continue
                c = self.detector.node_contacts(i, body.positions, surface, rb, 1e-3)
                if len(c):
                    worst = max(worst, float(-c.distance.min()))
        return worst
