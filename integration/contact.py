"""Unilateral contact with Coulomb friction inside the implicit step.

Each contact is a condition on the velocity, at the end of the step, of one soft point (a node, or a
point of a surface triangle with barycentric weights), in a frame (n, t1, t2) with n the rigid's
outward normal:

    non-penetration   n . (v - v_rigid) >= -d / h      (the gap d closes to zero, never below)
    separation        the normal force lam must be >= 0, else the contact is released
    Coulomb friction  stick: t . (v - v_rigid) = 0 while |f_t| <= mu lam;
                      slip: a force mu lam opposite to the sliding direction.

An active-set loop solves the step systems of all soft bodies exactly under the current set, releases
pulling contacts, adds violated ones and switches stick/slip until nothing changes. A contact at a node
is eliminated in the node's frame (softbody.integrator); a contact at a point of a triangle is a
constraint row with a multiplier (coupling.py). Changing only the slip forces reuses the factorisation.

A contact or attachment on a link of a movable rigid body moves with that body, whose velocity
change du is found in the same solve (coupling.py): v_rigid = v_free + J du, with J the point
Jacobian of the rigid material point. Attachments hold all three components of a node to the rigid
point (bilateral, never released).
"""
from __future__ import annotations

import dataclasses
import operator
from dataclasses import dataclass, field

import numpy as np

from softbody.integrator import Constraints, LinearSystem

from . import kernels
from .collision import barycentric, closest_on_triangles
from .convex import ConvexSolver, JointRows, Rows as ConvexRows, SoftPart
from .coupling import CoupledPart, CoupledSolver, Rows
from .islands import Islands, components
from .distance import cross


# cosine above which two face contacts of one rigid point hold the same face (nearly the same constraint)
SAME_FACE = 0.9
# penetration [m] a soft contact leaves where it is (_ContactSet.tolerate)
SOFT_SLOP = 5e-5
# a rigid point counts on a soft triangle in the convex problem while it lies over it to within this fraction of
# the triangle beyond its edges (barycentric coordinates >= -FACE_BAND)
FACE_BAND = 0.02


def _in_set(keys: np.ndarray, members: set | dict) -> np.ndarray:
    """(m,) bool: which keys (m,) are in the set (or are keys of the dict) (np.isin's sort costs more at the usual
    tens of contacts)."""
    if not members:
        return np.zeros(len(keys), dtype=bool)
    return np.fromiter(map(members.__contains__, keys.tolist()), dtype=bool, count=len(keys))


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """Orthonormal frames (m, 3, 3) with the unit normals (m, 3) as first column."""
    F = np.empty((len(normals), 3, 3))
    if kernels.ENABLED:  # the same arithmetic, contact by contact (integration.kernels)
        kernels.tangent_frames(np.ascontiguousarray(normals, dtype=float), F)
        return F
    n = F[:, :, 0]  # lengths summed left to right, as the kernel does (einsum's order differs in the last bit)
    np.divide(normals, np.sqrt(normals[:, 0] * normals[:, 0] + normals[:, 1] * normals[:, 1]
                               + normals[:, 2] * normals[:, 2])[:, None], out=n)
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    # t1 = n x e_x (or n x e_y where n is nearly along x), normalised; t2 = n x t1
    along_x = np.abs(x) >= 0.9
    t1 = F[:, :, 1]
    t1[:, 0] = np.where(along_x, -z, 0.0)
    t1[:, 1] = np.where(along_x, 0.0, z)
    t1[:, 2] = np.where(along_x, x, -y)
    t1 /= np.sqrt(t1[:, 0] * t1[:, 0] + t1[:, 1] * t1[:, 1] + t1[:, 2] * t1[:, 2])[:, None]
    F[:, :, 2] = cross(n, t1)
    return F


@dataclass
class NodeContacts:
    """Per-node contact data for one soft body (one entry per node).

    node (m,), normal (m, 3), distance (m,), rigid_velocity (m, 3) [m/s] of the rigid material point
    (for a movable body: under its free motion over the step), mu (m,), rigid (m,) pybullet body id,
    point (m, 3), link (m,) link index (-1: base), jacobian (m, 3, n): velocity of the rigid point per
    unit of the coupled rigid velocity change du (None: nothing coupled); carried (m,) bool: the contact
    was found at the end of the step and carried back with the link, so its distance is no penetration
    (never undone at a bounded speed, see ContactSolver.push_speed); None: none is.
    """

    node: np.ndarray
    normal: np.ndarray
    distance: np.ndarray
    rigid_velocity: np.ndarray
    mu: np.ndarray
    rigid: np.ndarray
    point: np.ndarray
    link: np.ndarray | None = None
    jacobian: np.ndarray | None = None
    carried: np.ndarray | None = None

    def __post_init__(self):
        if self.link is None:
            self.link = np.full(len(self.node), -1, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.node)

    def select(self, keep: np.ndarray) -> "NodeContacts":
        return type(self)(*(None if getattr(self, f) is None else getattr(self, f)[keep]
                            for f in self.__dataclass_fields__))


@dataclass
class FaceContacts(NodeContacts):
    """Contacts at points of soft surface triangles (one entry per rigid point on a triangle).

    As NodeContacts, with node (m,) a key of the triangle and the rigid link (for the warm start of the
    next step), nodes (m, 3), weights (m, 3) the triangle's nodes and the point's barycentric weights,
    group (m,) the rigid point (one point may face several triangles), primary (m,) whether the point
    projects into the triangle at the start of the step (the others are neighbours it may cross into:
    they take part only if it does, see collision.FaceHits); edge (m,): the point lies on an edge (weights over
    its two nodes), where it holds whatever the triangles around do (None: none does)."""

    nodes: np.ndarray | None = None
    weights: np.ndarray | None = None
    group: np.ndarray | None = None
    primary: np.ndarray | None = None
    edge: np.ndarray | None = None


@dataclass
class PairContacts(NodeContacts):
    """Contacts between soft bodies (softcontact.py): as NodeContacts (node: the contact's key; rigid_velocity
    zero, rigid -1), with parts (m, 4) the indices of the step's soft bodies of the slots (a, b, b, b), nodes
    (m, 4) the node of a and the triangle's of b, weights (m, 4): 1 and minus the barycentric weights, so
    that a row's value is the normal velocity of a's node relative to b's triangle point."""

    parts: np.ndarray | None = None
    nodes: np.ndarray | None = None
    weights: np.ndarray | None = None

    def relabel(self, local: np.ndarray) -> "PairContacts":
        """The same contacts with parts mapped through ``local`` (array: old index -> new) (the other fields shared)."""
        return dataclasses.replace(self, parts=local[self.parts])


