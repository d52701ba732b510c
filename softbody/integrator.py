"""One backward Euler step (docs/method.md section 3) with stiffness warping and exact constraints.

Data flows one way through a step:

    positions -> rotations R_e -> K' = sum R K R^T assembled (FemBody.warped_stiffness_upper)
    -> A = (1 + h alpha) M + (h beta + h^2) K',  f_el = -K' (x - c) + sum R K X
    -> b = M v + h (f_el + f_ext) (+ h alpha M v_r: damping spares rigid motion, FemBody.rigid_damping_relief)
    -> constraints (supports; contacts from the integration layer)
    -> solve A v' = b -> x' = x + h v'

(The iterative solve only needs products with A; for tet10 it takes K' y element by element from
the rotated gradients instead of assembling K', see IterativeSettings.operator.)

Constraints are per-node velocity conditions in a node frame T (columns = local axes): the
components picked by a mask are set exactly (a fixed node: all three, identity frame; a contact:
the normal component). They are eliminated inside the fixed sparsity pattern (rows and columns
zeroed, a scaled identity on the diagonal), so the symbolic factorisation runs once per body.

Two ways to solve, same answer to the stated tolerance:
- ``DirectSystem``: factorise A every solve (the reference);
- ``IterativeSystem``: conjugate gradients on the free components (one sparse product with A
  per iteration), warm-started from the velocity extrapolated from the last two steps and
  preconditioned by the last factorised system matrix (single precision, supports eliminated),
  conjugated with per-node rotations, with the other constrained nodes (contacts) removed exactly
  by a Schur complement (softbody.preconditioner); it refactorises only when the iterations grow.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
import scipy.sparse as sp

from . import kernels
from .body import FemBody
from .errors import InvalidInputError, SolverError
from .linsolve import SpdSolver
from .preconditioner import ConstraintCorrection, Preconditioner
from .solvers import new_preconditioner


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

    def dense(self, n_nodes: int) -> tuple["NodeFrames | None", np.ndarray, np.ndarray]:
        """Per-node arrays: frames (NodeFrames, or None if all identity), mask (N, 3), value (N, 3)."""
        T = None
        if self.frames is not None and len(self):
            rotated = (self.frames.reshape(-1, 9) != _EYE9).any(axis=1)
            if rotated.any():
                T = NodeFrames(self.nodes[rotated], self.frames[rotated])
        mask = np.zeros((n_nodes, 3), dtype=bool)
        value = np.zeros((n_nodes, 3))
        mask[self.nodes] = self.mask
        value[self.nodes] = np.where(self.mask, self.value, 0.0)
        return T, mask, value


_EYE9 = np.eye(3).ravel()


def _any_component(mask: np.ndarray) -> np.ndarray:
    """(N,) whether any of a node's three components is set in mask (N, 3) (numpy's any over an axis costs more)."""
    return mask[:, 0] | mask[:, 1] | mask[:, 2]


def merge(first: Constraints, second: Constraints) -> Constraints:
    """Union of two constraint sets; for a node in both, ``first`` wins."""
    keep = ~np.isin(second.nodes, first.nodes)
    if not keep.any():
        return first
    frames = None
    if first.frames is not None or second.frames is not None:
        eye = lambda c: c.frames if c.frames is not None else np.broadcast_to(np.eye(3), (len(c), 3, 3))
        frames = np.concatenate([eye(first), eye(second)[keep]])
    return Constraints(np.concatenate([first.nodes, second.nodes[keep]]),
                       np.concatenate([first.mask, second.mask[keep]]),
                       np.concatenate([first.value, second.value[keep]]), frames)


#: multigrid's iteration counts on the same hierarchy spread with the right-hand side by this fraction of the fewest (a
#: 41 x 4 x 4-node tet4 bar, six random loads: 65-69 iterations): counts within it are what a fresh set-up needs too,
#: not work that buys one (softbody.preconditioner's rent-or-buy rule)
MULTIGRID_SPREAD = 0.1
#: the trial solves' default tolerance with multigrid (IterativeSettings.loose_tol): the 72k-node tet4 sheet through the
#: impact (steps 11-22, the same active sets) took 20-25 iterations a step with 5e-2, 25-34 with 1e-2, 33-45 with 1e-3
#: (a confirmation from 5e-2 costs 11-19 iterations, the trials 4-8 together)
LOOSE_MULTIGRID = 5e-2


class Timings(dict):
    """Seconds by phase, accumulated over a step (rotations, forces, assembly, factorize, solve, and the phases a
    caller opens around them): exclusive, a phase entered inside another counts to the inner one only, so that the
    phases add up to the wall time and nothing is subtracted afterwards. ``timed`` opens and closes them."""

    __slots__ = ("_open",)

    def __init__(self, *args, **kw):
        super().__init__(*args, **kw)
        self._open: list[list] = []  # [phase, tic] of the open phases, innermost last

    def enter(self, phase: str) -> None:
        now = time.perf_counter()
        if self._open:  # the enclosing phase pauses
            outer = self._open[-1]
            self[outer[0]] = self.get(outer[0], 0.0) + now - outer[1]
        self._open.append([phase, now])

    def leave(self) -> None:
        now = time.perf_counter()
        phase, tic = self._open.pop()
        self[phase] = self.get(phase, 0.0) + now - tic
        if self._open:  # and resumes
            self._open[-1][1] = now


class timed:
    """``with timed(timings, phase):`` adds the wall time of the block to timings[phase] (nothing when timings is
    None; exclusive of the phases nested in it when timings is a :class:`Timings`). A class, not a generator context
    manager: a step enters a dozen of these, and contextlib's costs about 3 us each."""

    __slots__ = ("timings", "phase", "tic")

    def __init__(self, timings: dict | None, phase: str):
        self.timings, self.phase = timings, phase

    def __enter__(self) -> None:
        if isinstance(self.timings, Timings):
            self.timings.enter(self.phase)
        elif self.timings is not None:
            self.tic = time.perf_counter()

    def __exit__(self, *exc) -> None:
        if isinstance(self.timings, Timings):
            self.timings.leave()
        elif self.timings is not None:
            self.timings[self.phase] = self.timings.get(self.phase, 0.0) + time.perf_counter() - self.tic


