"""Unilateral contact with Coulomb friction inside the implicit step.

Each contact is a condition on one soft node's velocity at the end of the step, in a frame
(n, t1, t2) with n the rigid's outward normal:

    non-penetration   n . (v - v_rigid) >= -d / h      (the gap d closes to zero, never below)
    separation        the normal force lam = r_n / h must be >= 0, else the contact is released
    Coulomb friction  stick: t . (v - v_rigid) = 0 while |f_t| <= mu lam;
                      slip: a force mu lam opposite to the sliding direction.

An active-set loop solves the step system exactly under the current set (the constrained
components are eliminated, see softbody.integrator), releases pulling contacts, adds violated
ones and switches stick/slip until nothing changes. Changing only the slip forces reuses the
factorisation.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softbody.integrator import Constraints, LinearSystem, merge


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

    node (m,), normal (m, 3), distance (m,), rigid_velocity (m, 3) [m/s] of the rigid material point,
    mu (m,), rigid (m,) pybullet id, point (m, 3).
    """

    node: np.ndarray
    normal: np.ndarray
    distance: np.ndarray
    rigid_velocity: np.ndarray
    mu: np.ndarray
    rigid: np.ndarray
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


class ContactSolver:
    """Active-set solver for unilateral node contacts with Coulomb friction.

    max_iterations bounds the active-set loop; force_tol [N] and velocity_tol [m/s] are the
    thresholds for releasing and adding contacts.
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

    def solve(self, system: LinearSystem, supports: Constraints, c: NodeContacts, h: float
              ) -> tuple[np.ndarray, ContactResult]:
        body = system.body
        keep = ~np.isin(c.node, supports.nodes)  # supports win over contacts
        c = NodeContacts(*(getattr(c, f)[keep] for f in NodeContacts.__dataclass_fields__))
        m = len(c)
        if m == 0:
            v, _ = system.solve(supports)
            self.previous[id(body)] = (set(), set(), {})
            return v, ContactResult(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, bool), 1, 1)
        frames = tangent_frames(c.normal)
        vr_local = np.einsum("mji,mj->mi", frames, c.rigid_velocity)  # rigid velocity in (n, t1, t2)
        target = vr_local.copy()
        target[:, 0] -= c.distance / h
        prev_active, prev_stick, prev_slip = self.previous.get(id(body), (set(), set(), {}))
        active = (c.distance <= 0) | np.isin(c.node, list(prev_active))
        friction = c.mu > 0
        stick = friction & (np.isin(c.node, list(prev_stick)) | ~np.isin(c.node, list(prev_active)))
        slip_force = np.zeros((m, 3))  # local frame, tangential components only
        carried = [i for i, n in enumerate(c.node.tolist()) if n in prev_slip and not stick[i]]
        if carried:  # last step's sliding friction, in this step's tangent plane
            f_prev = np.array([prev_slip[int(c.node[i])] for i in carried])
            slip_force[carried, 1:] = np.einsum("mji,mj->mi", frames[carried], f_prev)[:, 1:]
        factorizations = 0
        last_key = None
        released = np.zeros(m, dtype=bool)  # a contact released once this step is not released again
        for it in range(1, self.max_iterations + 1):
            mask = np.zeros((m, 3), dtype=bool)
            mask[:, 0] = active
            mask[:, 1:] = (active & stick)[:, None]
            sel = mask.any(axis=1)
            cons = merge(supports, Constraints(c.node[sel], mask[sel], target[sel], frames[sel]))
            extra = np.zeros((body.n_nodes, 3))
            slipping = active & ~stick & friction
            if slipping.any():
                np.add.at(extra, c.node[slipping], h * np.einsum("mij,mj->mi", frames[slipping], slip_force[slipping]))
            key = (c.node[sel].tobytes(), mask[sel].tobytes())
            v, r = system.solve(cons, extra if slipping.any() else None, reuse=(key == last_key))
            factorizations += key != last_key
            last_key = key
            rl = r[c.node] / h  # reaction force in the local frame [N]
            lam = rl[:, 0]
            vrel = np.einsum("mji,mj->mi", frames, v[c.node]) - vr_local
            gap_rate = vrel[:, 0] + c.distance / h
            release = active & (lam < 0) & ~released
            add = ~active & (gap_rate < -self.velocity_tol)
            released |= release
            changed = release.any() or add.any()
            # friction: stick -> slip when the needed force leaves the cone; slip -> stick when sliding stops
            ft = rl[:, 1:]
            ftn = np.linalg.norm(ft, axis=1)
            switching = it <= self.friction_switches
            want_slip = active & stick & (ftn > c.mu * np.maximum(lam, 0) * (1 + self.cone_tol))
            to_slip = switching & want_slip
            vt = vrel[:, 1:]
            vtn = np.linalg.norm(vt, axis=1)
            old = slip_force[:, 1:]
            reversed_ = np.einsum("mi,mi->m", vt, old) > 0  # sliding along the friction force: it stopped
            want_stick = active & ~stick & friction & (reversed_ | (vtn < self.velocity_tol))
            to_stick = switching & want_stick
            new_slip = np.zeros((m, 2))
            with np.errstate(invalid="ignore", divide="ignore"):
                d_stick = np.where(ftn[:, None] > 0, ft / ftn[:, None], 0.0)  # direction of the needed force
                d_slip = np.where(vtn[:, None] > 0, -vt / vtn[:, None], 0.0)
            mag = (c.mu * np.maximum(lam, 0))[:, None]
            new_slip = np.where(to_slip[:, None], mag * d_stick, new_slip)
            cont = active & ~stick & friction & ~to_stick
            new_slip = np.where(cont[:, None], mag * d_slip, new_slip)
            slip_change = np.abs(new_slip - old).max(initial=0.0) > self.slip_tol * max(1e-12, mag.max(initial=0.0))
            refine = it <= self.friction_switches + 1  # slip forces: a bounded fixed-point iteration
            changed = changed or to_slip.any() or to_stick.any() or (refine and slip_change and cont.any())
            if not changed:
                break
            active = (active & ~release) | add
            stick = (stick & ~to_slip) | to_stick
            slip_force[:, 1:] = np.where((to_slip | cont)[:, None], new_slip, 0.0)
            slip_force[~active] = 0.0
        force_local = np.where(active[:, None], rl, 0.0)
        slipping = active & ~stick & friction
        force_local[slipping, 1:] = slip_force[slipping, 1:]
        force_local[active & ~friction, 1:] = 0.0
        force = np.einsum("mij,mj->mi", frames, force_local)
        # friction state for the next step, including the switches this step did not make
        next_stick = active & friction & ((stick & ~want_slip) | want_stick)
        next_slip = active & friction & ~next_stick
        slip_world = np.einsum("mij,mj->mi", frames, np.where(want_slip[:, None], np.c_[np.zeros(m), mag * d_stick],
                                                                np.c_[np.zeros(m), new_slip]))
        self.previous[id(body)] = (set(c.node[active].tolist()), set(c.node[next_stick].tolist()),
                                   {int(n): f for n, f in zip(c.node[next_slip], slip_world[next_slip])})
        viol = float(np.max(-(gap_rate * h), initial=0.0))
        full = np.zeros((len(keep), 3))
        full[keep] = force
        act, stk = np.zeros(len(keep), bool), np.zeros(len(keep), bool)
        act[keep], stk[keep] = active, stick & active
        return v, ContactResult(full, act, stk, it, factorizations, viol)
