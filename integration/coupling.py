"""Two-way coupling of soft bodies, movable rigid bodies and constraint rows, solved in one implicit step.

Two kinds of constraints meet here:

- *eliminated* node constraints (supports, attachments, node contacts): each constrained velocity
  component k of soft body b takes the value c_k = c0_k + G_bk du, where du (n,) is the change of the
  movable rigid bodies' generalized velocities (stacked) against their free motion over the step, and
  G_b (rows of the point Jacobians in the constraints' local frames) says how the rigid point moves;
- *rows* with multipliers (a rigid feature on a soft triangle, a soft node on another soft body's
  triangle): row k asks sum_i w_ki t_k . v[node_ki] - g_k . du = target_k over nodes of one or two
  soft bodies (barycentric weights w, direction t_k, g_k = J_k^T t_k the rigid point's generalized
  direction), with impulse lambda_k: + w_ki lambda_k t_k on the soft nodes, - lambda_k t_k on the rigid.

The equations of the step:

    A_b v_b = b_b + r_b + C_b^T lambda        soft: the step system; r_b the eliminated constraints' impulses
    M du    = s - sum_b G_b^T r_b - g^T lambda  rigid: the impulses back; s the sliding friction's
    C v - g du = target                         the rows

Each soft solve is linear in its constrained values and loads, so v_b = y0_b + Y_b du + Z_b lambda and
r_b = r0_b + R_b du + Q_b lambda, with (y0, r0) the solve at du = 0, lambda = 0, and the columns of (Y, R)
and (Z, Q) homogeneous solves (the step's load dropped) with the values G_b e_j, or the load C_b^T e_k;
only columns that touch b are solved for. Eliminating v and r leaves a small dense system in
(du, lambda):

    [ M + G^T R    G^T Q + g^T ] [du    ]   [ s - G^T r0        ]
    [ C Y - g      C Z         ] [lambda] = [ target - C y0     ]

(by reciprocity C Y = -(G^T Q)^T: it is a saddle point problem of the whole system's energy), as ArtiSynth
and SOFA solve rigid and FEM bodies together. Both sides agree on every impulse, so momentum is
exchanged exactly and the step is the implicit step of one mechanical system: light rigid bodies are not
overshot.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from softbody.integrator import Constraints, LinearSystem

from . import kernels

if TYPE_CHECKING:
    from .bullet import BodyDynamics

# compliance of the rows relative to their free diagonal (sum w^2 / M_ii over their nodes): keeps the dense
# system regular when two rows (or a row and an eliminated node constraint) hold the same motion, at no
# visible cost in accuracy
ROW_COMPLIANCE = 1e-9


@dataclass
class CoupledPart:
    """One soft body's eliminated constraints for a coupled solve.

    cons: its constraints (supports, attachments, node contacts), values at du = 0; G (len(cons), 3, n):
    the derivative of each constrained node's local values with respect to du (None: not coupled);
    extra (N, 3): an extra right-hand side (sliding friction impulses) or None; reuse: the system may keep
    its last factorisation (only values or extra changed since its last solve)."""

    system: LinearSystem
    cons: Constraints
    G: np.ndarray | None = None
    extra: np.ndarray | None = None
    reuse: bool = False

    def key(self) -> tuple[bytes, bytes, bytes]:
        frames = b"" if self.cons.frames is None else np.ascontiguousarray(self.cons.frames).tobytes()
        return self.cons.nodes.tobytes(), self.cons.mask.tobytes(), frames


@dataclass
class Rows:
    """Constraint rows with multipliers (m rows, s node slots each).

    part (m, s): index of the soft body (CoupledPart) of each slot, -1 for an unused slot; node (m, s);
    weight (m, s): the slot's weight (barycentric, negative on the second body of a soft-soft row);
    direction (m, 3): unit t_k; g (m, n): J_k^T t_k of the rigid point (zeros if none is coupled);
    target (m,): the row's value [m/s] at du = 0."""

    part: np.ndarray
    node: np.ndarray
    weight: np.ndarray
    direction: np.ndarray
    g: np.ndarray
    target: np.ndarray

    def __len__(self) -> int:
        return len(self.target)

    @classmethod
    def empty(cls, n: int = 0, slots: int = 3) -> "Rows":
        return cls(np.zeros((0, slots), np.int64), np.zeros((0, slots), np.int64), np.zeros((0, slots)),
                   np.zeros((0, 3)), np.zeros((0, n)), np.zeros(0))

    @classmethod
    def concat(cls, parts: list["Rows"], n: int) -> "Rows":
        parts = [r for r in parts if r is not None and len(r)]
        if not parts:
            return cls.empty(n)
        s = max(r.part.shape[1] for r in parts)

        def pad(a, fill):
            return np.pad(a, ((0, 0), (0, s - a.shape[1])), constant_values=fill)

        return cls(np.concatenate([pad(r.part, -1) for r in parts]), np.concatenate([pad(r.node, 0) for r in parts]),
                   np.concatenate([pad(r.weight, 0.0) for r in parts]), np.concatenate([r.direction for r in parts]),
                   np.concatenate([r.g for r in parts]), np.concatenate([r.target for r in parts]))

    def values(self, part: int, v: np.ndarray, only: np.ndarray | None = None) -> np.ndarray:
        """C_part v: (m,) for the soft velocities v (N, 3) of one part, (m, k) for k of them (k, N, 3); of the rows
        ``only`` (indices), if given."""
        rp, rn, rw, rd = self.part, self.node, self.weight, self.direction
        if only is not None:
            rp, rn, rw, rd = rp[only], rn[only], rw[only], rd[only]
        if kernels.ENABLED:  # row by row, compiled (integration.kernels)
            V = np.ascontiguousarray(v, dtype=float)
            out = np.empty((len(rp), 1 if V.ndim == 2 else len(V)))
            kernels.row_values(part, rp, rn, np.ascontiguousarray(rw, dtype=float), np.ascontiguousarray(rd, dtype=float),
                               V[None] if V.ndim == 2 else V, out)
            return out[:, 0] if V.ndim == 2 else out
        on = rp == part
        w = np.where(on, rw, 0.0)
        if v.ndim == 2:
            return np.einsum("ms,msi,mi->m", w, v[np.where(on, rn, 0)], rd)
        return np.einsum("ms,kmsi,mi->mk", w, v[:, np.where(on, rn, 0)], rd)

    def loads(self, ks: np.ndarray, part: int, n_nodes: int) -> np.ndarray:
        """C_part^T e_k (len(ks), N, 3): the unit impulses of rows ks on the nodes of ``part``."""
        f = np.zeros((len(ks), n_nodes, 3))
        on = self.part[ks] == part  # (k, s)
        j, slot = np.nonzero(on)
        np.add.at(f, (j, self.node[ks][j, slot]), self.weight[ks][j, slot, None] * self.direction[ks][j])
        return f

    def signatures(self, part: int) -> list[bytes]:
        """Per row, bytes that tell whether two rows act alike on ``part`` (its nodes, weights, direction)."""
        on = self.part == part
        table = np.concatenate([np.where(on, self.node, -1).astype(np.float64), np.where(on, self.weight, 0.0),
                                self.direction], axis=1)
        return [row.tobytes() for row in np.ascontiguousarray(table)]