@dataclass
class Attachments:
    """Soft nodes held to material points of movable rigid links (all three components, bilateral).

    node (m,); target (m, 3): the node velocity [m/s] that puts it on its rigid point at the end of the step
    under the rigid's free motion; jacobian (m, 3, n): the point's velocity per unit of du; rigid (m,),
    link (m,): pybullet body and link; point (m, 3): the rigid points at the start of the step [m]."""

    node: np.ndarray
    target: np.ndarray
    jacobian: np.ndarray
    rigid: np.ndarray
    link: np.ndarray
    point: np.ndarray

    def __len__(self) -> int:
        return len(self.node)


@dataclass
class ContactResult:
    """Outcome of one contact solve: per contact entry, world force on the soft point [N], flags."""

    force: np.ndarray
    active: np.ndarray
    stick: np.ndarray
    iterations: int
    factorizations: int
    max_violation: float = 0.0
    extra: dict = field(default_factory=dict)


@dataclass
class BodyStep:
    """One soft body's part of a step: its step system, supports, node contacts, face contacts and
    coupled attachments."""

    system: LinearSystem
    supports: Constraints
    contacts: NodeContacts | None = None
    attachments: Attachments | None = None
    faces: FaceContacts | None = None


@dataclass
class StepSolution:
    """What the contact solve found: per body the velocities (N, 3), the node and face contact results
    (or None) and the attachment forces on the soft nodes (m, 3) [N] (or None); du (n,) the rigid
    velocity change; pairs: the soft contacts solved (in up to two parts, one per mode) with their results
    (force: on the node of body a [N]; body b takes minus its weights' share)."""

    velocities: list[np.ndarray]
    contacts: list[ContactResult | None]
    faces: list[ContactResult | None]
    attachment_forces: list[np.ndarray | None]
    du: np.ndarray
    iterations: int
    pairs: list[tuple["PairContacts", ContactResult]] = field(default_factory=list)
    joint_impulses: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (k,) [N s or N m s], of the joint rows


def _stack(parts: list[Constraints]) -> Constraints:
    """Constraint sets on disjoint nodes, one after the other (frames made explicit)."""
    parts = [c for c in parts if len(c)]
    if not parts:
        return Constraints.empty()
    if len(parts) == 1:
        return parts[0]
    eye = lambda c: c.frames if c.frames is not None else np.broadcast_to(np.eye(3), (len(c), 3, 3))  # noqa: E731
    return Constraints(np.concatenate([c.nodes for c in parts]), np.concatenate([c.mask for c in parts]),
                       np.concatenate([c.value for c in parts]), np.concatenate([eye(c) for c in parts]))


