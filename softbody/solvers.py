"""The factorisations a stepper keeps from step to step, per body: the SPD solver of each backend (its
symbolic analysis done once for the body's fixed pattern) and the iterative path's preconditioner (a
single-precision factorisation of its own, refreshed when stale). Owned by whoever steps (a Simulation),
not stored on the bodies."""
from __future__ import annotations

from . import compilation
from .body import FemBody
from .linsolve import HAVE_PYAMG, SpdSolver
from .preconditioner import Preconditioner


class BodySolvers:
    """Per body (by identity) and backend: ``solver(body, backend)`` and ``preconditioner(body, solver)``."""

    def __init__(self):
        self._solvers: dict[tuple[int, str], tuple[FemBody, SpdSolver, int]] = {}
        self._preconditioners: dict[tuple[int, str], tuple[FemBody, Preconditioner]] = {}

    def solver(self, body: FemBody, backend: str = "auto") -> SpdSolver:
        """The body's SPD solver for ``backend`` (made on first use: one symbolic analysis per body; "auto" chooses
        again once the compiled kernels become ready, see softbody.compilation: the block Cholesky needs them). The
        direct solves need an exact backend: for "amg" (the iterative path's alone), "auto" chooses one."""
        backend = "auto" if backend == "amg" else backend
        key = (id(body), backend)
        held = self._solvers.get(key)
        if held is None or held[0] is not body or (backend == "auto" and held[2] != compilation.switches):
            held = self._solvers[key] = (body, new_solver(body, backend), compilation.switches)
        return held[1]

    def preconditioner(self, body: FemBody, solver: SpdSolver, backend: str | None = None) -> Preconditioner:
        """The body's preconditioner for the iterative path beside ``solver`` (kept under its backend): made by
        :func:`new_preconditioner` for ``backend`` (None: ``solver``'s), kept from step to step."""
        key = (id(body), solver.backend)
        held = self._preconditioners.get(key)
        if held is None or held[0] is not body:
            held = self._preconditioners[key] = (body, new_preconditioner(body, backend or solver.backend))
        return held[1]

    def retain(self, bodies) -> None:
        """Drop the solvers and preconditioners of every body not in ``bodies`` (released with them)."""
        keep = {id(b) for b in bodies}
        for held in (self._solvers, self._preconditioners):
            for key in [k for k, (b, *_) in held.items() if id(b) not in keep]:
                del held[key]

    def save_state(self, bodies: list[FemBody]) -> dict[tuple[int, str], dict]:
        """The preconditioners' states (Preconditioner.save_state) of ``bodies``, keyed by (index in ``bodies``,
        backend): what the iterative path carries from step to step. The direct path's factorisations are made
        anew every step and hold nothing across steps."""
        out = {}
        for i, body in enumerate(bodies):
            for (key, backend), (held, pre) in self._preconditioners.items():
                if key == id(body) and held is body:
                    out[(i, backend)] = pre.save_state()
        return out

    def load_state(self, bodies: list[FemBody], states: dict[tuple[int, str], dict]) -> None:
        """Take over the states of :meth:`save_state` for the same ``bodies`` (in the same order): a preconditioner
        that had not been made then is dropped now, the others take their saved factor, frames and counters."""
        for i, body in enumerate(bodies):
            for key in [k for k, (held, _) in self._preconditioners.items() if k[0] == id(body)]:
                if (i, key[1]) not in states:
                    del self._preconditioners[key]
        for (i, backend), state in states.items():
            body = bodies[i]
            held = self._preconditioners.get((id(body), backend))
            if held is None or held[0] is not body or held[1].solver.backend != state["backend"]:
                held = self._preconditioners[(id(body), backend)] = (body, new_preconditioner(body, state["backend"]))
            held[1].load_state(state)

    def held_preconditioner(self, body: FemBody, backend: str) -> Preconditioner | None:
        """The body's preconditioner for ``backend`` if one was made, else None (for counters)."""
        held = self._preconditioners.get((id(body), backend))
        return held[1] if held is not None and held[0] is body else None


def new_solver(body: FemBody, backend: str = "auto", precision: str = "double") -> SpdSolver:
    """An SPD solver on the body's fixed pattern (upper triangle)."""
    p = body.pattern
    return SpdSolver(p.up_indptr, p.up_indices, body.n_dofs, backend, precision=precision)


#: "auto" sets up algebraic multigrid instead of a factor when the single-precision factorisation would take more
#: than this many bytes per node (PARDISO's own count from the analysis, iparm 17: about 4 bytes per nonzero of the
#: factor): the factor of a 3-D body grows as N^4/3 and beyond, multigrid's hierarchy stays a few times A. On the tet4
#: sheet-on-sphere the factor takes 4.6 kB per node at 31k nodes and 7.7 kB at 72k. Steps 9-15 into the impact
#: (2026-11-29, multigrid aggregating nodes, softbody.linsolve.AMGFactorization): at 31k nodes 9.3 s with multigrid
#: against 7.8 s with the factor, at 72k nodes 39.2 s against 39.1 s, for a peak of 13.4 against 23.2 kB per node (softbody bench --large):
#: multigrid from about 62k tet4 nodes on
MULTIGRID_FACTOR_BYTES = 7168

#: bodies below this many unknowns keep a factor without asking (their factor is small; no analysis up front)
MULTIGRID_MIN_DOFS = 60_000


def new_preconditioner(body: FemBody, backend: str = "auto") -> Preconditioner:
    """A fresh preconditioner (not yet set up) for the body's iterative path: a single-precision factor of
    ``backend``, or algebraic multigrid for "amg", and for "auto" where the factor would be large
    (MULTIGRID_FACTOR_BYTES per node; the analysis made to count it, nested dissection alone, is kept)."""
    if backend == "amg":
        return Preconditioner(new_solver(body, "amg"), None, None)
    solver = new_solver(body, backend, precision="single")
    if backend == "auto" and solver.backend == "pardiso" and body.n_dofs >= MULTIGRID_MIN_DOFS and HAVE_PYAMG:
        solver.ORDERINGS = {2: solver.ORDERINGS[2]}  # (minimum degree loses on bodies this large, at length)
        solver.analyse(body.pattern.upper_data(body.M_blocks))
        if solver.factorization.factor_bytes > MULTIGRID_FACTOR_BYTES * body.n_nodes:
            return Preconditioner(new_solver(body, "amg"), None, None)
    return Preconditioner(solver, None, None)