@dataclass
class CoupledSystem:
    """The dense system H z = rhs of a coupled solve, z = (du (n,), lambda (m,)), and per part the solve at
    z = 0 (base: v, r) and its responses to the columns of z it depends on (columns: indices, Y, R)."""

    H: np.ndarray
    rhs: np.ndarray
    base: list[tuple[np.ndarray, np.ndarray]]
    columns: list[tuple]
    n: int

    @property
    def size(self) -> int:
        return len(self.rhs)

    def combine(self, z: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every part's velocities and reactions (v (N, 3), r (N, 3)) for the unknowns z."""
        out = list(self.base)
        for i, (cols, Y, R) in enumerate(self.columns):
            if len(cols):
                y0, r0 = out[i]
                w = z[cols]
                k = len(w)  # the weighted sums of the responses, as products with their flattened stacks
                out[i] = (y0 + (w @ Y.reshape(k, -1)).reshape(y0.shape),
                          r0 + (w @ R.reshape(k, -1)).reshape(r0.shape))
        return out


def generalized(cons: Constraints, r: np.ndarray, G: np.ndarray) -> np.ndarray:
    """G^T r: the generalized impulse (n,) of the reactions r (N, 3, local frames) of the constrained
    components of ``cons`` through G (len(cons), 3, n); (n, k) for k sets of reactions r (k, N, 3)."""
    if r.ndim == 2:
        return np.einsum("ca,can->n", np.where(cons.mask, r[cons.nodes], 0.0), G)
    return np.einsum("kca,can->nk", np.where(cons.mask, r[:, cons.nodes], 0.0), G)


class CoupledSolver:
    """Solves the constraint sets of several soft bodies at once, coupled through movable rigid bodies
    with mass matrix M (n, n) (None or n = 0: none) and through constraint rows.

    Lives for one step: it keeps each body's solve while its constraints, values and loads are unchanged,
    and its homogeneous responses while its constraint set is unchanged, so an active-set iteration costs
    a solve only for the bodies whose contacts changed, plus a small dense solve.
    """

    def __init__(self, M: np.ndarray | None = None):
        self.M = None if M is None or not M.size else np.asarray(M, float)
        self._bases: dict[int, tuple] = {}  # part -> (signature, system, (y0, r0))
        self._responses: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}  # (part, part key, column key) -> (y, r)
        self.homogeneous_solves = 0

    @property
    def n(self) -> int:
        return 0 if self.M is None else len(self.M)

    def solve(self, parts: list[CoupledPart], rows: Rows | None = None, slip: np.ndarray | None = None
              ) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray, np.ndarray]:
        """Velocities and reactions (v (N, 3), r (N, 3) local) per part, du (n,) and the rows' impulses (m,),
        with every row an equality.

        slip (n,): the generalized impulse s of forces on the rigid side that do not depend on du or lambda."""
        system = self.assemble(parts, rows, slip)
        if system.size == 0:
            return system.base, np.zeros(0), np.zeros(0)
        try:
            z = np.linalg.solve(system.H, system.rhs)
        except np.linalg.LinAlgError:  # a massless direction no constraint holds: the least-squares answer
            z = np.linalg.lstsq(system.H, system.rhs, rcond=None)[0]
        return system.combine(z), z[:self.n], z[self.n:]

    def assemble(self, parts: list[CoupledPart], rows: Rows | None = None, slip: np.ndarray | None = None
                 ) -> "CoupledSystem":
        """The dense system H z = rhs in z = (du, lambda) of the module doc, with the responses to rebuild
        every part's velocities and reactions from z (CoupledSystem.combine)."""
        out = [self._base(i, part) for i, part in enumerate(parts)]
        n, m = self.n, 0 if rows is None else len(rows)
        H = np.zeros((n + m, n + m))
        rhs = np.zeros(n + m)
        if n + m == 0:
            return CoupledSystem(H, rhs, out, [], n)
        if n:
            H[:n, :n] = self.M
            if slip is not None:
                rhs[:n] = slip
        if m:
            H[n:, :n] = -rows.g
            H[:n, n:] = rows.g.T
            rhs[n:] = rows.target
        columns = []  # per part: (column indices into (du, lambda), Y (k, N, 3), R (k, N, 3))
        for i, (part, (y0, r0)) in enumerate(zip(parts, out)):
            cols, Y, R = self._columns(i, part, rows)
            columns.append((cols, Y, R))
            coupled = part.G is not None and len(part.cons)
            if coupled:
                rhs[:n] -= generalized(part.cons, r0, part.G)
            if m:
                rhs[n:] -= rows.values(i, y0)
            if len(cols):
                if coupled:
                    H[:n, cols] += generalized(part.cons, R, part.G)
                if m:  # only the rows touching part i are not zero: their block alone (a pile: m / parts rows)
                    touch = np.flatnonzero((rows.part == i).any(axis=1))
                    H[np.ix_(n + touch, cols)] += rows.values(i, Y, touch)
        if m:
            # a row whose soft points cannot move (all held by eliminated constraints) is no constraint of
            # its own: its multiplier is zero; a tiny compliance on the others keeps H regular where rows
            # repeat a constraint. The scale: a row's diagonal if nothing held its points, sum w^2 / M_ii.
            free = np.zeros(m)
            for i, part in enumerate(parts):
                on = rows.part == i
                body = part.system.body
                mass = body.M_data[body.pattern.diag][np.where(on, rows.node, 0)]  # the mass matrix's diagonal
                free += np.where(on, rows.weight ** 2 / np.maximum(mass, 1e-300), 0.0).sum(axis=1)
            # A held row that moves a rigid body (a box on a fixed rim) stays: its scale is then the rigid side's,
            # the diagonal of g M^-1 g^T.
            held = np.diag(H)[n:] <= 1e-9 * free
            if n and held.any():
                g = rows.g[held]
                rigid = np.einsum("ij,ji->i", g, np.linalg.solve(self.M, g.T))
                free[held] = rigid
                held[held] = rigid <= 0.0
            if held.any():
                k = n + np.flatnonzero(held)
                H[k, :], H[:, k], rhs[k] = 0.0, 0.0, 0.0
                H[k, k] = 1.0
            k = np.arange(n, n + m)
            H[k, k] += ROW_COMPLIANCE * free  # on the diagonal only (np.diag would add a whole m x m matrix)
        return CoupledSystem(H, rhs, out, columns, n)

    def _base(self, i: int, part: CoupledPart) -> tuple[np.ndarray, np.ndarray]:
        """The solve of part i at du = 0 and lambda = 0, repeated only if its constraints, values or extra
        load changed."""
        sig = (part.key(), part.cons.value.tobytes(), None if part.extra is None else part.extra.tobytes())
        cached = self._bases.get(i)
        if cached is not None and cached[0] == sig and cached[1] is part.system:
            return cached[2]
        out = part.system.solve(part.cons, part.extra, reuse=part.reuse)
        self._bases[i] = (sig, part.system, out)
        return out

    def _columns(self, i: int, part: CoupledPart, rows: Rows | None) -> tuple[list[int], np.ndarray, np.ndarray]:
        """The columns of (du, lambda) that touch part i and its homogeneous responses to each (Y, R (k, N, 3)),
        solved anew (all new ones in one batched solve) only for columns not seen with the same constraint set."""
        n, key, N = self.n, part.key(), part.system.body.n_nodes
        cols, keys = [], []
        new_du, new_rows = [], []
        if part.G is not None and n and len(part.cons):
            G = np.where(part.cons.mask[:, :, None], part.G, 0.0)
            for j in np.flatnonzero(np.abs(G).max(axis=(0, 1), initial=0.0) > 0).tolist():
                ck = (i, key, ("du", G[:, :, j].tobytes()))
                if ck not in self._responses:
                    new_du.append((ck, G[:, :, j]))
                cols.append(j)
                keys.append(ck)
        if rows is not None and len(rows):
            sigs = rows.signatures(i)
            pending = set()
            for k in np.flatnonzero((rows.part == i).any(axis=1)).tolist():
                ck = (i, key, ("row", sigs[k]))
                if ck not in self._responses and ck not in pending:
                    new_rows.append((ck, k))
                    pending.add(ck)
                cols.append(n + k)
                keys.append(ck)
        if new_du:
            Y, R = part.system.responses(part.cons, values=np.array([g for _, g in new_du]))
            for (ck, _), y, r in zip(new_du, Y, R):
                self._responses[ck] = (y, r)
            self.homogeneous_solves += len(new_du)
        if new_rows:
            Y, R = part.system.responses(part.cons, loads=rows.loads(np.array([k for _, k in new_rows]), i, N))
            for (ck, _), y, r in zip(new_rows, Y, R):
                self._responses[ck] = (y, r)
            self.homogeneous_solves += len(new_rows)
        if not cols:
            return [], np.zeros((0, N, 3)), np.zeros((0, N, 3))
        return cols, np.array([self._responses[ck][0] for ck in keys]), np.array([self._responses[ck][1] for ck in keys])