class _ContactSet:
    """The contacts of one kind on one soft body within one step's active-set loop: which are active,
    which stick, the sliding friction forces, and the switching rules of :class:`ContactSolver`.
    ``keys`` (m,) identify contacts from one step to the next (nodes, or triangles)."""

    def __init__(self, solver: "ContactSolver", c: NodeContacts, keys: np.ndarray, previous: tuple, h: float,
                 may_start: np.ndarray | None = None):
        self.solver, self.c, self.h = solver, c, h
        m = len(c)
        self.frames = tangent_frames(c.normal)
        # d(local rigid velocity) / d du: the point Jacobians in the contact frames
        self.G = None if c.jacobian is None else np.einsum("mji,mjn->min", self.frames, c.jacobian)
        prev_active, prev_stick, prev_slip = previous
        self.keys = keys
        was_active = _in_set(keys, prev_active)
        if kernels.ENABLED:  # the lines below, contact by contact (integration.kernels)
            self.vr_free, self.gap, self.target = np.empty((m, 3)), np.empty(m), np.empty((m, 3))
            self.active, self.friction, self.stick = np.empty((3, m), dtype=bool)  # three rows (views)
            kernels.contact_start(self.frames, np.ascontiguousarray(c.rigid_velocity, dtype=float), c.distance,
                                  np.ones(m, dtype=bool) if may_start is None else may_start,
                                  np.zeros(m, dtype=bool) if c.carried is None else c.carried, -solver.push_speed * h,
                                  h, c.mu, was_active, _in_set(keys, prev_stick), self.vr_free, self.gap, self.target,
                                  self.active, self.friction, self.stick)
        else:
            self._start(c, may_start, was_active, _in_set(keys, prev_stick), solver.push_speed)
        self.slip_force = np.zeros((m, 3))  # local frame, tangential components only
        carried = np.flatnonzero(_in_set(keys, prev_slip) & ~self.stick)
        if len(carried):  # last step's sliding friction, in this step's tangent plane
            f_prev = np.array([prev_slip[k] for k in keys[carried].tolist()])
            self.slip_force[carried, 1:] = np.einsum("mji,mj->mi", self.frames[carried], f_prev)[:, 1:]
        self.released = np.zeros(m, dtype=bool)  # a contact released once this step is not released again
        # a contact that stopped sliding in this step does not slip again in it (its want to is carried to the next
        # step, as switches past the cap are): near the cone's edge stick and slip took turns until the cap (a 31k-node
        # sheet through the impact: 12 solves a step where 7 settle it), and sticking does no work
        self.restuck = np.zeros(m, dtype=bool)
        # the sliding forces' fixed point goes on while their change shrinks: the change at the last read that changed
        # nothing else (inf: none; near the tolerance the velocities' round-off can turn it round, and it then grew
        # to the cap: a 72k-node sheet's impact step, 1e-3 of the forces at the 6th solve, 0.7 at the 12th)
        self.last_slip = np.array([np.inf])  # (not np.full: a Python frame, tests/test_step_cost.py)
        self.switches = solver.friction_switches  # iterations in which stick/slip may change (see ContactSolver)
        self.lock_after = 0  # iterations after which a released contact stays released
        self.factorizations = 0
        self.last_key = None
        self.reuse = False
        self.want_slip = self.want_stick = np.zeros(m, dtype=bool)
        self.rl = np.zeros((m, 3))
        self.gap_rate = np.zeros(m)
        self.mag = np.zeros((m, 1))
        self.d_stick = self.new_slip = np.zeros((m, 2))

    def _start(self, c: NodeContacts, may_start: np.ndarray | None, was_active: np.ndarray, in_stick: np.ndarray,
               push_speed: float) -> None:
        """The rigid velocities in the contact frames, the gaps to close, the targets and the starting state
        (numpy; kernels.contact_start does the same contact by contact)."""
        h = self.h
        self.vr_free = np.einsum("mji,mj->mi", self.frames, c.rigid_velocity)  # rigid velocity in (n, t1, t2)
        # the gap to close: a contact that may start active (a node, or a point on its own triangle) closes
        # its whole gap; a neighbour (its point not on that triangle yet) only keeps from penetrating further,
        # its distance to the triangle's extended plane being no penetration to undo
        gap = c.distance if may_start is None else np.where(may_start, c.distance, np.maximum(c.distance, 0.0))
        # a penetration (an overlap the scene started with, or a contact caught late) is undone at a bounded
        # speed, over as many steps as it takes, so that it adds no more than that speed's kinetic energy
        bounded = np.maximum(gap, -push_speed * h)
        self.gap = bounded if c.carried is None else np.where(c.carried, gap, bounded)
        self.target = self.vr_free.copy()
        self.target[:, 0] -= self.gap / h
        touching = c.distance <= 0 if may_start is None else (c.distance <= 0) & may_start
        self.active = touching | was_active
        self.friction = c.mu > 0
        self.stick = self.friction & (in_stick | ~was_active)

    def end_switching(self, it: int) -> None:
        """From the read of iteration ``it`` on, stick and slip no longer switch and the sliding forces no longer
        refine in this step: what they would do is carried to the next step, as past ``friction_switches``. Contacts
        are still added and released (non-penetration stays exact)."""
        self.switches = min(self.switches, it - 2)

    def tolerate(self, slop: float) -> None:
        """Leave penetrations up to ``slop`` [m] where they are (closing only what lies beyond): a contact
        between two deforming surfaces is linearised at the start of the step (normal and weights), so its
        end state is off by a little, and undoing that little each step would feed energy into the scene."""
        gap = np.where(self.gap < 0, np.minimum(self.gap + slop, 0.0), self.gap)
        self.target[:, 0] += (self.gap - gap) / self.h
        self.gap = gap

    def mask(self) -> np.ndarray:
        """(m, 3): the constrained local components (normal if active, tangents if also sticking)."""
        mask = np.zeros((len(self.c), 3), dtype=bool)
        mask[:, 0] = self.active
        mask[:, 1:] = (self.active & self.stick)[:, None]
        return mask

    def slipping(self) -> np.ndarray:
        return self.active & ~self.stick & self.friction

    def slip_impulse(self) -> np.ndarray | None:
        """Generalized impulse (n,) on the rigid side of the sliding friction (None if none or uncoupled)."""
        s = self.slipping()
        if self.G is None or not s.any():
            return None
        return -self.h * np.einsum("mk,mkn->n", self.slip_force[s], self.G[s])

    def update(self, rl: np.ndarray, v_soft: np.ndarray, du: np.ndarray, it: int,
               eligible: np.ndarray | None = None) -> bool:
        """Read a solve: the contact forces rl (m, 3) [N] and the soft points' velocities v_soft (m, 3) in the
        contact frames, du (n,); switch the set and return True if it changed. Only ``eligible`` (m,)
        contacts may be added."""
        s, c = self.solver, self.c
        vr_local = self.vr_free if self.G is None or not len(du) else self.vr_free + self.G @ du
        if kernels.ENABLED:  # the same rules and arithmetic, contact by contact (integration.kernels)
            return self._update_compiled(rl, v_soft - vr_local, it, eligible)
        lam = rl[:, 0]
        vrel = v_soft - vr_local
        gap_rate = vrel[:, 0] + self.gap / self.h
        active, stick = self.active, self.stick
        release = active & (lam < 0) & ~(self.released & (it > self.lock_after))
        add = ~active & (gap_rate < -s.velocity_tol)
        if eligible is not None:
            add &= eligible
        self.released |= release
        changed = release.any() or add.any()
        # friction: stick -> slip when the needed force leaves the cone; slip -> stick when sliding stops
        ft = rl[:, 1:]
        ftn = np.sqrt(np.einsum("mi,mi->m", ft, ft))
        switching = it <= self.switches
        want_slip = active & stick & (ftn > c.mu * np.maximum(lam, 0) * (1 + s.cone_tol))
        to_slip = switching & want_slip & ~self.restuck
        vt = vrel[:, 1:]
        vtn = np.sqrt(np.einsum("mi,mi->m", vt, vt))
        old = self.slip_force[:, 1:]
        reversed_ = np.einsum("mi,mi->m", vt, old) > 0  # sliding along the friction force: it stopped
        want_stick = active & ~stick & self.friction & (reversed_ | (vtn < s.velocity_tol))
        to_stick = switching & want_stick
        self.restuck |= to_stick
        new_slip = np.zeros((len(c), 2))
        d_stick = np.divide(ft, ftn[:, None], out=np.zeros_like(ft), where=ftn[:, None] > 0)  # the needed force's
        d_slip = np.divide(-vt, vtn[:, None], out=np.zeros_like(vt), where=vtn[:, None] > 0)  # direction; sliding's
        mag = (c.mu * np.maximum(lam, 0))[:, None]
        new_slip = np.where(to_slip[:, None], mag * d_stick, new_slip)
        cont = active & ~stick & self.friction & ~to_stick
        new_slip = np.where(cont[:, None], mag * d_slip, new_slip)
        change = float(np.abs(new_slip - old).max(initial=0.0))
        slip_change = change > s.slip_tol * max(1e-12, mag.max(initial=0.0))
        refine = it <= self.switches + 1  # slip forces: a bounded fixed-point iteration, while their change shrinks
        structural = bool(changed or to_slip.any() or to_stick.any())
        changed = structural or (refine and slip_change and cont.any() and change < self.last_slip[0])
        self.last_slip[0] = np.inf if structural else change
        self.rl, self.gap_rate, self.mag, self.d_stick, self.new_slip = rl, gap_rate, mag, d_stick, new_slip
        self.want_slip, self.want_stick = want_slip, want_stick
        if changed:
            self.active = (active & ~release) | add
            self.stick = (stick & ~to_slip) | to_stick
            self.slip_force[:, 1:] = np.where((to_slip | cont)[:, None], new_slip, 0.0)
            self.slip_force[~self.active] = 0.0
        return bool(changed)

    def _update_compiled(self, rl: np.ndarray, vrel: np.ndarray, it: int, eligible: np.ndarray | None) -> bool:
        """:meth:`update` by kernels.friction_update, from the relative velocities vrel (m, 3)."""
        s, m = self.solver, len(self.c)
        gap_rate, mag, d_stick, new_slip = np.empty(m), np.empty(m), np.empty((m, 2)), np.empty((m, 2))
        want_slip, want_stick, new_active, new_stick = np.empty((4, m), dtype=bool)  # four rows (views)
        changed = kernels.friction_update(
            rl, vrel, self.gap, self.h, self.active, self.stick, self.released, self.restuck, self.friction, self.c.mu,
            self.slip_force, np.ones(m, dtype=bool) if eligible is None else eligible, it, self.lock_after,
            self.switches, self.last_slip, s.velocity_tol, s.cone_tol, s.slip_tol, gap_rate, mag, d_stick, new_slip,
            want_slip, want_stick, new_active, new_stick)
        self.rl, self.gap_rate, self.mag, self.d_stick, self.new_slip = rl, gap_rate, mag[:, None], d_stick, new_slip
        self.want_slip, self.want_stick = want_slip, want_stick
        if changed:
            self.active, self.stick = new_active, new_stick
        return bool(changed)

    def result(self, iterations: int) -> tuple[ContactResult, tuple]:
        """The contact result of the final solve, and the friction state for the next step."""
        keys, active, stick, m = self.keys, self.active, self.stick, len(self.c)
        if kernels.ENABLED:  # the lines below, contact by contact (integration.kernels)
            force, slip_world = np.empty((m, 3)), np.empty((m, 3))
            next_stick, next_slip = np.empty(m, dtype=bool), np.empty(m, dtype=bool)
            kernels.contact_finish(self.frames, np.ascontiguousarray(self.rl, dtype=float), self.slip_force, active,
                                   stick, self.friction, self.want_slip, self.want_stick,
                                   np.ascontiguousarray(self.mag, dtype=float).reshape(m, 1),
                                   np.ascontiguousarray(self.d_stick, dtype=float),
                                   np.ascontiguousarray(self.new_slip, dtype=float), force, next_stick, next_slip,
                                   slip_world)
        else:
            force_local = np.where(active[:, None], self.rl, 0.0)
            slipping = active & ~stick & self.friction
            force_local[slipping, 1:] = self.slip_force[slipping, 1:]
            force_local[active & ~self.friction, 1:] = 0.0
            force = np.einsum("mij,mj->mi", self.frames, force_local)
            # friction state for the next step, including the switches this step did not make
            next_stick = active & self.friction & ((stick & ~self.want_slip) | self.want_stick)
            next_slip = active & self.friction & ~next_stick
            slip_local = np.zeros((m, 3))
            slip_local[:, 1:] = np.where(self.want_slip[:, None], self.mag * self.d_stick, self.new_slip)
            slip_world = np.einsum("mij,mj->mi", self.frames, slip_local)
        previous = (set(keys[active].tolist()), set(keys[next_stick].tolist()),
                    {int(k): f for k, f in zip(keys[next_slip], slip_world[next_slip])})
        viol = max(0.0, -float(self.gap_rate.min(initial=0.0)) * self.h)
        return ContactResult(force, active.copy(), stick & active, iterations, self.factorizations, viol), previous