@dataclass
class NodeFrames:
    """Local frames R (m, 3, 3) (axes as columns) at distinct nodes (m,); the identity at all others."""

    nodes: np.ndarray
    R: np.ndarray

    def dense(self, n_nodes: int) -> np.ndarray:
        T = np.broadcast_to(np.eye(3), (n_nodes, 3, 3)).copy()
        T[self.nodes] = self.R
        return T


Frames = NodeFrames | np.ndarray | None  # sparse frames, per-node frames (N, 3, 3), or identity


def _per_node(T: Frames, x: np.ndarray, spec: str) -> np.ndarray:
    """Apply per-node 3x3 frames to x (..., N, 3) by the einsum ``spec`` (T^T x or T x); None: identity."""
    if T is None:
        return x
    if isinstance(T, NodeFrames):
        y = x.copy()
        y[..., T.nodes, :] = np.einsum(spec, T.R, x[..., T.nodes, :])
        return y
    if kernels.ENABLED and x.ndim == 2:  # one vector per node: a compiled loop (einsum costs 8x at 1445 nodes)
        out = np.empty(x.shape)
        kernels.frames_apply(np.arange(len(x)), np.ascontiguousarray(T, dtype=float),
                             np.ascontiguousarray(x, dtype=float), spec == _TO_LOCAL, out)
        return out
    return np.einsum(spec, T, x)


_TO_LOCAL, _TO_GLOBAL = "nji,...nj->...ni", "nij,...nj->...ni"


def to_local(T: Frames, x: np.ndarray) -> np.ndarray:
    """T^T x per node for x (..., N, 3)."""
    return _per_node(T, x, _TO_LOCAL)


def to_global(T: Frames, y: np.ndarray) -> np.ndarray:
    """T y per node for y (..., N, 3)."""
    return _per_node(T, y, _TO_GLOBAL)


def _frames_at(T: Frames, nodes: np.ndarray, n_nodes: int) -> np.ndarray:
    """The frames (M, 3, 3) of ``nodes`` (M,) among n_nodes."""
    if T is None:
        return np.broadcast_to(np.eye(3), (len(nodes), 3, 3))
    if isinstance(T, NodeFrames):
        T = T.dense(n_nodes)
    return T[nodes]


def factorize_constrained(body: FemBody, A: np.ndarray, T: NodeFrames | None, mask: np.ndarray,
                          solver: SpdSolver, timings: Timings | None = None) -> tuple[np.ndarray, float]:
    """Factorise T^T A T with the masked components eliminated (identity * scale on the diagonal).

    A: block data (nnzb, 3, 3). Returns the rotated block data (for products) and the scale.
    """
    pat = body.pattern
    if kernels.ENABLED:  # the same arithmetic, block by block and entry by entry (softbody.kernels)
        frame_of = np.full(pat.n_nodes, -1)
        if T is not None:
            frame_of[T.nodes] = np.arange(len(T.nodes))
        R = _NO_FRAMES if T is None else np.ascontiguousarray(T.R, dtype=float)
        return _factorize_compiled(body, A, frame_of, R, T is not None, mask, solver, timings)
    if T is not None:
        A = A.copy()
        where = np.full(pat.n_nodes, -1)
        where[T.nodes] = np.arange(len(T.nodes))
        rows, cols = where[pat.block_row] >= 0, where[pat.indices] >= 0
        A[rows] = np.swapaxes(T.R[where[pat.block_row[rows]]], 1, 2) @ A[rows]
        A[cols] = A[cols] @ T.R[where[pat.indices[cols]]]
    data = pat.upper_data(A)
    scale = float(np.mean(data[pat.up_diag]))
    mflat = mask.ravel()
    if mflat.any():
        data = data.copy()
        data[mflat[pat.up_row] | mflat[pat.up_col]] = 0.0
        data[pat.up_diag[mflat]] = scale
    with timed(timings, "factorize"):
        solver.factorize(data)
    return A, scale


_NO_FRAMES = np.zeros((0, 3, 3))


def _factorize_compiled(body: FemBody, A: np.ndarray, frame_of: np.ndarray, R: np.ndarray, turned: bool,
                        mask: np.ndarray, solver: SpdSolver, timings: Timings | None) -> tuple[np.ndarray, float]:
    """factorize_constrained by kernels: frame_of (N,) each node's row in the frames R (m, 3, 3) (-1: identity);
    turned: whether any node turns (else A is used as it is)."""
    pat = body.pattern
    A = np.ascontiguousarray(A, dtype=float)
    if turned:
        rotated = np.empty(A.shape)
        kernels.rotate_blocks(A, pat.block_row, pat.indices, frame_of, R, rotated)
        A = rotated
    data = np.empty(len(pat.up_gather))
    scale = kernels.constrained_upper(A.reshape(-1), pat.up_gather, pat.up_row, pat.up_col, pat.up_diag,
                                      mask.reshape(-1), data)
    with timed(timings, "factorize"):
        solver.factorize(data)
    return A, scale


