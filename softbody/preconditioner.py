"""The iterative solver's preconditioner: one factorised system matrix, reused over many steps, and
corrected exactly for the constraints that it does not eliminate.

P is the system matrix A of an earlier step with the supports' components eliminated (rows and columns
zeroed, a scaled identity on the diagonal; see :func:`softbody.integrator.factorize_constrained`),
factorised once. A later solve needs the inverse of the current A restricted to its free components.
The integrator follows the rotation of each node since the factorisation by conjugating P with per-node
frames; this module removes the other constrained directions (contacts) exactly, by a Schur complement.

For constrained unit directions E (n_dof, m) in P's frames, the inverse of P restricted to the
complement of E is

    P^-1 - P^-1 E S^-1 E^T P^-1,   S = E^T P^-1 E (m, m).

P^-1 E only needs P^-1 of the three unit vectors of each constrained node: one 3-column solve per node,
kept for the life of the factorisation (within a memory cap). A change of the contact set then costs no
refactorisation and no extra iterations, and a node that stays in contact costs nothing after its first solve;
contacts beyond the cap are projected out by the PCG, at the cost of iterations.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import InvalidInputError
from .linsolve import SpdSolver


@dataclass
class ConstraintCorrection:
    """The Schur-complement correction for constrained directions at M nodes.

    rows (3M,): the nodes' dofs; Y (n_dof, K): cached columns of P^-1, among them those of the nodes' unit vectors,
    columns ``cols`` (3M,) of Y (None: Y holds exactly those, in order); G (3M, 3M): B S^-1 B^T, with B (3M, m) the
    m constrained unit directions at those dofs in P's frames and S = B^T Y[rows, cols] B, so that
    P^-1 E S^-1 E^T P^-1 g = Y[:, cols] G (P^-1 g)[rows].
    """

    rows: np.ndarray
    Y: np.ndarray
    G: np.ndarray
    cols: np.ndarray | None = None

    def apply(self, u: np.ndarray) -> np.ndarray:
        """u = P^-1 g (n_dof,) -> (P restricted to the complement of E)^-1 g, in place."""
        c = (self.G @ u[self.rows]).astype(self.Y.dtype, copy=False)
        if self.cols is not None:  # the product over all cached columns, the others' coefficients zero (no copy)
            z = np.zeros(self.Y.shape[1], dtype=self.Y.dtype)
            z[self.cols] = c
            c = z
        u -= self.Y @ c
        return u


#: a refactorisation's savings recur over the solves after it: it is bought once the iterations spent beyond a fresh
#: factor's reach 1/REFACTOR_HORIZON of its cost. Measured on the sheet-on-sphere against the earlier fixed rule
#: (a refactorisation after any solve of more than 3 iterations): tet10 9x9x2, 200 steps, 695 iterations and 7
#: factorisations against 672 and 8 (1: 763 and 5; 8: 672 and 8); 72k tet4 nodes, steps 9-15 into the impact, 76 s
#: against 133 s (1: 58 s, 8: 78 s): the small sheets keep their cost, the large ones refactorise rarely
REFACTOR_HORIZON = 4.0

#: the correction's cached columns hold at most this many bytes per node of the body (Preconditioner.column_cap):
#: 64 nodes' columns in single precision (IterativeSettings.max_corrected_nodes), whatever the body's size (at 72k
#: nodes, 4 x 64 nodes' columns took 0.66 GB, 9 kB per node; the products read them in place, GATHER_BYTES)
COLUMN_BYTES_PER_NODE = 2304

#: the columns of the nodes a correction uses are gathered into a copy of their own (one product over them alone) only
#: where they are fewer than half the cached ones and the copy is at most this many bytes; else the product runs over
#: every cached column (at most twice the work, or a fraction of a PCG iteration on a large body) and nothing is copied
#: (at 72k nodes the copy of 61 nodes' columns took 150 MB, 2.1 kB per node, beside the cache's 158 MB)
GATHER_BYTES = 16 * 2**20

#: new columns are solved for this many nodes at a time (the solve's right-hand sides and answers, in double, are
#: the transient memory: 3 x 8 nodes' columns of a 72k-node body take 41 MB)
COLUMN_BATCH = 8


@dataclass
class Preconditioner:
    """The last factorised system (per body): its solver, the constraint frames T and node rotations Q
    it was factorised with, the nodes it eliminates, cached P^-1 columns, and counters.

    stale: refactorise before the next solve. ``eliminated`` (N,) bool: nodes with components
    eliminated in P (None before the first factorisation). ``spent``: the work since the factorisation
    that a fresh one would have saved, in PCG iterations beyond a fresh factor's count; a refactorisation is
    due once it reaches :meth:`refactor_cost` (a rent-or-buy rule).
    """

    solver: SpdSolver
    T: Any
    Q: np.ndarray | None
    stale: bool = True
    factorizations: int = 0
    iterations: int = 0
    eliminated: np.ndarray | None = None
    column_nodes: int = 0  # nodes whose P^-1 columns were solved for, over all factorisations
    previous_velocities: np.ndarray | None = None  # at the start of the last step, for the PCG's warm start
    products: int = 0  # products with A in the current (after it: the last) step, for IterativeSettings.operator
    solved: bool | None = None  # whether the last step's system was solved by its own PCG (None: no system yet; False:
    # a coupled solve took its matrix whole), for IterativeSettings.operator
    spent: float = 0.0  # PCG iterations' worth spent since the factorisation that a fresh one saves (see above)
    fewest: int | None = None  # the fewest iterations of a full solve since the factorisation
    last_iterations: int | None = None  # of the last full solve
    _slot: np.ndarray | None = None  # (N,) first column of each node's P^-1 columns in _Y, -1: none yet
    _Y: np.ndarray | None = None  # (n_dof, 3 * cached nodes), P^-1 of the cached nodes' unit vectors (a view of _store)
    _store: np.ndarray | None = None  # (n_dof, 3 * column_cap): room for the columns, taken as they fill
    _last: tuple = (None, None)  # (the columns' slots, their gathered copy) of the last call that gathered

    @property
    def cached_nodes(self) -> int:
        """Nodes whose P^-1 columns are cached for the current factorisation."""
        return 0 if self._Y is None else self._Y.shape[1] // 3

    # the fields that a saved state holds (the rest, _last, is a gather made again from these)
    _STATE = ("T", "Q", "stale", "factorizations", "iterations", "eliminated", "column_nodes", "previous_velocities",
              "products", "solved", "spent", "fewest", "last_iterations", "_slot", "_Y")

    def save_state(self) -> dict:
        """Everything the next steps read of this preconditioner, copied: its frames, counters, warm start, cached
        columns and the values its solver factorised (softbody.state)."""
        out = {name: copy.deepcopy(getattr(self, name)) for name in self._STATE}
        out["factor"] = self.solver.factor_values()
        out["backend"] = self.solver.backend
        out["orderings"] = sorted(self.solver.ORDERINGS)  # the orderings its analysis tried (the same again)
        return out

    def load_state(self, state: dict) -> None:
        """Take over a state of :meth:`save_state` (from this body's preconditioner with the same backend): the
        factor is made again from the saved values, the same to the bit."""
        if state["backend"] != self.solver.backend:
            raise InvalidInputError(f"a preconditioner state of backend {state['backend']!r} for one of {self.solver.backend!r}")
        for name in self._STATE:
            if name in state:  # (a state saved before a field existed keeps its default)
                setattr(self, name, copy.deepcopy(state[name]))
        self._last, self._store = (None, None), None  # (the loaded columns are copied into new room when more come)
        if "orderings" in state:
            self.solver.ORDERINGS = {k: type(self.solver).ORDERINGS[k] for k in state["orderings"]}
        self.solver.refactorize(state["factor"])

    def refactor_cost(self) -> float | None:
        """The work that buys a refactorisation, in PCG iterations beyond a fresh preconditioner's (each about one
        solve with P): a numeric factorisation's cost from the backend's own counts (SpdSolver.costs) over
        REFACTOR_HORIZON, at least 1; None if the backend does not count them (then the iteration count alone
        decides, IterativeSettings)."""
        costs = self.solver.costs()
        if costs is None or costs[1] <= 0:
            return None
        return max(1.0, costs[0] / costs[1] / REFACTOR_HORIZON)

    def drop_columns(self) -> None:
        """Let the cached columns go (before a refactorisation, which makes them stale: its peak then holds the new
        factor without the old columns beside it, 158 MB at 72k tet4 nodes)."""
        if self._slot is not None:
            self._slot = np.full(len(self._slot), -1)
        self._Y, self._store, self._last = None, None, (None, None)

    def factorized(self, T, Q: np.ndarray | None, eliminated: np.ndarray) -> None:
        """Record a new factorisation: its frames, node rotations and eliminated nodes; drop cached columns."""
        self.T, self.Q, self.eliminated = T, Q, eliminated
        self.stale = False
        self.spent, self.fewest = 0.0, None
        self.factorizations += 1
        self._slot, self._Y, self._store, self._last = np.full(len(eliminated), -1), None, None, (None, None)

    def columns(self, nodes: np.ndarray, cap: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
        """P^-1 of the unit vectors of ``nodes`` (M,): (Y, cols), Y (n_dof, K) cached columns and cols (3M,) the nodes'
        among them, or cols None where Y is a copy of exactly the nodes' columns (GATHER_BYTES); solves for the
        nodes not cached yet (room is made for ``cap`` nodes' columns at once)."""
        new = nodes[self._slot[nodes] < 0]
        if len(new):
            n_dof = self.solver.n
            start = 0 if self._Y is None else self._Y.shape[1]
            end = start + 3 * len(new)
            if self._store is None or self._store.shape[1] < end:
                # room for the cap at once, not grown by copies: np.empty's pages are taken only as columns fill
                store = np.empty((n_dof, max(end, 3 * cap)), dtype=self.solver.dtype, order="F")
                if start:
                    store[:, :start] = self._Y
                self._store = store
            for a in range(0, len(new), COLUMN_BATCH):  # in batches: the solve's work arrays stay small
                batch = new[a:a + COLUMN_BATCH]
                E = np.zeros((n_dof, 3 * len(batch)), order="F")
                E[(3 * batch[:, None] + np.arange(3)).ravel(), np.arange(3 * len(batch))] = 1.0
                self._store[:, start + 3 * a:start + 3 * (a + len(batch))] = self.solver.solve(E).reshape(n_dof, -1)
            self._Y = self._store[:, :end]
            self._slot[new] = start + 3 * np.arange(len(new))
            self.column_nodes += len(new)
        slots = self._slot[nodes]
        cols = (slots[:, None] + np.arange(3)).ravel()
        K = self._Y.shape[1]
        if 2 * len(cols) >= K or self._Y.shape[0] * len(cols) * self._Y.itemsize > GATHER_BYTES:
            self._last = (None, None)
            return self._Y, cols
        if self._last[0] is None or not np.array_equal(self._last[0], slots):  # else the same gather as last time
            self._last = (slots, self._Y[:, cols])
        return self._last[1], None

    def column_cap(self, limit: int) -> int:
        """The most nodes whose columns are cached at once: 4 x ``limit`` (IterativeSettings.max_corrected_nodes), and
        within COLUMN_BYTES_PER_NODE of memory per node of the body (each cached node holds 3 columns of 3N entries)
        unless that is below ``limit``."""
        within = int(COLUMN_BYTES_PER_NODE // (9 * np.dtype(self.solver.dtype).itemsize))
        return max(limit, min(4 * limit, within))

    def correctable(self, nodes: np.ndarray, limit: int, cap: int) -> np.ndarray:
        """Of ``nodes`` (ascending), the at most ``limit`` to correct: those whose columns are cached first, then
        new ones while the cache holds at most ``cap`` nodes."""
        cached = self._slot[nodes] >= 0
        room = max(0, min(limit - int(cached.sum()), cap - self.cached_nodes))
        return np.sort(np.r_[nodes[cached][:limit], nodes[~cached][:room]])

    def correction(self, nodes: np.ndarray, mask: np.ndarray, frames: np.ndarray, cap: int = 0) -> ConstraintCorrection:
        """The correction for constrained components ``mask`` (M, 3) of ``nodes`` (M,), whose local axes
        in P's frames are the columns of ``frames`` (M, 3, 3) (``cap``: see :meth:`columns`).

        Raises numpy.linalg.LinAlgError if S is not positive definite (P is then no preconditioner for
        this constraint set)."""
        M = len(nodes)
        Y, cols = self.columns(nodes, cap)
        rows = (3 * nodes[:, None] + np.arange(3)).ravel()
        j, i = np.nonzero(mask)  # constraint c: node j[c], local axis i[c]
        B = np.zeros((3 * M, len(j)))
        B[3 * j[:, None] + np.arange(3), np.arange(len(j))[:, None]] = frames[j, :, i]
        S = B.T @ ((Y[rows] if cols is None else Y[np.ix_(rows, cols)]).astype(float) @ B)
        L = np.linalg.cholesky(0.5 * (S + S.T))  # LinAlgError unless positive definite
        X = np.linalg.solve(L, B.T)  # G = B S^-1 B^T = X^T X
        return ConstraintCorrection(rows, Y, X.T @ X, cols)