@dataclass
class RigidCoupling:
    """The movable rigid bodies of one step: their dynamics at the start (bullet.BodyDynamics), their slices of
    the stacked du, the block-diagonal mass matrix and the point Jacobians of contacts and attachments."""

    dynamics: dict[int, BodyDynamics]
    offset: dict[int, int]
    n: int

    @classmethod
    def of(cls, dynamics: dict[int, BodyDynamics]) -> "RigidCoupling":
        offset, n = {}, 0
        for b, dyn in dynamics.items():
            offset[b] = n
            n += dyn.n
        return cls(dynamics, offset, n)

    def mass_matrix(self) -> np.ndarray:
        M = np.zeros((self.n, self.n))
        for b, dyn in self.dynamics.items():
            o = self.offset[b]
            M[o:o + dyn.n, o:o + dyn.n] = dyn.M
        return M

    def jacobians(self, adapter, rigid: np.ndarray, link: np.ndarray,
                  points: np.ndarray) -> np.ndarray:
        """Point Jacobians (m, 3, n) of rigid points (body ids (m,), links (m,), world points (m, 3));
        zero rows for points on bodies that are not coupled."""
        J = np.zeros((len(rigid), 3, self.n))
        for b, dyn in self.dynamics.items():
            o = self.offset[b]
            on_body = rigid == b
            for lk in np.unique(link[on_body]).tolist():
                sel = on_body & (link == lk)
                J[sel, :, o:o + dyn.n] = adapter.point_jacobians(dyn, lk, points[sel])
        return J