class _NodeSet(_ContactSet):
    """Node contacts: eliminated in each node's contact frame."""

    def __init__(self, solver, c: NodeContacts, previous: tuple, h: float, n_nodes: int):
        super().__init__(solver, c, c.node, previous, h)
        self.n_nodes = n_nodes

    def constraints(self) -> tuple[Constraints, np.ndarray | None, np.ndarray | None]:
        """The active contacts as constraints (values at du = 0), their G rows, and the sliding friction as
        an extra right-hand side (N, 3) (None if nothing slides)."""
        c, h = self.c, self.h
        mask = self.mask()
        sel = mask[:, 0] | mask[:, 1] | mask[:, 2]
        cons = Constraints(c.node[sel], mask[sel], self.target[sel], self.frames[sel])
        key = (c.node[sel].tobytes(), mask[sel].tobytes())
        self.reuse = key == self.last_key
        self.factorizations += not self.reuse
        self.last_key = key
        extra = None
        slipping = self.slipping()
        if slipping.any():
            extra = np.zeros((self.n_nodes, 3))
            np.add.at(extra, c.node[slipping], h * np.einsum("mij,mj->mi", self.frames[slipping],
                                                             self.slip_force[slipping]))
        return cons, None if self.G is None else self.G[sel], extra

    def read(self, v: np.ndarray, r: np.ndarray, du: np.ndarray, it: int) -> bool:
        """Update from the body's solve: v (N, 3), reactions r (N, 3) in the contact frames."""
        nodes = self.c.node
        if kernels.ENABLED and (self.G is None or not len(du)):  # no rigid motion to add: one compiled pass
            rl, vrel = np.empty((len(nodes), 3)), np.empty((len(nodes), 3))
            kernels.node_read(np.ascontiguousarray(v, dtype=float), np.ascontiguousarray(r, dtype=float), nodes,
                              self.frames, self.h, self.vr_free, rl, vrel)
            return self._update_compiled(rl, vrel, it, None)
        return self.update(r[nodes] / self.h, np.einsum("mji,mj->mi", self.frames, v[nodes]), du, it)


class _RowSet(_ContactSet):
    """Contacts held by constraint rows with multipliers: points with weights (m, s) over nodes (m, s) of the
    soft bodies ``parts`` (m, s) (an int: all of one body); a node contact is a point with one weight of 1, a
    soft-soft contact a node of one body (weight 1) against a triangle point of another (minus its weights).
    sizes: {part: its number of nodes}."""

    def __init__(self, solver, c: NodeContacts, nodes: np.ndarray, weights: np.ndarray, parts, previous: tuple,
                 h: float, sizes: dict[int, int], may_start: np.ndarray | None = None):
        super().__init__(solver, c, c.node, previous, h, may_start)
        self.nodes, self.weights, self.sizes = nodes, weights, sizes
        self.parts = np.broadcast_to(np.asarray(parts, dtype=np.int64), nodes.shape)

    def rows(self, n: int, every: bool = False) -> tuple[Rows, dict[int, np.ndarray]]:
        """The active contacts' rows (values at du = 0) and the sliding friction as extra right-hand sides
        {part: (N, 3)} of the bodies (empty if nothing slides); remembers each row's (contact, axis). every:
        all three rows of every contact (contact-major), whatever the state."""
        c, h = self.c, self.h
        ci, ax = np.nonzero(np.ones((len(c), 3), dtype=bool) if every else self.mask())
        self.row_index = (ci, ax)
        direction = self.frames[ci, :, ax]
        g = np.einsum("mi,min->mn", direction, c.jacobian[ci]) if c.jacobian is not None and n else np.zeros((len(ci), n))
        rows = Rows(self.parts[ci], self.nodes[ci], self.weights[ci], direction, g, self.target[ci, ax])
        extra = {}
        slipping = self.slipping()
        if slipping.any():
            f = h * np.einsum("mij,mj->mi", self.frames[slipping], self.slip_force[slipping])
            parts, nodes, weights = self.parts[slipping], self.nodes[slipping], self.weights[slipping]
            for part in np.unique(parts).tolist():
                j, slot = np.nonzero(parts == part)
                e = np.zeros((self.sizes[part], 3))
                np.add.at(e, nodes[j, slot], weights[j, slot, None] * f[j])
                extra[part] = e
        return rows, extra

    def point_velocities(self, vs) -> np.ndarray:
        """(m, 3) the velocities sum_s w_s v[node_s] of the contact points, vs[part] (N, 3) each body's."""
        out = np.zeros((len(self.c), 3))
        for part in np.unique(self.parts).tolist():
            on = self.parts == part
            out += np.einsum("ms,msi->mi", np.where(on, self.weights, 0.0), vs[part][np.where(on, self.nodes, 0)])
        return out

    def read(self, vs, lam: np.ndarray, du: np.ndarray, it: int) -> bool:
        """Update from the bodies' velocities vs[part] (N, 3) and the impulses lam of this set's rows."""
        rl = np.zeros((len(self.c), 3))
        ci, ax = self.row_index
        rl[ci, ax] = lam / self.h
        v_point = self.point_velocities(vs)
        return self.update(rl, np.einsum("mji,mj->mi", self.frames, v_point), du, it, self.eligible(vs, du))

    def eligible(self, vs, du: np.ndarray, active: np.ndarray | None = None) -> np.ndarray | None:
        return None


