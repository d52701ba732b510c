"""One backward Euler step (SPEC.md section 3) with stiffness warping and exact constraints.

Data flows one way through a step:

    positions -> rotations R_e -> K' = sum R K R^T, f_el = -sum R K (R^T x - X)
    -> A = (1 + h alpha) M + (h beta + h^2) K',  b = M v + h (f_el + f_ext)
    -> constraints (supports; contacts from the integration layer) -> solve A v' = b
    -> x' = x + h v'

Constraints are per-node velocity conditions in a node frame T (columns = local axes): the
components picked by a mask are set exactly (a fixed node: all three, identity frame; a contact:
the normal component). They are applied by eliminating those rows and columns inside the fixed
sparsity pattern, so the symbolic factorisation is computed once for the body's lifetime.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .body import FemBody
from .linsolve import SpdSolver


@dataclass
class Constraints:
    """Velocity (or displacement) conditions for one solve.

    nodes (m,) node ids; mask (m, 3) which local components are constrained; value (m, 3) their
    target values in the local frame; frames (m, 3, 3) local axes as columns (None: identity).
    """

    nodes: np.ndarray
    mask: np.ndarray
    value: np.ndarray
    frames: np.ndarray | None = None

    @classmethod
    def empty(cls) -> "Constraints":
        return cls(np.zeros(0, dtype=np.int64), np.zeros((0, 3), dtype=bool), np.zeros((0, 3)))

    @classmethod
    def full(cls, nodes: np.ndarray, value: np.ndarray) -> "Constraints":
        """All three components of ``nodes`` set to ``value`` (m, 3), identity frames."""
        return cls(np.asarray(nodes, dtype=np.int64), np.ones((len(nodes), 3), dtype=bool), np.asarray(value, float))

    def __len__(self) -> int:
        return len(self.nodes)


def merge(first: Constraints, second: Constraints) -> Constraints:
    """Union of two constraint sets; for a node in both, ``first`` wins."""
    keep = ~np.isin(second.nodes, first.nodes)
    if not keep.any():
        return first
    eye = lambda c: c.frames if c.frames is not None else np.broadcast_to(np.eye(3), (len(c), 3, 3))
    frames = None
    if first.frames is not None or second.frames is not None:
        frames = np.concatenate([eye(first), eye(second)[keep]])
    return Constraints(np.concatenate([first.nodes, second.nodes[keep]]),
                       np.concatenate([first.mask, second.mask[keep]]),
                       np.concatenate([first.value, second.value[keep]]), frames)


@dataclass
class LinearSystem:
    """A (block data, nnzb x 3 x 3) and right-hand side b (N, 3) of one body, solvable under constraints."""

    body: FemBody
    A: np.ndarray
    b: np.ndarray
    solver: SpdSolver
    stats: dict = field(default_factory=dict)

    def solve(self, cons: Constraints, extra_rhs: np.ndarray | None = None,
              reuse: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Solve A y = b (+ extra_rhs, (N, 3) global) with the constrained components of y fixed to their values.

        Returns y (N, 3) in global coordinates and the constraint reactions r = A y - b (N, 3)
        expressed in each constrained node's local frame (zero elsewhere). For a step system,
        r / h is the constraint force [N]. reuse=True keeps the last factorisation: valid when only
        extra_rhs or the constrained values changed since the previous call, not the constrained set.
        """
        pat = self.body.pattern
        N = pat.n_nodes
        A, b = self.A, self.b if extra_rhs is None else self.b + extra_rhs
        T = None
        if cons.frames is not None and len(cons):
            T = np.broadcast_to(np.eye(3), (N, 3, 3)).copy()
            T[cons.nodes] = cons.frames
            rotated = np.zeros(N, dtype=bool)
            rotated[cons.nodes] = True
            A = A.copy()
            rows = rotated[pat.block_row]
            cols = rotated[pat.indices]
            A[rows] = np.swapaxes(T[pat.block_row[rows]], 1, 2) @ A[rows]
            A[cols] = A[cols] @ T[pat.indices[cols]]
            b = np.einsum("nji,nj->ni", T, b)
        mask = np.zeros((N, 3), dtype=bool)
        value = np.zeros((N, 3))
        mask[cons.nodes] = cons.mask
        value[cons.nodes] = np.where(cons.mask, cons.value, 0.0)
        data = pat.upper_data(A)
        mflat = mask.ravel()
        if mflat.any():
            rhs = b - pat.matvec(A, value)
            scale = float(np.mean(data[pat.up_diag]))
            data = data.copy()
            data[mflat[pat.up_row] | mflat[pat.up_col]] = 0.0
            data[pat.up_diag[mflat]] = scale
            rhs = rhs.ravel()
            rhs[mflat] = scale * value.ravel()[mflat]
        else:
            rhs = b.ravel()
        if not reuse:
            self.solver.factorize(data)
            self.stats["factorizations"] = self.stats.get("factorizations", 0) + 1
        y = self.solver.solve(rhs).reshape(N, 3)
        y[mask] = value[mask]  # exact, not up to round-off
        reaction = np.where(mask, pat.matvec(A, y) - b, 0.0)
        if T is not None:
            y = np.einsum("nij,nj->ni", T, y)
        return y, reaction


def step_system(body: FemBody, h: float, f_ext: np.ndarray, solver: SpdSolver) -> LinearSystem:
    """Assemble the backward Euler system (M + h C + h^2 K') v' = M v + h (f_el + f_ext) at the current state."""
    alpha, beta = body.damping
    x, v = body.positions, body.velocities
    R = body.rotations(x)
    K = body.pattern.assemble(body.warped_stiffness(R))
    f_el = body.scatter_nodal(body.element_forces(x, R))
    M = body.M_blocks
    A = (1.0 + h * alpha) * M + (h * beta + h * h) * K
    b = body.pattern.matvec(M, v) + h * (f_el + f_ext)
    return LinearSystem(body, A, b, solver)


def support_constraints(body: FemBody, t_next: float, h: float) -> Constraints:
    """Velocity constraints that put fixed and prescribed nodes exactly where they must be at t_next."""
    nodes, vel = body.constrained_targets(t_next, h)
    return Constraints.full(nodes, vel)
