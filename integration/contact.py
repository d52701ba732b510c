"""Unilateral contact with Coulomb friction inside the implicit step.

Each contact is a condition on one soft node's velocity at the end of the step, in a frame
(n, t1, t2) with n the rigid's outward normal:

    non-penetration   n . (v - v_rigid) >= -d / h      (the gap d closes to zero, never below)
    separation        the normal force lam = r_n / h must be >= 0, else the contact is released
    Coulomb friction  stick: t . (v - v_rigid) = 0 while |f_t| <= mu lam;
                      slip: a force mu lam opposite to the sliding direction.

An active-set loop solves the step systems of all soft bodies exactly under the current set (the
constrained components are eliminated, see softbody.integrator), releases pulling contacts, adds
violated ones and switches stick/slip until nothing changes. Changing only the slip forces reuses the
factorisation.

A contact or attachment on a link of a movable rigid body moves with that body, whose velocity
change du is found in the same solve (coupling.py): v_rigid = v_free + J du, with J the point
Jacobian of the rigid material point. Attachments hold all three components of a node to the rigid
point (bilateral, never released).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softbody.integrator import Constraints, LinearSystem

from .coupling import CoupledPart, CoupledSolver


def tangent_frames(normals: np.ndarray) -> np.ndarray:
    """Orthonormal frames (m, 3, 3) with the unit normals (m, 3) as first column."""
    n = normals / np.sqrt(np.einsum("mi,mi->m", normals, normals))[:, None]
    x, y, z = n.T
    # t1 = n x e_x (or n x e_y where n is nearly along x), normalised; t2 = n x t1
    along_x = np.abs(x) >= 0.9
    t1 = np.where(along_x[:, None], np.stack([-z, np.zeros_like(x), x], axis=1), np.stack([np.zeros_like(x), z, -y], axis=1))
    t1 /= np.sqrt(np.einsum("mi,mi->m", t1, t1))[:, None]
    a, b, c = t1.T
    t2 = np.stack([y * c - z * b, z * a - x * c, x * b - y * a], axis=1)
    return np.stack([n, t1, t2], axis=2)




@dataclass
class NodeContacts:
    """Per-node contact data for one soft body (one entry per node).

    node (m,), normal (m, 3), distance (m,), rigid_velocity (m, 3) [m/s] of the rigid material point
    (for a movable body: under its free motion over the step), mu (m,), rigid (m,) pybullet body id,
    point (m, 3), link (m,) link index (-1: base), jacobian (m, 3, n): velocity of the rigid point per
    unit of the coupled rigid velocity change du (None: nothing coupled).
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

    def __post_init__(self):
        if self.link is None:
            self.link = np.full(len(self.node), -1, dtype=np.int64)

    def __len__(self) -> int:
        return len(self.node)

    def select(self, keep: np.ndarray) -> "NodeContacts":
        return NodeContacts(*(None if getattr(self, f) is None else getattr(self, f)[keep]
                              for f in NodeContacts.__dataclass_fields__))


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
    """Outcome of one contact solve: per contact entry, world force on the soft node [N], flags."""

    force: np.ndarray
    active: np.ndarray
    stick: np.ndarray
    iterations: int
    factorizations: int
    max_violation: float = 0.0
    extra: dict = field(default_factory=dict)


@dataclass
class BodyStep:
    """One soft body's part of a step: its step system, supports, contacts and coupled attachments."""

    system: LinearSystem
    supports: Constraints
    contacts: NodeContacts | None = None
    attachments: Attachments | None = None


@dataclass
class StepSolution:
    """What the contact solve found: per body the velocities (N, 3), the contact result (or None) and the
    attachment forces on the soft nodes (m, 3) [N] (or None); du (n,) the rigid velocity change."""

    velocities: list[np.ndarray]
    contacts: list[ContactResult | None]
    attachment_forces: list[np.ndarray | None]
    du: np.ndarray
    iterations: int


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


