"""pybullet's user constraints (``createConstraint``) as rows of the coupled problem (convex.JointRows).

pybullet enforces a user constraint in its own step, before the soft bodies' reactions are known; the coupled
correction that follows would otherwise treat the constrained bodies as free and carry them off the constraint (a
rod hung by a point-to-point constraint, with a soft block attached off-centre, settled at 7.14 degrees where
statics gives 8.40). Here each constraint that holds a body of the coupled problem is rows of that problem, on the
constrained bodies' generalized velocities u at the end of the step:

- point-to-point: the two pivots' velocities agree, J_a(p_a) u - J_b(p_b) u = -(p_a - p_b) / h (three rows, world
  axes: the pivots meet at the end of the step);
- fixed: the same at the pivots, and the two frames' angular velocities agree, omega_a - omega_b = -theta / h
  (theta: the rotation vector from the child's constraint frame to the parent's);
- gear (between two joints of multibodies): qd_a + ratio qd_b = 0.

The pivots are given in each link's centre-of-mass frame (pybullet's convention; the child -1 is the world, its pivot
in world coordinates). Each row's whole impulse, pybullet's (its reported constraint force times h) and the solve's,
stays within +-maxForce h, as pybullet bounds each row. A partner body that pybullet moves joins the coupled problem
with the body it holds (World._build_problem); a constraint with a partner the problem cannot move (a body with
spherical or planar joints) stays pybullet's alone (``skip``), with a warning.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .bullet import quat_matrix
from .convex import JointRows
from .coupling import RigidCoupling

if TYPE_CHECKING:
    from .bullet import BulletAdapter

POINT2POINT, FIXED, GEAR = 5, 4, 6  # pybullet.JOINT_POINT2POINT, JOINT_FIXED, JOINT_GEAR
KINDS = {POINT2POINT: "point2point", FIXED: "fixed", GEAR: "gear"}


@dataclass(frozen=True)
class UserConstraint:
    """One pybullet user constraint (getConstraintInfo): ``id``; the parent body and link and the child body (-1: the
    world) and link; ``kind`` (POINT2POINT, FIXED, GEAR or another pybullet joint type, not coupled); the pivots in
    their links' centre-of-mass frames (3,) and the frames' orientations (4,); ``max_force`` [N or N m]; the gear
    ratio."""

    id: int
    parent: int
    parent_link: int
    child: int
    child_link: int
    kind: int
    pivot_parent: np.ndarray
    pivot_child: np.ndarray
    frame_parent: np.ndarray
    frame_child: np.ndarray
    max_force: float
    gear_ratio: float

    @classmethod
    def of(cls, cid: int, info: tuple) -> "UserConstraint":
        return cls(int(cid), int(info[0]), int(info[1]), int(info[2]), int(info[3]), int(info[4]),
                   np.array(info[6], float), np.array(info[7], float), np.array(info[8], float),
                   np.array(info[9], float), float(info[10]), float(info[11]))

    @property
    def bodies(self) -> list[int]:
        return [b for b in (self.parent, self.child) if b >= 0]

    @property
    def coupled(self) -> bool:
        """Whether the coupled problem holds this kind of constraint (point-to-point, fixed, gear)."""
        return self.kind in KINDS


def _frame(adapter: "BulletAdapter", body: int, link: int) -> tuple[np.ndarray, np.ndarray]:
    """(centre of mass (3,), rotation (3, 3)) of a link, the world's for body -1."""
    if body < 0:
        return np.zeros(3), np.eye(3)
    c, q = adapter.pose(body, link)
    return np.asarray(c, float), quat_matrix(q)


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vector (3,) of a rotation matrix (small angles: its skew part)."""
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s, c = np.linalg.norm(w), 0.5 * (np.trace(R) - 1.0)
    angle = math.atan2(s, c)
    return w * (angle / s) if s > 1e-12 else w


def constraint_rows(constraints: list[UserConstraint], coupling: RigidCoupling, adapter: "BulletAdapter", h: float,
                    skip: set[int] = frozenset()) -> JointRows:
    """The rows of the user ``constraints`` that hold a body of ``coupling``, at the start configuration, over a step h
    [s], but for those joining a body in ``skip`` (moved by pybullet, not by the problem); labels (kind name,
    constraint id, row within it)."""
    n = coupling.n
    parts = []
    for uc in constraints:
        if not uc.coupled or not any(b in coupling.dynamics for b in uc.bodies) or set(uc.bodies) & skip:
            continue
        if uc.kind == GEAR:
            C = np.zeros((1, n))
            for body, link, weight in ((uc.parent, uc.parent_link, 1.0), (uc.child, uc.child_link, uc.gear_ratio)):
                dyn = coupling.dynamics.get(body)
                if dyn is not None and link in dyn.joints:
                    C[0, coupling.offset[body] + (6 if dyn.free_base else 0) + dyn.joints.index(link)] += weight
            target = np.zeros(1)
        else:
            ca, Ra = _frame(adapter, uc.parent, uc.parent_link)
            cb, Rb = _frame(adapter, uc.child, uc.child_link)
            pa, pb = ca + Ra @ uc.pivot_parent, cb + Rb @ uc.pivot_child
            Ja = _point_jacobian(coupling, adapter, uc.parent, uc.parent_link, pa)
            Jb = _point_jacobian(coupling, adapter, uc.child, uc.child_link, pb)
            C, target = Ja - Jb, -(pa - pb) / h
            if uc.kind == FIXED:
                Wa = _angular_jacobian(coupling, adapter, uc.parent, uc.parent_link)
                Wb = _angular_jacobian(coupling, adapter, uc.child, uc.child_link)
                Fa, Fb = Ra @ quat_matrix(uc.frame_parent), Rb @ quat_matrix(uc.frame_child)
                C = np.vstack([C, Wa - Wb])
                target = np.concatenate([target, -_rotation_vector(Fa @ Fb.T) / h])
        k = len(target)
        bound = uc.max_force * h
        parts.append(JointRows(C, np.zeros(k), target, np.full(k, -bound), np.full(k, bound),
                               [(KINDS[uc.kind], uc.id, r) for r in range(k)]))
    return JointRows.concat(parts, n)


def _point_jacobian(coupling: RigidCoupling, adapter: "BulletAdapter", body: int, link: int, point: np.ndarray
                    ) -> np.ndarray:
    """(3, n): the velocity of a material point of a link per unit u (zero for bodies the problem does not move)."""
    if body not in coupling.dynamics:
        return np.zeros((3, coupling.n))
    return coupling.jacobians(adapter, np.array([body]), np.array([link]), point[None])[0]


def _angular_jacobian(coupling: RigidCoupling, adapter: "BulletAdapter", body: int, link: int) -> np.ndarray:
    """(3, n): a link's angular velocity per unit u (zero for bodies the problem does not move)."""
    out = np.zeros((3, coupling.n))
    dyn = coupling.dynamics.get(body)
    if dyn is not None:
        o = coupling.offset[body]
        out[:, o:o + dyn.n] = adapter.angular_jacobian(dyn, link)
    return out