@dataclass
class RigidWarmStart:
    """The coupled rigid bodies' velocity change du of the last coupled solve, per body (its pybullet id): where the
    next solve starts. In a steady grasp or a body at rest du is nearly the same from step to step (the contacts'
    impulses against the motors' and gravity's); from du = 0 the solve's first iterate drives the links through the
    soft body at their free motion and Newton spends its iterations finding which rows hold (a Panda gripping with
    20 N: 31 iterations a solve from zero, 14 from the last du). A body whose unknowns changed in number starts from 0."""

    kept: dict[int, np.ndarray] = field(default_factory=dict)

    def guess(self, coupling: RigidCoupling) -> np.ndarray:
        """(n,) the starting du of a solve over ``coupling``'s bodies."""
        du = np.zeros(coupling.n)
        for b, o in coupling.offset.items():
            last = self.kept.get(b)
            if last is not None and len(last) == coupling.dynamics[b].n:
                du[o:o + len(last)] = last
        return du

    def keep(self, coupling: RigidCoupling, du: np.ndarray) -> None:
        """Keep a solve's du (n,) per body (only the bodies of this step: the others start from 0 when they come
        back)."""
        self.kept = {b: du[o:o + coupling.dynamics[b].n].copy() for b, o in coupling.offset.items()}