class _ActiveSet:
    """The contacts of one soft body within one step's active-set loop: which are active, which stick,
    the sliding friction forces, and the switching rules of :class:`ContactSolver`."""

    def __init__(self, solver: "ContactSolver", c: NodeContacts, previous: tuple, h: float, n_nodes: int):
        self.solver, self.c, self.h, self.n_nodes = solver, c, h, n_nodes
        m = len(c)
        self.frames = tangent_frames(c.normal)
        self.vr_free = np.einsum("mji,mj->mi", self.frames, c.rigid_velocity)  # rigid velocity in (n, t1, t2)
        # d(local rigid velocity) / d du: the point Jacobians in the contact frames
        self.G = None if c.jacobian is None else np.einsum("mji,mjn->min", self.frames, c.jacobian)
        self.target = self.vr_free.copy()
        self.target[:, 0] -= c.distance / h
        prev_active, prev_stick, prev_slip = previous
        self.active = (c.distance <= 0) | np.isin(c.node, list(prev_active))
        self.friction = c.mu > 0
        self.stick = self.friction & (np.isin(c.node, list(prev_stick)) | ~np.isin(c.node, list(prev_active)))
        self.slip_force = np.zeros((m, 3))  # local frame, tangential components only
        carried = [i for i, n in enumerate(c.node.tolist()) if n in prev_slip and not self.stick[i]]
        if carried:  # last step's sliding friction, in this step's tangent plane
            f_prev = np.array([prev_slip[int(c.node[i])] for i in carried])
            self.slip_force[carried, 1:] = np.einsum("mji,mj->mi", self.frames[carried], f_prev)[:, 1:]
        self.released = np.zeros(m, dtype=bool)  # a contact released once this step is not released again
        self.factorizations = 0
        self.last_key = None
        self.want_slip = self.want_stick = np.zeros(m, dtype=bool)
        self.rl = np.zeros((m, 3))
        self.gap_rate = np.zeros(m)
        self.mag = np.zeros((m, 1))
        self.d_stick = self.new_slip = np.zeros((m, 2))

    def constraints(self) -> tuple[Constraints, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """The active contacts as constraints (values at du = 0), their G rows, the sliding friction as an
        extra right-hand side (N, 3), and its generalized impulse on the rigid side (n,) (None if none)."""
        c, h = self.c, self.h
        mask = np.zeros((len(c), 3), dtype=bool)
        mask[:, 0] = self.active
        mask[:, 1:] = (self.active & self.stick)[:, None]
        sel = mask.any(axis=1)
        cons = Constraints(c.node[sel], mask[sel], self.target[sel], self.frames[sel])
        key = (c.node[sel].tobytes(), mask[sel].tobytes())
        self.reuse = key == self.last_key
        self.factorizations += not self.reuse
        self.last_key = key
        extra = slip = None
        slipping = self.active & ~self.stick & self.friction
        if slipping.any():
            extra = np.zeros((self.n_nodes, 3))
            np.add.at(extra, c.node[slipping], h * np.einsum("mij,mj->mi", self.frames[slipping],
                                                             self.slip_force[slipping]))
            if self.G is not None:  # the opposite impulse on the rigid side
                slip = -h * np.einsum("mk,mkn->n", self.slip_force[slipping], self.G[slipping])
        return cons, None if self.G is None else self.G[sel], extra, slip

    def update(self, v: np.ndarray, r: np.ndarray, du: np.ndarray, it: int) -> bool:
        """Read a solve (v (N, 3), reactions r (N, 3) local, du (n,)) and switch the set; True if it changed."""
        s, c, h = self.solver, self.c, self.h
        vr_local = self.vr_free if self.G is None or not len(du) else self.vr_free + self.G @ du
        rl = r[c.node] / h  # reaction force in the local frame [N]
        lam = rl[:, 0]
        vrel = np.einsum("mji,mj->mi", self.frames, v[c.node]) - vr_local
        gap_rate = vrel[:, 0] + c.distance / h
        active, stick = self.active, self.stick
        release = active & (lam < 0) & ~self.released
        add = ~active & (gap_rate < -s.velocity_tol)
        self.released |= release
        changed = release.any() or add.any()
        # friction: stick -> slip when the needed force leaves the cone; slip -> stick when sliding stops
        ft = rl[:, 1:]
        ftn = np.linalg.norm(ft, axis=1)
        switching = it <= s.friction_switches
        want_slip = active & stick & (ftn > c.mu * np.maximum(lam, 0) * (1 + s.cone_tol))
        to_slip = switching & want_slip
        vt = vrel[:, 1:]
        vtn = np.linalg.norm(vt, axis=1)
        old = self.slip_force[:, 1:]
        reversed_ = np.einsum("mi,mi->m", vt, old) > 0  # sliding along the friction force: it stopped
        want_stick = active & ~stick & self.friction & (reversed_ | (vtn < s.velocity_tol))
        to_stick = switching & want_stick
        new_slip = np.zeros((len(c), 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            d_stick = np.where(ftn[:, None] > 0, ft / ftn[:, None], 0.0)  # direction of the needed force
            d_slip = np.where(vtn[:, None] > 0, -vt / vtn[:, None], 0.0)
        mag = (c.mu * np.maximum(lam, 0))[:, None]
        new_slip = np.where(to_slip[:, None], mag * d_stick, new_slip)
        cont = active & ~stick & self.friction & ~to_stick
        new_slip = np.where(cont[:, None], mag * d_slip, new_slip)
        slip_change = np.abs(new_slip - old).max(initial=0.0) > s.slip_tol * max(1e-12, mag.max(initial=0.0))
        refine = it <= s.friction_switches + 1  # slip forces: a bounded fixed-point iteration
        changed = changed or to_slip.any() or to_stick.any() or (refine and slip_change and cont.any())
        self.rl, self.gap_rate, self.mag, self.d_stick, self.new_slip = rl, gap_rate, mag, d_stick, new_slip
        self.want_slip, self.want_stick = want_slip, want_stick
        if changed:
            self.active = (active & ~release) | add
            self.stick = (stick & ~to_slip) | to_stick
            self.slip_force[:, 1:] = np.where((to_slip | cont)[:, None], new_slip, 0.0)
            self.slip_force[~self.active] = 0.0
        return bool(changed)

    def result(self, iterations: int) -> tuple[ContactResult, tuple]:
        """The contact result of the final solve, and the friction state for the next step."""
        c, active, stick, m = self.c, self.active, self.stick, len(self.c)
        force_local = np.where(active[:, None], self.rl, 0.0)
        slipping = active & ~stick & self.friction
        force_local[slipping, 1:] = self.slip_force[slipping, 1:]
        force_local[active & ~self.friction, 1:] = 0.0
        force = np.einsum("mij,mj->mi", self.frames, force_local)
        # friction state for the next step, including the switches this step did not make
        next_stick = active & self.friction & ((stick & ~self.want_slip) | self.want_stick)
        next_slip = active & self.friction & ~next_stick
        slip_world = np.einsum("mij,mj->mi", self.frames,
                               np.where(self.want_slip[:, None], np.c_[np.zeros(m), self.mag * self.d_stick],
                                        np.c_[np.zeros(m), self.new_slip]))
        previous = (set(c.node[active].tolist()), set(c.node[next_stick].tolist()),
                    {int(n): f for n, f in zip(c.node[next_slip], slip_world[next_slip])})
        viol = float(np.max(-(self.gap_rate * self.h), initial=0.0))
        return ContactResult(force, active.copy(), stick & active, iterations, self.factorizations, viol), previous


class ContactSolver:
    """Active-set solver for unilateral node contacts with Coulomb friction, for all soft bodies of a
    step at once (coupled through movable rigid bodies, see coupling.py).

    max_iterations bounds the active-set loop; velocity_tol [m/s] is the threshold for adding contacts
    and for a slide to count as stopped; slip_tol the relative change of sliding forces that still
    counts as a change; cone_tol the relative slack of the friction cone before stick turns to slip.
    """

    def __init__(self, max_iterations: int = 30, velocity_tol: float = 1e-7, slip_tol: float = 1e-3,
                 friction_switches: int = 1, cone_tol: float = 1e-3):
        self.max_iterations = max_iterations
        self.velocity_tol = velocity_tol
        self.slip_tol = slip_tol
        # stick/slip may change only in the first friction_switches iterations of a step; later changes
        # are carried to the next step (lagged friction: a node on the cone's edge would otherwise
        # flip forever, and each flip costs a solve). Non-penetration stays exact in every iteration.
        self.friction_switches = friction_switches
        self.cone_tol = cone_tol
        # id(body) -> (active nodes, sticking nodes, {slipping node: friction force (3,) world [N]})
        self.previous: dict[int, tuple[set, set, dict]] = {}

    def solve(self, steps: list[BodyStep], h: float, mass_matrix: np.ndarray | None = None) -> StepSolution:
        """Solve one step of every body in ``steps``; ``mass_matrix`` (n, n): the movable rigid bodies' mass
        matrix for the coupled velocity change du (None: no rigid body is coupled)."""
        coupled = CoupledSolver(mass_matrix)
        n = coupled.n
        base, base_G, sets = [], [], []
        for st in steps:
            body = st.system.body
            held = st.supports.nodes
            cons, G = [st.supports], [np.zeros((len(st.supports), 3, n))]
            a = st.attachments
            if a is not None and len(a):  # supports win over attachments, both over contacts
                keep = ~np.isin(a.node, held)
                cons.append(Constraints.full(a.node[keep], a.target[keep]))
                G.append(a.jacobian[keep] if n else np.zeros((int(keep.sum()), 3, 0)))
                held = np.concatenate([held, a.node[keep]])
            base.append(_stack(cons))
            base_G.append(np.concatenate(G) if n else None)
            c = st.contacts
            if c is not None and len(c):
                c = c.select(~np.isin(c.node, held))
            if c is None or not len(c):
                self.previous[id(body)] = (set(), set(), {})
                sets.append(None)
            else:
                sets.append(_ActiveSet(self, c, self.previous.get(id(body), (set(), set(), {})), h, body.n_nodes))
        it = 0
        for it in range(1, self.max_iterations + 1):
            parts, slip = [], np.zeros(n)
            for st, b_cons, b_G, aset in zip(steps, base, base_G, sets):
                if aset is None:
                    parts.append(CoupledPart(st.system, b_cons, b_G, None, reuse=it > 1))
                    continue
                c_cons, c_G, extra, s = aset.constraints()
                cons = _stack([b_cons, c_cons])
                G = None
                if n:
                    G = np.concatenate([b_G, c_G if c_G is not None else np.zeros((len(c_cons), 3, n))])
                parts.append(CoupledPart(st.system, cons, G, extra, aset.reuse))
                if s is not None:
                    slip += s
            out, du = coupled.solve(parts, slip if n else None)
            changed = False
            for aset, (v, r) in zip(sets, out):
                if aset is not None:
                    changed |= aset.update(v, r, du, it)
            if not changed:
                break
        velocities, results, attach = [], [], []
        for st, aset, (v, r), part in zip(steps, sets, out, parts):
            velocities.append(v)
            if aset is None:
                results.append(None)
            else:
                res, self.previous[id(st.system.body)] = aset.result(it)
                results.append(res)
            a = st.attachments
            if a is not None and len(a):
                f = np.zeros((len(a), 3))
                kept = np.isin(a.node, part.cons.nodes) & ~np.isin(a.node, st.supports.nodes)
                f[kept] = r[a.node[kept]] / h  # identity frames: world forces on the soft nodes
                attach.append(f)
            else:
                attach.append(None)
        return StepSolution(velocities, results, attach, du, it)