@dataclass
class DirectSystem:
    """Assembled A (block data) and b (N, 3); every solve factorises (unless reuse) and solves exactly."""

    iterative = False  # solves are exact (``loose`` is ignored)
    trials_pay = False  # (an exact solve is the same whether trial or final)
    confirmation_ends_switching = False  # (no trials: nothing to confirm)

    body: FemBody
    A: np.ndarray
    b: np.ndarray
    solver: SpdSolver
    stats: dict = field(default_factory=dict)
    timings: Timings | None = None
    rotations: np.ndarray | None = None  # (E, 3, 3): the warped step's element rotations it was built with

    def solve(self, cons: Constraints, extra_rhs: np.ndarray | None = None,
              reuse: bool = False, homogeneous: bool = False, loose: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Solve A y = b (+ extra_rhs, (N, 3)) with the constrained components of y fixed to their values.

        Returns y (N, 3) in global coordinates and the constraint reactions r = A y - b (N, 3)
        in each constrained node's local frame (zero elsewhere); for a step system r / h is the
        constraint force [N] (``loose`` asks an iterative system for a trial solve; this one is exact anyway).
        reuse=True keeps the last factorisation: valid when only extra_rhs
        or the constrained values changed since the previous call, not the constrained set.
        homogeneous=True drops the step's own load b (extra_rhs alone is the load): the response to the
        constrained values and extra_rhs alone, for a coupling that makes them unknowns.
        """
        if not self.solver.factorization.exact:
            raise InvalidInputError(f"a direct solve needs an exact backend, not {self.solver.backend!r} (a "
                                    "preconditioner only: for direct solves 'auto' chooses one)")
        if kernels.ENABLED:  # the same arithmetic in a few compiled passes (softbody.kernels)
            return self._solve_compiled(cons, extra_rhs, reuse, homogeneous)
        pat = self.body.pattern
        T, mask, value = cons.dense(pat.n_nodes)
        load = np.zeros_like(self.b) if homogeneous else self.b
        b = to_local(T, load if extra_rhs is None else load + extra_rhs)
        if not reuse or getattr(self, "_rotated", None) is None:
            self._rotated, self._scale = factorize_constrained(self.body, self.A, T, mask, self.solver, self.timings)
            self.stats["factorizations"] = self.stats.get("factorizations", 0) + 1
        A, scale = pat.to_bsr(self._rotated), self._scale
        rhs = b - (A @ value.reshape(-1)).reshape(-1, 3)
        rhs[mask] = scale * value[mask]
        with timed(self.timings, "solve"):
            y = self.solver.solve(rhs.ravel()).reshape(-1, 3)
        y[mask] = value[mask]  # exact, not up to round-off
        reaction = np.where(mask, (A @ y.reshape(-1)).reshape(-1, 3) - b, 0.0)
        return to_global(T, y), reaction

    def _solve_compiled(self, cons: Constraints, extra_rhs: np.ndarray | None, reuse: bool, homogeneous: bool
                        ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`solve` by kernels: the constraints spread over the nodes (kernels.local_constraints), the loads
        turned into their frames, the eliminated factorisation, the right-hand side with A value over the held
        nodes' blocks only (kernels.constrained_rhs), and the held values and reactions after the solve
        (kernels.constrained_finish, the products over the held nodes' rows only)."""
        pat, N = self.body.pattern, self.body.pattern.n_nodes
        R = _NO_FRAMES if cons.frames is None else np.ascontiguousarray(cons.frames, dtype=float)
        frame_of, mask, value = np.empty(N, dtype=np.int64), np.empty((N, 3), dtype=bool), np.empty((N, 3))
        turned = kernels.local_constraints(np.asarray(cons.nodes, dtype=np.int64), np.asarray(cons.mask, dtype=bool),
                                           np.asarray(cons.value, dtype=float), R, frame_of, mask, value)
        load = np.zeros((N, 3)) if homogeneous else self.b
        if extra_rhs is not None:
            load = load + extra_rhs
        b = np.empty((N, 3))
        kernels.frames_apply(frame_of, R, np.ascontiguousarray(load, dtype=float), True, b)
        if not reuse or getattr(self, "_rotated", None) is None:
            self._rotated, self._scale = _factorize_compiled(self.body, self.A, frame_of, R, turned > 0, mask,
                                                             self.solver, self.timings)
            self.stats["factorizations"] = self.stats.get("factorizations", 0) + 1
        A = np.ascontiguousarray(self._rotated, dtype=float)
        rhs, held = np.empty((N, 3)), np.empty(N, dtype=bool)
        kernels.constrained_rhs(A, pat.indptr, pat.indices, mask, value, b, self._scale, held, rhs)
        with timed(self.timings, "solve"):
            y = np.ascontiguousarray(self.solver.solve(rhs.reshape(-1)), dtype=float).reshape(N, 3)
        reaction, out = np.empty((N, 3)), np.empty((N, 3))
        kernels.constrained_finish(A, pat.indptr, pat.indices, mask, value, held, b, y, reaction)
        kernels.frames_apply(frame_of, R, y, False, out)
        return out, reaction

    def apply(self, y: np.ndarray) -> np.ndarray:
        """A y for y (N, 3)."""
        return (self.body.pattern.to_bsr(self.A) @ y.reshape(-1)).reshape(-1, 3)

    def responses(self, cons: Constraints, values: np.ndarray | None = None,
                  loads: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Homogeneous solves (the step's load dropped) for k columns at once, with the factorisation of the
        last solve (which must have had the constrained set of ``cons``): the constrained components set to
        ``values`` (k, len(cons), 3) (local frames; zero if None) and the loads ``loads`` (k, N, 3) (zero if
        None). Returns y (k, N, 3) global and the reactions (k, N, 3) local, as :meth:`solve` for each."""
        pat = self.body.pattern
        N = pat.n_nodes
        T, mask, _ = cons.dense(N)
        k = len(values) if values is not None else len(loads)
        V = np.zeros((k, N, 3))
        if values is not None:
            V[:, cons.nodes] = np.where(cons.mask, values, 0.0)
        b = np.zeros((k, N, 3)) if loads is None else to_local(T, loads)
        if getattr(self, "_rotated", None) is None:
            self._rotated, self._scale = factorize_constrained(self.body, self.A, T, mask, self.solver, self.timings)
        if getattr(self, "_csr", None) is None or self._csr[0] is not self._rotated:
            self._csr = (self._rotated, pat.to_bsr(self._rotated).tocsr())  # sparse x dense products by CSR
        A, scale = self._csr[1], self._scale
        rhs = b if values is None else b - (A @ V.reshape(k, -1).T).T.reshape(k, N, 3)
        rhs = rhs.copy()
        rhs[:, mask] = scale * V[:, mask]
        with timed(self.timings, "solve"):
            y = self.solver.solve(np.asfortranarray(rhs.reshape(k, -1).T)).T.reshape(k, N, 3)
        y[:, mask] = V[:, mask]
        rows = np.flatnonzero(mask.ravel())  # the reactions live on the constrained components only
        reaction = np.zeros((k, 3 * N))
        if len(rows):
            reaction[:, rows] = (A[rows] @ y.reshape(k, -1).T).T - b.reshape(k, -1)[:, rows]
        return to_global(T, y), reaction.reshape(k, N, 3)


@dataclass
class IterativeSettings:
    """tol: relative residual of the free components; max_iter per solve.

    The residual r = b - A y on the free components must reach ||r|| <= tol * max(||b||, sum_t ||t||),
    where t runs over the terms that make up b (M v, h f_el, h f_ext, friction impulses), all on the
    free components; only if both vanish (prescribed motion alone is a load) is it relative to the
    initial residual. The terms matter at rest: there b is the small difference of large terms
    (gravity against elastic forces), and a tolerance on ||b|| alone would ask for an accuracy far
    below what the terms themselves resolve. The warm start does not enter the tolerance.

    The preconditioner is refactorised for the next solve when the iterations spent beyond a fresh
    preconditioner's (``refactor_after`` a solve for a factor; multigrid's own first count after its set-up)
    reach Preconditioner.refactor_cost, the factorisation's cost from the backend's own counts (flops, not
    timings, so runs are reproducible anywhere) over REFACTOR_HORIZON; with a backend that does not count
    (SuperLU), when a solve needed more than ``refactor_after`` iterations. And at once when CG fails to
    converge. An iteration costs one product with A (sparse, or matrix-free, see ``operator``) and one
    single-precision triangular solve pair (multigrid: one V-cycle). Measured with the fixed count on the tet10
    (9,9,2) sheet-on-sphere run (150 steps in contact, before the extrapolated warm start): refactor_after = 3
    gave 3.3-3.6 PCG iterations and 0.04-0.09 refactorisations per step, 4 gave 4.2 and 0.05, 6 and more a
    single factorisation for the whole run and 5.7 iterations per step.

    The factorisation eliminates the supports only; other constrained nodes (contacts) are removed from the
    preconditioner exactly by a Schur complement (softbody.preconditioner), for up to ``max_corrected_nodes``
    nodes, their columns cached within Preconditioner.column_cap; with a counting backend the others are
    projected out by the PCG (their extra iterations count towards the next refactorisation), without one the
    next factorisation eliminates them all (they stay eliminated, in their frames of that moment, until a
    refactorisation), as it does when the cache is full. Multigrid corrects none.

    ``loose_tol``: the tolerance of an active set's trial solves (IterativeSystem.trials_pay; default
    max(1e-3, tol) with a factor, max(LOOSE_MULTIGRID, tol) with multigrid, whose every digit costs 4-5 iterations),
    each set confirmed by a solve to ``tol``.

    ``operator``: how the PCG applies A. "assembled": K' is assembled every step (its upper blocks
    into A's BSR data) and each product is one sparse product; "matrix-free": K' y comes element by
    element from the rotated gradients (FemBody.warped_product), and A is assembled only when a
    refactorisation needs it; "auto": matrix-free where FemBody.prefers_matrix_free (tet10 with
    warping) as long as the last step took at most ``matrix_free_max_products`` products with A (one
    for the forces, one per solve and one per PCG iteration) and no refactorisation is due, else
    assembled. The threshold is empirical, from the tet10 sheet-on-sphere run (the step, alternating
    assembled and matrix-free in one process, benchmarks/operator_ab.py): matrix-free took 0.73x the
    time at (9,9,2) (3.3 iterations per step), 0.94x at (14,14,3) during the impact (6.5 iterations,
    about 9.5 products), but 1.07x at (24,24,5) (10 iterations, about 13 products).

    ``pcg_responses``: a batch of homogeneous responses (IterativeSystem.responses, one per contact row
    of a coupled solve) larger than this is solved by one exact double-precision factorisation of A
    instead of a PCG solve per column (a factorisation costs about 10-20 PCG iterations, a response 3-6).
    """

    tol: float = 1e-5
    max_iter: int = 200
    refactor_after: int = 3
    max_corrected_nodes: int = 64
    operator: Literal["auto", "assembled", "matrix-free"] = "auto"
    matrix_free_max_products: int = 10
    pcg_responses: int = 4
    loose_tol: float | None = None

    def __post_init__(self):
        if self.operator not in ("auto", "assembled", "matrix-free"):
            raise InvalidInputError("IterativeSettings.operator must be 'auto', 'assembled' or 'matrix-free', "
                                    f"got {self.operator!r}")
        if not (isinstance(self.tol, (int, float)) and 0 < self.tol < 1):
            raise InvalidInputError(f"IterativeSettings.tol must be a number in (0, 1), got {self.tol!r}")
        if self.loose_tol is not None and not (isinstance(self.loose_tol, (int, float))
                                               and self.tol <= self.loose_tol < 1):
            raise InvalidInputError(f"IterativeSettings.loose_tol must be None or a number in [tol, 1), got "
                                    f"{self.loose_tol!r}")
        for name, least in (("max_iter", 1), ("refactor_after", 0), ("max_corrected_nodes", 0),
                            ("matrix_free_max_products", 0), ("pcg_responses", 0)):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and value >= least):
                raise InvalidInputError(f"IterativeSettings.{name} must be an integer >= {least}, got {value!r}")


    def loose(self, exact: bool) -> float:
        """The trial solves' tolerance with an exact (factor) or inexact (multigrid) preconditioner."""
        if self.loose_tol is not None:
            return float(self.loose_tol)
        return max(1e-3 if exact else LOOSE_MULTIGRID, float(self.tol))


def _product_of(matrix: sp.spmatrix) -> Callable[[np.ndarray], np.ndarray]:
    """y (N, 3) -> matrix @ y (N, 3) for a sparse (3N, 3N) matrix."""
    return lambda y: (matrix @ y.reshape(-1)).reshape(-1, 3)


class IterativeSystem:
    """A = c_m M + c_k K' (an assembled BSR matrix or a matrix-free product) and b (N, 3), solved by
    projected conjugate gradients preconditioned by the body's last factorised system matrix."""

    iterative = True  # solves stop at a tolerance (``loose``: IterativeSettings.loose_tol)

    @property
    def trials_pay(self) -> bool:
        """Whether an active set's trial solves should be loose (then confirmed by a full one): with multigrid always
        (a changed set costs it 10-20 iterations to the full tolerance), with a factor when the body's last full solve
        needed more than ``refactor_after`` iterations. Where a solve takes one or two, a confirmation costs as much
        as the iterations a loose tolerance saves (tet10 9x9x2 sheet: 423 solves and 673 iterations over 150 steps
        with trials, 250 and 640 without)."""
        if not self.pre.solver.exact:
            return True
        last = self.pre.last_iterations
        return last is not None and last > self.settings.refactor_after

    @property
    def confirmation_ends_switching(self) -> bool:
        """Whether an active set's friction switches and sliding-force refinements end once a full solve confirms
        its trials (what they would do carried to the next step): with multigrid, where each solve after the
        confirmation costs 8-20 iterations (549k tet4 nodes through the impact: 4-6 such solves a step in half the
        steps, for stick/slip switches of a few contacts in a thousand and sliding forces that kept changing by 5-20%)."""
        return not self.pre.solver.exact

    def __init__(self, body: FemBody, A: np.ndarray | Callable[[], np.ndarray], b: np.ndarray, x0: np.ndarray,
                 pre: Preconditioner, settings: IterativeSettings, timings: Timings | None = None,
                 Q: np.ndarray | Callable[[], np.ndarray] | None = None, terms: tuple[np.ndarray, ...] = (),
                 A_op: Callable[[np.ndarray], np.ndarray] | sp.spmatrix | None = None,
                 direct: SpdSolver | None = None):
        """A: block data (nnzb, 3, 3) of the system matrix, or a function that assembles it (called
        only if a refactorisation needs it); A_op: the product y (N, 3) -> A y (N, 3), as a function or
        a sparse matrix (default: A's BSR matrix); b (N, 3); x0 (N, 3) the warm start; Q (N, 3, 3)
        per-node rotations for conjugating the preconditioner, or a function that makes them (called at the first
        use: a system whose matrix a coupled solve takes whole never needs them); terms: the (N, 3) terms that sum to b,
        for the tolerance (IterativeSettings); direct: the body's double-precision solver, for batches of
        responses (see :meth:`responses`)."""
        self.body, self.b = body, b
        self.terms = terms
        self.rotations: np.ndarray | None = None  # (E, 3, 3): the warped step's element rotations (step_system)
        self._A = A
        if A_op is None:
            A_op = body.pattern.to_bsr(self.assemble())
        self.matrix_free = callable(A_op)  # a function (FemBody.warped_product), not a matrix
        self._product = A_op if self.matrix_free else _product_of(A_op)
        self._G = None  # (factorisation count, per-node frames of the factorised matrix), see _preconditioner_frames
        self.x0 = x0
        self.pre = pre
        self.settings = settings
        self._Q = Q  # per-node rotations, for conjugating the preconditioner (or the function that makes them)
        self.stats: dict = {"iterations": 0, "factorizations": 0}
        self.timings = timings
        self.direct = direct
        self._exact: tuple[bytes, DirectSystem] | None = None  # (constraint set, its factorised system)

    @property
    def operator(self) -> WarpedOperator | None:
        """The matrix-free A (WarpedOperator) while A is not assembled, else None."""
        return self._product if self.matrix_free and callable(self._A) and isinstance(self._product,
                                                                                    WarpedOperator) else None

    def diagonal(self) -> np.ndarray:
        """(N, 3, 3) the diagonal blocks of A (from the assembled A, or matrix-free)."""
        op = self.operator
        return op.diagonal() if op is not None else self.assemble()[self.body.pattern.diag]

    @property
    def Q(self) -> np.ndarray | None:
        """(N, 3, 3) the per-node rotations (made at the first use if given as a function), or None."""
        if callable(self._Q):
            with timed(self.timings, "rotations"):
                self._Q = self._Q()
        return self._Q

    def apply(self, y: np.ndarray) -> np.ndarray:
        """A y for y (N, 3)."""
        return self._product(y)

    def assemble(self) -> np.ndarray:
        """Block data (nnzb, 3, 3) of A (for refactorisation), assembled at the first call if need be."""
        if callable(self._A):
            self._A = self._A()
        return self._A

    def _refactor(self, T: NodeFrames | None, mask: np.ndarray, everything: bool = False) -> None:
        """Factorise the current A with the supports' constrained components eliminated (with
        ``everything``, all constrained components)."""
        with timed(self.timings, "assembly"):
            A = self.assemble()
            if self.matrix_free:  # A exists now: its sparse product is the cheaper one for the rest of the step
                self._product = _product_of(self.body.pattern.to_bsr(A))
        keep = mask if everything else mask & self.body.supported()[:, None]
        self.pre.drop_columns()
        factorize_constrained(self.body, A, T, keep, self.pre.solver, self.timings)
        self.pre.factorized(T, self.Q, _any_component(keep))
        self.stats["factorizations"] += 1

    def _prepared(self, T: NodeFrames | None, mask: np.ndarray) -> tuple[Frames, ConstraintCorrection | None]:
        """The preconditioner for constraint set (T, mask): its per-node frames C and the correction for
        the constrained nodes that the factorisation does not eliminate (refactorising if due).

        With a backend that counts its costs (Preconditioner.refactor_cost), contacts never force a
        refactorisation: up to ``max_corrected_nodes`` of the nodes not eliminated are corrected (those with
        cached columns first, at most Preconditioner.column_cap cached), the rest only projected out by the PCG; the
        extra iterations this costs add to the work that buys the next refactorisation. Without counts, more
        nodes than that refactorise at once, eliminating them all. An inexact preconditioner (multigrid)
        corrects none."""
        pre, limit = self.pre, self.settings.max_corrected_nodes
        constrained = _any_component(mask)
        counted = pre.refactor_cost() is not None
        outside = lambda: constrained & ~pre.eliminated  # noqa: E731
        # the columns of every node corrected since the factorisation are kept; past their cap (memory: n_dof x 3
        # per node) a refactorisation starts them afresh, or (counted) no more are added
        cap = pre.column_cap(limit)
        if pre.stale or (not counted and (np.count_nonzero(outside()) > limit
                                          or pre.cached_nodes + np.count_nonzero(outside()) > cap)):
            self._refactor(T, mask, everything=np.count_nonzero(constrained & ~self.body.supported()) > limit)
        nodes = np.flatnonzero(outside())
        if not pre.solver.exact:  # multigrid: a column is a V-cycle, as dear as an iteration; projection alone
            nodes = nodes[:0]
        elif counted:
            nodes = pre.correctable(nodes, limit, cap)
        with timed(self.timings, "solve"):
            C = self._preconditioner_frames(T)
        if not len(nodes):
            return C, None
        with timed(self.timings, "factorize"):  # preconditioner set-up: new columns, Schur complement
            try:
                return C, pre.correction(nodes, mask[nodes], _frames_at(C, nodes, self.body.n_nodes), cap)
            except np.linalg.LinAlgError:  # not positive definite: P is too far off for this set
                pass
        self._refactor(T, mask, everything=True)
        with timed(self.timings, "solve"):
            return self._preconditioner_frames(T), None

    def _preconditioner_frames(self, T: NodeFrames | None) -> Frames:
        """Per-node C with A^-1 ~ C^T P^-1 C in the current local frames, P the factorised matrix:
        C = pre.T^T Qrel^T T, Qrel = Q pre.Q^T the rotation of each node since the factorisation."""
        pre = self.pre
        if self._G is None or self._G[0] != pre.factorizations:
            G = None  # factorised local frame -> current global frame, per node
            if self.Q is not None and pre.Q is not None:
                if kernels.ENABLED:
                    G = np.empty(self.Q.shape)
                    kernels.frame_products(np.ascontiguousarray(self.Q), np.ascontiguousarray(pre.Q), G)
                else:
                    G = self.Q @ np.swapaxes(pre.Q, 1, 2)
                if pre.T is not None:
                    G[pre.T.nodes] = G[pre.T.nodes] @ pre.T.R
            elif pre.T is not None:
                G = pre.T
            self._G = (pre.factorizations, G)
        G = self._G[1]
        if G is None:
            return T
        if isinstance(G, NodeFrames):
            if T is None:
                return NodeFrames(G.nodes, np.swapaxes(G.R, 1, 2))
            G = G.dense(self.body.n_nodes)
        C = np.swapaxes(G, 1, 2).copy()
        if T is not None:
            C[T.nodes] = C[T.nodes] @ T.R
        return C

    def solve(self, cons: Constraints, extra_rhs: np.ndarray | None = None,
              reuse: bool = False, homogeneous: bool = False, loose: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Same contract as DirectSystem.solve (``reuse`` is implied: the preconditioner is kept). A
        homogeneous solve starts from zero and leaves the warm start of the step's next solve alone. A
        ``loose`` one stops at IterativeSettings.loose_tol (an active set's trial solve, confirmed by a full
        one once the set stands)."""
        self.pre.solved = True
        T, mask, value = cons.dense(self.body.n_nodes)
        load = np.zeros_like(self.b) if homogeneous else self.b
        b = to_local(T, load if extra_rhs is None else load + extra_rhs)
        A = lambda y: to_local(T, self.apply(to_global(T, y)))
        free = ~mask
        C, fix = self._prepared(T, mask)
        y = np.zeros_like(self.b) if homogeneous else np.array(to_local(T, self.x0))  # a copy: x0 may be the body's velocities
        y[mask] = value[mask]
        with timed(self.timings, "solve"):
            r_full = b - A(y)
            # tolerance relative to the load on the free components or its terms; if both vanish
            # (prescribed motion alone is a load), to the initial residual (see IterativeSettings)
            terms = (() if homogeneous else self.terms) + (() if extra_rhs is None else (extra_rhs,))
            scale = max(np.linalg.norm(b[free]), sum(np.linalg.norm(to_local(T, t)[free]) for t in terms))
            tol = self.settings.loose(self.pre.solver.exact) if loose else self.settings.tol
            atol = tol * (scale if scale > 0 else max(np.linalg.norm(r_full[free]), 1e-300))
            y, r_full, its, ok = self._pcg(A, y, r_full, free, C, fix, atol)
        self.pre.products += 1 + its  # the initial residual and one per iteration
        if not ok:  # the preconditioner is too far off: refactorise now and finish from y
            self.pre.stale = True
            fix = None  # (it holds the cached columns, which the refactorisation lets go)
            C, fix = self._prepared(T, mask)
            with timed(self.timings, "solve"):
                y, r_full, its, ok = self._pcg(A, y, r_full, free, C, fix, atol)
            self.pre.products += its
            if not ok:
                raise SolverError(f"conjugate gradients did not converge in {self.settings.max_iter} "
                                  "iterations with a fresh factorisation (is the system positive definite?)")
        if not homogeneous and not loose:  # a homogeneous solve starts cold, a loose one stops early: their counts
            self._charge(its)  # say nothing of the preconditioner's age
        self.pre.iterations += its
        self.stats["iterations"] += its
        y = to_global(T, y)
        if not homogeneous:
            self.x0 = y  # warm start for the next solve of this step (active-set loops)
        reaction = np.where(mask, -r_full, 0.0)  # A y - b on the constrained components
        return y, reaction

    def _charge(self, its: int) -> None:
        """After a solve of ``its`` iterations: the iterations beyond what a fresh preconditioner needs add to its
        spent work, and a refactorisation is due once that reaches its cost (Preconditioner.refactor_cost; a
        backend without counts: at once). A fresh factor needs ``refactor_after``; multigrid, inexact, the fewest
        of an earlier solve since its set-up (at least that), give or take MULTIGRID_SPREAD."""
        pre = self.pre
        fresh = self.settings.refactor_after
        if not pre.solver.exact:  # multigrid: its own fewest count since a set-up, and the spread of its counts
            fresh = max(fresh, math.ceil((1.0 + MULTIGRID_SPREAD) * (its if pre.fewest is None else pre.fewest)))
        pre.spent += max(0, its - fresh)
        pre.fewest = its if pre.fewest is None else min(pre.fewest, its)
        pre.last_iterations = its
        cost = pre.refactor_cost()
        pre.stale = pre.spent >= cost if cost is not None else its > self.settings.refactor_after

    def responses(self, cons: Constraints, values: np.ndarray | None = None,
                  loads: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Same contract as DirectSystem.responses. Up to ``IterativeSettings.pcg_responses`` columns: one
        homogeneous PCG solve each; more (a coupled contact solve asks for one per contact row): one exact
        factorisation of A under ``cons`` (kept while the constraint set stays) and one batched solve."""
        k = len(values) if values is not None else len(loads)
        if k > self.settings.pcg_responses and self.direct is not None:
            key = b"".join((cons.nodes.tobytes(), cons.mask.tobytes(),
                            b"" if cons.frames is None else np.ascontiguousarray(cons.frames).tobytes()))
            if self._exact is None or self._exact[0] != key:
                with timed(self.timings, "assembly"):
                    A = self.assemble()
                self._exact = (key, DirectSystem(self.body, A, self.b, self.direct, timings=self.timings))
                self.stats["factorizations"] += 1
            return self._exact[1].responses(cons, values, loads)
        out = [self.solve(cons if values is None else Constraints(cons.nodes, cons.mask, values[j], cons.frames),
                          None if loads is None else loads[j], homogeneous=True) for j in range(k)]
        return np.array([o[0] for o in out]), np.array([o[1] for o in out])

    def _precondition(self, r: np.ndarray, free: np.ndarray, C: Frames, fix: ConstraintCorrection | None) -> np.ndarray:
        """z = C^T P_F^-1 C r on the free components (r, z (N, 3) in the current local frames), P_F^-1
        the inverse of P restricted to the free components (P^-1 corrected by ``fix``)."""
        u = self.pre.solver.solve(to_global(C, r).reshape(-1))
        if fix is not None:
            u = fix.apply(u)
        return np.where(free, to_local(C, u.reshape(-1, 3)), 0.0)

    def _pcg(self, A, y, r_full, free, C, fix, atol):
        """Projected PCG on the free components from y; r_full = b - A y on all components (kept
        up to date, so the constrained components give the reactions without another product)."""
        r = np.where(free, r_full, 0.0)
        if np.linalg.norm(r) <= atol:
            return y, r_full, 0, True
        z = self._precondition(r, free, C, fix)
        d = z.copy()
        rz = float(np.vdot(r, z))
        for it in range(1, self.settings.max_iter + 1):
            Ad = A(d)
            dAd = float(np.vdot(d, Ad))
            if not dAd > 0:
                return y, r_full, it, False
            a = rz / dAd
            y += a * d  # y and r_full are the caller's own arrays
            r_full -= a * Ad
            r = np.where(free, r_full, 0.0)
            if np.linalg.norm(r) <= atol:
                return y, r_full, it, True
            z = self._precondition(r, free, C, fix)
            rz_new = float(np.vdot(r, z))
            d *= rz_new / rz
            d += z
            rz = rz_new
        return y, r_full, self.settings.max_iter, False


LinearSystem = DirectSystem | IterativeSystem


def assembled_system(body: FemBody, A: np.ndarray, b: np.ndarray, solver: SpdSolver, method: str,
                     settings: IterativeSettings, timings: Timings | None, x0: np.ndarray,
                     terms: tuple[np.ndarray, ...] = (), Q: np.ndarray | None = None,
                     pre: Preconditioner | None = None) -> LinearSystem:
    """A linear system A y = b (A: block data (nnzb, 3, 3), b (N, 3)) to be solved with constraints, direct
    (factorised) or iterative (PCG from x0 (N, 3), preconditioned by ``pre``, the body's preconditioner kept by
    the stepper (softbody.solvers.BodySolvers; None: a fresh one), conjugated with the per-node rotations Q
    (N, 3, 3) if given; terms: the (N, 3) parts of b, for the tolerance)."""
    if method == "direct":
        return DirectSystem(body, A, b, solver, timings=timings)
    pre = pre if pre is not None else new_preconditioner(body, solver.backend)
    return IterativeSystem(body, A, b, x0, pre, settings, timings, Q, terms, None, solver)


@dataclass
class WarpedOperator:
    """A = c_m M + c_k K' of a warped body applied without assembling K' (K' y by FemBody.warped_product from the
    rotated gradients g of the step's rotations): y (N, 3) -> A y (N, 3). Its diagonal blocks come the same way
    (FemBody.warped_diagonal), and a stack's member's operator is the member's own with its elements' gradients."""

    body: FemBody
    g: np.ndarray | tuple
    c_m: float
    c_k: float

    def __call__(self, y: np.ndarray) -> np.ndarray:
        return self.c_m * self.body.mass_product(y) + self.c_k * self.body.warped_product(self.g, y)

    def diagonal(self) -> np.ndarray:
        """(N, 3, 3) the diagonal blocks of A."""
        D = self.c_k * self.body.warped_diagonal(self.g)
        D[:, [0, 1, 2], [0, 1, 2]] += self.c_m * self.body.M_data[self.body.pattern.diag][:, None]
        return D

    def member(self, i: int) -> "WarpedOperator":
        """The operator of member i of a stack (softbody.stack.BodyStack: its elements are rows element_offsets[i]:
        element_offsets[i + 1] of the stack's)."""
        rows = slice(int(self.body.element_offsets[i]), int(self.body.element_offsets[i + 1]))
        g = tuple(x[rows] for x in self.g) if isinstance(self.g, tuple) else self.g[rows]
        return WarpedOperator(self.body.members[i], g, self.c_m, self.c_k)


def step_system(body: FemBody, h: float, f_ext: np.ndarray, solver: SpdSolver, method: str = "direct",
                settings: IterativeSettings | None = None, timings: Timings | None = None,
                pre: Preconditioner | None = None) -> LinearSystem:
    """The backward Euler system (M + h C + h^2 K') v' = M v + h (f_el + f_ext) at the current state (+ h alpha M v_r
    where alpha M spares the body's rigid motion, FemBody.rigid_damping_relief).

    K' (as its upper blocks, FemBody.warped_stiffness_upper) is assembled once, straight into
    A = c_m M + c_k K'; the warped elastic forces f_el = -K' (x - c) + sum_e R_e K_e X_e take K' (x - c)
    from A. Or, on the iterative path with a matrix-free operator (IterativeSettings.operator), K' is
    not assembled: K' y comes from FemBody.warped_product, and A is assembled only if the
    preconditioner is refactorised. method "direct" factorises A; "iterative" runs PCG (see the
    module doc). timings, if given, accumulates seconds per phase (rotations, assembly, forces,
    factorize, solve). pre: the body's preconditioner for the iterative path, kept by the stepper from step to
    step (softbody.solvers.BodySolvers; None: a fresh one, factorised in this step).
    """
    alpha, beta = body.damping
    x, v = body.positions, body.velocities
    with timed(timings, "rotations"):
        R = body.rotations(x) if body.warping else None
    c_m, c_k = 1.0 + h * alpha, h * beta + h * h
    settings = settings or IterativeSettings()
    if method == "direct":
        pre = None
    elif pre is None:
        pre = new_preconditioner(body, solver.backend)
    operator = settings.operator
    if operator == "auto":
        # matrix-free saves the assembly only if no refactorisation is due (stale: it needs A anyway); none is due for
        # a body whose last system was not solved by its own PCG (a coupled solve took it whole, and takes this one
        # so too: it applies A, and assembles it only to factorise)
        due = pre is not None and pre.stale and pre.solved is not False
        operator = ("matrix-free" if body.prefers_matrix_free and pre is not None and not due
                    and pre.products <= settings.matrix_free_max_products else "assembled")
    matrix_free = pre is not None and operator == "matrix-free"
    if pre is not None:
        pre.products = 1  # K' u for the forces; IterativeSystem.solve counts the rest
        pre.solved = False  # until IterativeSystem.solve runs
    u = x - np.add.reduce(x, axis=0) / len(x)  # any point works (K' annihilates translations); the mean limits
    # round-off (np.mean's arithmetic, without its wrapper)
    if matrix_free:  # K' y element by element; A assembled only if a refactorisation asks for it
        with timed(timings, "assembly"):
            g = body.rotated_gradients(R)
            load = body.rest_loads(R)
        with timed(timings, "forces"):
            Ku = body.warped_product(g, u)
        A = lambda: body.system_blocks(body.warped_stiffness_upper(R)[0], c_m, c_k)  # noqa: E731
        A_op = WarpedOperator(body, g, c_m, c_k)
    else:
        with timed(timings, "assembly"):
            K, load = body.warped_stiffness_upper(R)
            A = body.system_blocks(K, c_m, c_k)
            A_op = body.pattern.to_bsr(A) if pre is not None else None  # the iterative path's operator
        with timed(timings, "forces"):
            # K' u from the system matrix, (A u - c_m M u) / c_k, so that K' is never formed whole: its
            # round-off relative to K' u is about eps * (c_m M / c_k K'); where that exceeds 1e-12 (very
            # soft bodies or tiny steps: c_m M over 1e4 x c_k K'), K' u comes from K' itself
            if c_m * body.mass_scale <= 1e4 * c_k * float(np.abs(K[body.diagonal_upper, ::4]).max()):
                Ku = (body.pattern.product(A, u) - c_m * body.mass_product(u)) / c_k
            else:
                Ku = body.pattern.product(body.stiffness_blocks(K), u)
    with timed(timings, "forces"):
        terms = (body.mass_product(v), h * (load - Ku), h * f_ext)
        relief = body.rigid_damping_relief(h, terms[0])  # alpha M spares the rigid motion
        if relief is not None:
            terms += (relief,)
        b = sum(terms[1:], terms[0])
    if pre is None:
        return DirectSystem(body, A, b, solver, timings=timings, rotations=R)
    Q = (lambda: body.node_frames(R)) if body.warping else None  # made if the system's own solve needs them
    # warm start: the velocity extrapolated linearly from the last two steps' (a better guess than v
    # alone when the motion is smooth: on the tet10 (9,9,2) sheet-on-sphere run, 3.3 instead of 3.6 PCG
    # iterations and a third of the refactorisations per step)
    v_prev, pre.previous_velocities = pre.previous_velocities, v.copy()
    x0 = 2.0 * v - v_prev if v_prev is not None and v_prev.shape == v.shape else v
    system = IterativeSystem(body, A, b, x0, pre, settings, timings, Q, terms, A_op, solver)
    system.rotations = R
    return system


def support_constraints(body: FemBody, t_next: float, h: float) -> Constraints:
    """Velocity constraints that put fixed and prescribed nodes exactly where they must be at t_next."""
    nodes, vel = body.constrained_targets(t_next, h)
    return Constraints.full(nodes, vel)