class _FaceSet(_RowSet):
    """Contacts at points of one soft body's triangles, between their nodes."""

    def __init__(self, solver, c: FaceContacts, part: int, previous: tuple, h: float, positions: np.ndarray):
        super().__init__(solver, c, c.nodes, c.weights, part, previous, h, {part: len(positions)}, c.primary)
        self.part = part
        # one active contact per rigid point to start with (its primary, else the first)
        idx = np.flatnonzero(self.active)
        order = idx[np.lexsort((~c.primary[idx], c.group[idx]))]
        dup = np.zeros(len(order), dtype=bool)
        dup[1:] = c.group[order][1:] == c.group[order][:-1]
        self.active[order[dup]] = False
        self.x_tri = positions[c.nodes]  # (m, 3, 3) at the start of the step

    def eligible(self, vs, du: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
        """(m,) which contacts may be added after a solve with velocities vs[part] (N, 3) and du, given the
        contacts ``active`` (m,) in that solve (default: this set's own active set): those whose rigid
        point, at the end of the step, projects into its triangle and has it as the nearest of its group,
        one per rigid point and iteration, and none nearly parallel to an active contact of that point; a point on
        an edge (c.edge) always."""
        c, h = self.c, self.h
        x_end = self.x_tri + h * vs[self.part][c.nodes]
        vr = c.rigid_velocity if c.jacobian is None or not len(du) else c.rigid_velocity + c.jacobian @ du
        q_end = c.point + h * vr
        if kernels.ENABLED:  # the lines below, contact by contact (integration.kernels)
            first = np.empty(len(q_end), dtype=bool)
            kernels.face_eligible(np.ascontiguousarray(x_end, dtype=float), np.ascontiguousarray(q_end, dtype=float),
                                  c.group, np.ascontiguousarray(c.normal, dtype=float),
                                  self.active if active is None else active, SAME_FACE, first)
            return _or_edges(first, c)
        inside = (barycentric(q_end, x_end[:, 0], x_end[:, 1], x_end[:, 2]) >= -1e-9).all(axis=1)
        dist = np.linalg.norm(q_end - closest_on_triangles(q_end, x_end[:, 0], x_end[:, 1], x_end[:, 2]), axis=1)
        groups = int(c.group.max()) + 1
        nearest = np.full(groups, np.inf)
        np.minimum.at(nearest, c.group, dist)
        ok = inside & (dist <= nearest[c.group] + 1e-9)
        # a rigid point takes a second triangle only across a crease: none whose normal is within ~25 degrees
        # of an active contact's of the same point (their rows would be nearly the same), the first of ties
        act = np.flatnonzero(self.active if active is None else active)
        for g, nrm in zip(c.group[act], c.normal[act]):
            ok &= ~((c.group == g) & (c.normal @ nrm > SAME_FACE))
        first = np.zeros(len(ok), dtype=bool)
        idx = np.flatnonzero(ok)
        _, pick = np.unique(c.group[idx], return_index=True)
        first[idx[pick]] = True
        return _or_edges(first, c)


def _or_edges(eligible: np.ndarray, c: FaceContacts) -> np.ndarray:
    """The eligible face contacts (m,) and those on edges (FaceContacts.edge), which hold whatever the triangles
    around them do."""
    edge = getattr(c, "edge", None)
    return eligible if edge is None else eligible | edge


def _coupled(c: NodeContacts) -> np.ndarray:
    """(m,) which contacts move with a coupled rigid body (a Jacobian not zero)."""
    if c.jacobian is None or not c.jacobian.size:
        return np.zeros(len(c), dtype=bool)
    return np.abs(c.jacobian).reshape(len(c), -1).max(axis=1) > 0


def _groups(count: int, pairs: PairContacts | None) -> np.ndarray:
    """(count,) a label per body: bodies joined by soft contacts (directly or through others) share one."""
    label = np.arange(count)
    if pairs is None or not len(pairs):
        return label
    # the first slot is body a's, the last body b's (an edge-edge row's second slot is a's too); each group labelled by
    # its first body
    return components(count, pairs.parts[:, 0], pairs.parts[:, -1])


def _add_extras(extras: list, parts: dict[int, np.ndarray]) -> None:
    """Add extra right-hand sides {part: (N, 3)} into extras[part] (None: none yet)."""
    for part, e in parts.items():
        extras[part] = e if extras[part] is None else extras[part] + e


class ContactSolver:
    """Active-set solver for unilateral contacts with Coulomb friction, for all soft bodies of a step at
    once (coupled through movable rigid bodies and constraint rows, see coupling.py).

    max_iterations bounds the active-set loop; velocity_tol [m/s] is the threshold for adding contacts
    and for a slide to count as stopped; slip_tol the relative change of sliding forces that still
    counts as a change; cone_tol the relative slack of the friction cone before stick turns to slip;
    push_speed [m/s] the fastest a penetration is undone (deeper ones take several steps).
    """

    def __init__(self, max_iterations: int = 30, velocity_tol: float = 1e-7, slip_tol: float = 1e-3,
                 friction_switches: int = 10, cone_tol: float = 1e-3, push_speed: float = 0.5):
        self.max_iterations = max_iterations
        self.push_speed = push_speed
        self.velocity_tol = velocity_tol
        self.slip_tol = slip_tol
        # stick/slip may change only in the first friction_switches iterations of a step; later changes
        # are carried to the next step (a contact on the cone's edge would otherwise flip forever, and each
        # flip costs a solve). One switching iteration was too few: contacts that touched down sticking held
        # more than mu times their pressure for a step (a rolling ball: 4-7x Coulomb's bound, every step).
        # Non-penetration stays exact in every iteration.
        self.friction_switches = friction_switches
        self.cone_tol = cone_tol
        # (kind, body) -> (active keys, sticking keys, {slipping key: friction force (3,) world [N]})
        self.previous: dict[tuple[str, object], tuple[set, set, dict]] = {}
        # the coupled problem of bodies touching movable rigid bodies, each other or frictional faces (convex.py):
        # keeps its sparse patterns and their analyses from step to step
        self.convex = ConvexSolver()

    def _set(self, kind: str, body, c, make):
        if c is None or not len(c):
            self.previous[(kind, body)] = (set(), set(), {})
            return None
        return make(self.previous.get((kind, body), (set(), set(), {})))

    def solve(self, steps: list[BodyStep], h: float, mass_matrix: np.ndarray | None = None,
              pairs: PairContacts | None = None, joints: JointRows | None = None,
              du_guess: np.ndarray | None = None) -> StepSolution:
        """Solve one step of every body in ``steps``; ``mass_matrix`` (n, n): the movable rigid bodies' mass
        matrix for the coupled velocity change du (None: no rigid body is coupled); ``pairs``: contacts
        between the soft bodies (their parts index ``steps``); ``joints``: motors and joint limits of the coupled
        rigid bodies (convex.JointRows: rows of the convex problem, solved with it even where no soft body is);
        ``du_guess`` (n,): where the coupled solve starts du (coupling.RigidWarmStart; None: 0).

        A body in touch with a movable rigid body (a contact or attachment whose Jacobian is not zero) is
        solved in the coupled convex problem with all others like it (:meth:`_solve_convex`, convex.py); so are
        bodies in soft contact (with each other or themselves), whose contacts come and go as the surfaces slide
        over each other, and bodies with frictional face contacts: the convex problem settles stick and slip within
        the step, where the active set carries a contact's change to the next step. The others are solved by the
        active set on eliminated node contacts (:meth:`_solve_sparse`)."""
        n = 0 if mass_matrix is None else len(mass_matrix)
        prepared, dense, held_by = [], [], []
        for st in steps:
            held = st.supports.nodes
            cons, G = [st.supports], [np.zeros((len(st.supports), 3, n))]
            a = st.attachments
            if a is not None and len(a):  # supports win over attachments, both over contacts
                keep = ~np.isin(a.node, held)
                cons.append(Constraints.full(a.node[keep], a.target[keep]))
                G.append(a.jacobian[keep] if n else np.zeros((int(keep.sum()), 3, 0)))
                held = np.concatenate([held, a.node[keep]])
            c, f = st.contacts, st.faces
            if len(held) and ((c is not None and len(c)) or (f is not None and len(f))):
                is_held = np.zeros(st.system.body.n_nodes, dtype=bool)
                is_held[held] = True
                # a contact at a held node (or on a triangle of held nodes only) is held already, unless it holds a
                # movable rigid body (a box resting on a fixed rim: the support is a rigid surface to it)
                if c is not None and len(c):
                    c = c.select(~is_held[c.node] | _coupled(c))
                if f is not None and len(f):
                    f = f.select(~is_held[f.nodes].all(axis=1) | _coupled(f))
            prepared.append((_stack(cons), np.concatenate(G) if n else None, c, f))
            dense.append((n > 0 and any(x is not None and len(x) and np.abs(x.jacobian).max() > 0 for x in (c, f, a)))
                         or (f is not None and len(f) > 0 and bool(np.any(f.mu > 0))))
            held_by.append(held)
        dense = np.array(dense, dtype=bool)
        if pairs is not None and len(pairs):  # a soft contact between held nodes only is held already
            free = np.zeros(pairs.parts.shape, dtype=bool)
            for i, held in enumerate(held_by):
                on = pairs.parts == i
                if len(held):
                    is_held = np.zeros(steps[i].system.body.n_nodes, dtype=bool)
                    is_held[held] = True
                    free |= on & ~is_held[np.where(on, pairs.nodes, 0)]
                else:
                    free |= on
            free = free.any(axis=1)
            if not free.all():
                pairs = pairs.select(free)
        if pairs is not None and len(pairs):  # bodies in soft contact go to the convex problem with all they touch
            group = _groups(len(steps), pairs)
            in_pair = np.zeros(len(steps), dtype=bool)  # the bodies with a soft contact (their own first slot)
            in_pair[pairs.parts[:, 0]] = True
            for g in np.unique(group):
                members = np.flatnonzero(group == g)
                if any(dense[i] for i in members) or len(members) > 1 or in_pair[members].any():
                    dense[members] = True
        results: list = [None] * len(steps)
        simple = [i for i in range(len(steps)) if not dense[i]]
        coupled = [i for i in range(len(steps)) if dense[i]]
        du, iterations, pair_results, joint_impulses = np.zeros(n), 0, [], np.zeros(0 if joints is None else len(joints))
        if not n:
            joints = None
        self._pair_previous = (set(), set(), {})
        for index, solve in ((simple, self._solve_sparse), (coupled, self._solve_convex)):
            if not index and not (solve == self._solve_convex and joints is not None):
                continue
            sub = None
            if pairs is not None and len(pairs):
                local = np.full(len(steps), -1)
                local[index] = np.arange(len(index))
                mine = local[pairs.parts[:, 0]] >= 0
                sub = pairs if mine.all() else pairs.select(mine)
                sub = sub.relabel(local) if len(sub) else None
            out, its, res = solve([steps[i] for i in index], [prepared[i] for i in index], h, index, results, sub,
                                  *(() if solve == self._solve_sparse else (mass_matrix, joints, du_guess)))
            if solve == self._solve_convex:
                du, joint_impulses = out
            iterations = max(iterations, its)
            if res is not None:
                mine = np.zeros(len(steps), dtype=bool)
                mine[index] = True
                mine = mine[pairs.parts[:, 0]]
                pair_results.append((pairs if mine.all() else pairs.select(mine), res))
        self.previous[("soft", 0)] = self._pair_previous
        velocities, nodes, faces, attach = [], [], [], []
        for st, (v, r, res_n, res_f) in zip(steps, results):
            velocities.append(v)
            nodes.append(res_n)
            faces.append(res_f)
            attach.append(self._attachment_forces(st, r, h))
        return StepSolution(velocities, nodes, faces, attach, du, iterations, pair_results, joint_impulses)

    def _pair_set(self, pairs: PairContacts | None, steps: list[BodyStep], h: float) -> "_RowSet | None":
        """The row set of the soft contacts ``pairs`` (parts local to ``steps``), warm-started."""
        if pairs is None or not len(pairs):
            return None
        sizes = {i: st.system.body.n_nodes for i, st in enumerate(steps)}
        rs = _RowSet(self, pairs, pairs.nodes, pairs.weights, pairs.parts,
                     self.previous.get(("soft", 0), (set(), set(), {})), h, sizes)
        rs.tolerate(SOFT_SLOP)
        return rs

    def _keep_pair_state(self, state: tuple) -> None:
        """Merge the friction state of one mode's soft contacts into this step's (see :meth:`solve`)."""
        active, stick, slip = self._pair_previous
        self._pair_previous = (active | state[0], stick | state[1], {**slip, **state[2]})

    @staticmethod
    def _attachment_forces(st: BodyStep, r: np.ndarray, h: float) -> np.ndarray | None:
        """The attachments' forces on the soft nodes (m, 3) [N] from the reactions r (N, 3) (identity frames)."""
        a = st.attachments
        if a is None or not len(a):
            return None
        f = np.zeros((len(a), 3))
        kept = ~np.isin(a.node, st.supports.nodes)
        f[kept] = r[a.node[kept]] / h
        return f

    def _solve_sparse(self, steps, prepared, h, index, results, pairs=None) -> tuple[None, int, ContactResult | None]:
        """Bodies touching no movable rigid body: node contacts eliminated in their frames, face contacts and
        soft contacts (``pairs``, parts local to ``steps``) as rows, an active set that solves the sparse
        systems anew when the set changes. Returns (None, iterations, the soft contacts' result)."""
        nodes, faces = [], []
        for i, (st, (b_cons, _, c, f)) in enumerate(zip(steps, prepared)):
            body = st.system.body
            nodes.append(self._set("node", body, c, lambda prev: _NodeSet(self, c, prev, h, body.n_nodes)))
            faces.append(self._set("face", body, f, lambda prev: _FaceSet(self, f, i, prev, h, body.positions)))
        pset = self._pair_set(pairs, steps, h)
        if pset is None and all(f is None for f in faces):
            return self._solve_nodes(steps, prepared, nodes, index, results)
        return self._solve_rows(steps, prepared, index, results, nodes, faces, pset)

    def _solve_rows(self, steps, prepared, index, results, nodes: list, faces: list, pset
                    ) -> tuple[None, int, ContactResult | None]:
        """_solve_sparse's active set with rows (face and soft contacts) through the coupled solver, every body
        together: the node sets ``nodes`` and face sets ``faces`` per body (None: none), the soft contacts' ``pset``
        (or None)."""
        coupled = CoupledSolver(None)
        it = 0
        for it in range(1, self.max_iterations + 1):
            row_parts, extras, cons_of, reuse_of = [], [None] * len(steps), [], []
            for i, (st, (b_cons, _, _, _), nset, fset) in enumerate(zip(steps, prepared, nodes, faces)):
                cons, reuse = b_cons, it > 1
                if nset is not None:
                    c_cons, _, extras[i] = nset.constraints()
                    cons = _stack([b_cons, c_cons])
                    reuse = nset.reuse
                if fset is not None:
                    r, f_extra = fset.rows(0)
                    row_parts.append(r)
                    _add_extras(extras, f_extra)
                cons_of.append(cons)
                reuse_of.append(reuse)
            if pset is not None:
                r, p_extra = pset.rows(0)
                row_parts.append(r)
                _add_extras(extras, p_extra)
            parts = [CoupledPart(st.system, cons, None, extra, reuse)
                     for st, cons, extra, reuse in zip(steps, cons_of, extras, reuse_of)]
            rows = Rows.concat(row_parts, 0) if row_parts else None
            out, du, lam = coupled.solve(parts, rows)
            vs = [v for v, _ in out]
            changed, k = False, 0
            for (v, r), nset, fset in zip(out, nodes, faces):
                if nset is not None:
                    changed |= nset.read(v, r, du, it)
                if fset is not None:
                    m = len(fset.row_index[0])
                    changed |= fset.read(vs, lam[k:k + m], du, it)
                    k += m
            if pset is not None:
                changed |= pset.read(vs, lam[k:], du, it)
            if not changed:
                break
        for j, st, nset, fset, (v, r) in zip(index, steps, nodes, faces, out):
            body = st.system.body
            res = []
            for kind, cset in (("node", nset), ("face", fset)):
                if cset is None:
                    res.append(None)
                else:
                    result, self.previous[(kind, body)] = cset.result(it)
                    res.append(result)
            results[j] = (v, r, *res)
        pair_result = None
        if pset is not None:
            pair_result, state = pset.result(it)
            self._keep_pair_state(state)
        return None, it, pair_result

    def _solve_nodes(self, steps, prepared, nodes: list, index, results) -> tuple[None, int, None]:
        """_solve_sparse when every contact is a node contact (no rows, no rigid body moved): each body's active set
        on its own, a body solved again only while its set changes (as the coupled solve's cache of unchanged
        solves would). Returns (None, iterations, None)."""
        out: list = [None] * len(steps)
        stale = [True] * len(steps)
        # per body: a trial solve will do while its set changes (below; map, not a comprehension: one Python call
        # fewer a step, tests/test_step_cost.py)
        loose = list(map(operator.attrgetter("system.trials_pay"), steps))
        no_du = np.zeros(0)
        it = 0
        for it in range(1, self.max_iterations + 1):
            for i, (st, (b_cons, _, _, _), nset) in enumerate(zip(steps, prepared, nodes)):
                if not stale[i]:
                    continue
                if nset is None:
                    out[i], stale[i] = st.system.solve(b_cons, None, reuse=it > 1), False
                    continue
                c_cons, _, extra = nset.constraints()
                cons = _stack([b_cons, c_cons])
                # an iterative system solves to a loose tolerance while the set is changing, and once a trial
                # leaves it standing, once more to the full tolerance (from the trial) and reads that answer: the
                # set that ends the loop stands on a full solve, as before, at a fraction of the iterations (the
                # trials' answers may steer the way there, e.g. which contacts were released; the last iteration
                # the loop allows solves in full)
                loose[i] &= it < self.max_iterations
                out[i] = st.system.solve(cons, extra, reuse=nset.reuse, loose=loose[i])
                stale[i] = nset.read(out[i][0], out[i][1], no_du, it)
                if loose[i] and not stale[i]:
                    loose[i] = False
                    if st.system.confirmation_ends_switching:
                        nset.end_switching(it)
                    out[i] = st.system.solve(cons, extra, reuse=True)
                    stale[i] = nset.read(out[i][0], out[i][1], no_du, it)
            if not any(stale):
                break
        for j, st, nset, (v, r) in zip(index, steps, nodes, out):
            node_result = None
            if nset is not None:
                node_result, self.previous[("node", st.system.body)] = nset.result(it)
            results[j] = (v, r, node_result, None)
        return None, it, None

    def _solve_convex(self, steps, prepared, h, index, results, pairs=None, M=None, joints=None, du_guess=None
                      ) -> tuple[tuple[np.ndarray, np.ndarray], int, ContactResult | None]:
        """Bodies touching movable rigid bodies, each other or frictional faces, together: every contact and two-way
        attachment a row of one convex problem (convex.py) over their velocities and the rigid velocity change du,
        with the ``joints`` rows on du, solved by Newton on sparse systems. Returns ((du, the joint rows' impulses),
        Newton iterations, the soft contacts' result)."""
        n = 0 if M is None else len(M)
        parts, kinds = [], []  # kinds: (step index, kind, contacts, row slice, selected (m,) bool)
        row_parts = []
        count = 0

        def add(i, kind, c, rows, keep):
            nonlocal count
            kinds.append((i, kind, c, slice(count, count + len(rows)), keep))
            row_parts.append(rows)
            count += len(rows)

        for i, (st, (_, _, c, f)) in enumerate(zip(steps, prepared)):
            system, sup = st.system, st.supports
            body = system.body
            operator = getattr(system, "operator", None)  # A not assembled: applied by the operator, made if needed
            A = system.assemble if operator is not None else (
                system.assemble() if hasattr(system, "assemble") else system.A)
            held = np.zeros((body.n_nodes, 3), dtype=bool)
            value = np.zeros((body.n_nodes, 3))
            if len(sup):
                held[sup.nodes] = sup.mask
                value[sup.nodes] = np.where(sup.mask, sup.value, 0.0)
            parts.append(SoftPart(body, A, system.b, held, value, body.velocities, operator))
            if c is not None and len(c):
                add(i, "node", c, self._contact_rows(c, i, c.node[:, None], np.ones((len(c), 1)), h, n), None)
            else:
                self.previous[("node", body)] = (set(), set(), {})
            if f is not None and len(f):
                # a rigid point holds on the triangles it lies over (within FACE_BAND beyond their edges: a point on
                # the edge between two is over both), on an edge it was found on, and on its primary triangle
                x = body.positions[f.nodes]
                over = barycentric(f.point, x[:, 0], x[:, 1], x[:, 2]).min(axis=1) >= -FACE_BAND
                keep = f.primary | over if f.edge is None else (f.primary | f.edge | over)
                sel = f.select(keep)
                add(i, "face", f, self._contact_rows(sel, i, sel.nodes, sel.weights, h, n), keep)
            else:
                self.previous[("face", body)] = (set(), set(), {})
            a = st.attachments
            if a is not None and len(a):
                kept = ~np.isin(a.node, sup.nodes)
                m = int(kept.sum())
                eye = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
                add(i, "attach", a, ConvexRows(np.full((m, 1), i), a.node[kept][:, None], np.ones((m, 1)), eye,
                                               a.target[kept], a.jacobian[kept] if n else None, np.zeros(m),
                                               np.zeros(m), np.ones(m, dtype=bool)), kept)
        if pairs is not None and len(pairs):
            add(None, "soft", pairs, self._contact_rows(pairs, pairs.parts, pairs.nodes, pairs.weights, h, n), None)
        rows = ConvexRows.concat(row_parts, n)
        sol = self._solve_islands(parts, rows, M, h, joints, du_guess)
        F = rows.frames
        force = np.einsum("mij,mj->mi", F, sol.gamma) / h  # on the weighted (soft) point [N]
        gap_end = h * (sol.vc[:, 0] - rows.v_hat)  # the normal gap at the end of the step (of its bounded target)
        per_body = {i: [None, None] for i in range(len(steps))}
        reactions = [np.zeros((st.system.body.n_nodes, 3)) for st in steps]
        pair_result = None
        for i, kind, c, sl, keep in kinds:
            g, fr, stick = sol.gamma[sl], force[sl], sol.stiction[sl]
            if kind == "attach":
                np.add.at(reactions[i], c.node[keep], g)  # identity frames: the impulse on the node [N s]
                continue
            mc = len(c)
            full_force, active, sticking = np.zeros((mc, 3)), np.zeros(mc, bool), np.zeros(mc, bool)
            where = np.arange(mc) if keep is None else np.flatnonzero(keep)
            full_force[where] = fr
            active[where] = g[:, 0] > 0
            sticking[where] = stick & (g[:, 0] > 0) & (c.mu[where] > 0)
            viol = max(0.0, -float(gap_end[sl].min(initial=0.0)))
            result = ContactResult(full_force, active, sticking, sol.iterations, sol.factorizations, viol,
                                   {"converged": sol.converged, "residual": sol.residual})
            keys = c.node
            sliding = active & ~sticking & (c.mu > 0)
            f, nrm = full_force[sliding], c.normal[sliding]
            tangential = f - np.einsum("ij,ij->i", f, nrm)[:, None] * nrm  # the sliding rows' friction forces [N]
            state = (set(keys[active].tolist()), set(keys[sticking].tolist()),
                     dict(zip(keys[sliding].tolist(), tangential)))
            if kind == "soft":
                pair_result = result
                self._keep_pair_state(state)
            else:
                self.previous[(kind, steps[i].system.body)] = state
                per_body[i][0 if kind == "node" else 1] = result
        for j, i in zip(index, range(len(steps))):
            results[j] = (sol.velocities[i], reactions[i], *per_body[i])
        return (sol.du, sol.joint_gamma), sol.iterations, pair_result

    def _solve_islands(self, parts: list[SoftPart], rows: ConvexRows, M: np.ndarray | None, h: float,
                       joints: JointRows | None, du_guess: np.ndarray | None):
        """The convex problem of ``parts`` and ``rows`` island by island (islands.py: the bodies, a stack's members
        apart, that rows join directly or through the rigid unknowns M (n, n)); one convex.Solution of the whole."""
        n = 0 if M is None else len(M)
        several = len(parts) > 1 or (len(parts) == 1 and hasattr(parts[0].body, "members"))  # bodies or a stack
        islands = Islands.of(parts, rows, n > 0) if several else None
        if islands is None or len(islands) == 1:  # one island: solved as it is (a stack whole)
            sol = self.convex.solve(parts, rows, M, h, joints, du_guess)
            self.convex.patterns.forget_idle()
            return sol
        solutions = []
        for island in islands.islands:
            sub_parts, sub_rows = islands.problem(island, rows)
            solutions.append(self.convex.solve(sub_parts, sub_rows, M if island.rigid else None, h,
                                               joints if island.rigid else None, du_guess if island.rigid else None))
        self.convex.patterns.forget_idle()
        return islands.merge(solutions, len(rows), n, len(joints) if joints is not None and n else 0)

    def _contact_rows(self, c: NodeContacts, parts, nodes: np.ndarray, weights: np.ndarray, h: float, n: int,
                      slop: float = 0.0) -> ConvexRows:
        """The convex problem's rows of contacts ``c`` (node, face or soft) over ``nodes`` (m, S) of ``parts`` (an index,
        or (m, S)) with ``weights`` (m, S): the gap closes within the step, a penetration at most at push_speed (unless
        the contact was carried back from the end of the step), ``slop`` [m] of it left where it is."""
        m = len(c)
        gap = c.distance
        if slop:
            gap = np.where(gap < 0, np.minimum(gap + slop, 0.0), gap)
        bounded = np.maximum(gap, -self.push_speed * h)
        if c.carried is not None:
            bounded = np.where(c.carried, gap, bounded)
        parts = np.broadcast_to(np.asarray(parts, dtype=np.int64), nodes.shape).copy()
        jac = c.jacobian if (n and c.jacobian is not None) else (np.zeros((m, 3, n)) if n else None)
        return ConvexRows(parts, np.asarray(nodes, dtype=np.int64), np.asarray(weights, dtype=float),
                          tangent_frames(c.normal), np.asarray(c.rigid_velocity, dtype=float), jac, -bounded / h,
                          np.asarray(c.mu, dtype=float), np.zeros(m, dtype=bool))