def applied_impulses(rows: JointRows, constraints: list[UserConstraint], adapter: "BulletAdapter", state,
                     h: float) -> np.ndarray:
    """The impulses (k,) [N s or N m s] pybullet's last step of h [s] gave the constraint rows of ``rows`` (labels
    (kind, id, row)), on the parent along the rows, from ``state(id)``: pybullet's getConstraintState, measured to be
    for a point-to-point constraint the force [N] on the child in world axes (a rod hung by it reports -m g), for a
    fixed one the force on the parent in world axes (+m g) and the torque [N m] on it in the axes of the parent's
    constraint frame, for a gear the impulse along the row; zero for rows of other kinds. One query per constraint;
    ``constraints`` and ``adapter``: for the fixed constraints' frames (at the step's start, as the rows)."""
    out = np.zeros(len(rows))
    sign = {"point2point": -1.0, "fixed": 1.0, "gear": 1.0}
    by_id = {uc.id: uc for uc in constraints}
    states: dict[int, np.ndarray] = {}
    for r, (kind, cid, row) in enumerate(rows.labels):
        if kind not in sign:
            continue
        if cid not in states:
            s = np.asarray(state(cid), float)
            if kind == "fixed" and len(s) == 6:  # its torque from the constraint frame's axes to the world's
                uc = by_id[cid]
                _, Ra = _frame(adapter, uc.parent, uc.parent_link)
                s[3:] = Ra @ quat_matrix(uc.frame_parent) @ s[3:]
            states[cid] = s
        if row < len(states[cid]):
            out[r] = sign[kind] * states[cid][row] * h
    return out
