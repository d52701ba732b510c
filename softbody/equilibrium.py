"""Static equilibrium of the warped (corotational) model however large the rotations, where softbody.solve_static is
small-strain linear (issue 33).

Two equilibria, as the two schemes settle (docs/method.md section 3); a body of a hyperelastic model
(FemBody(model="neo-hookean"), "corotated") has one, its energy's minimum ("energy" with that energy):

- ``model="energy"``: the minimiser of Pi(x) = Psi(x) - f^T x under the supports, Psi the warped strain energy
  (FemBody.elastic_energy: each element's displacement in its rotated frame), f gravity and the given forces; where
  ``Simulation(scheme="newton")`` comes to rest. Newton's method in load steps (f scaled by k / load_steps, each from
  the last one's solution): the exact gradient of Psi (FemBody.energy_gradient, rotation derivatives included), its
  Hessian made positive semi-definite per element as tangent (FemBody.energy_hessian_blocks), the supports eliminated
  in the same constrained solve as a step's (integrator.DirectSystem), a backtracking line search on Pi.
- ``model="warped"`` (default): where the warped force -R K (R^T x - X) balances the loads; where the default warped
  step comes to rest. The warped force is not quite the gradient of Psi (R's own change is left out), so from the
  energy's equilibrium Newton's method on the force balance takes it the rest of the way: the warped force's
  Jacobian, rotations' change included, per element by central differences (FemBody.warped_force_jacobian_blocks;
  not symmetric: a sparse LU solve), the step halved until the unbalanced force falls. (The iteration with the warped
  step's own tangent K'(x), used before, converged linearly and diverged for a hex8 cantilever sagging 65 % of its
  length and a tet10 one sagging 15 %.) Measured on a soft cantilever 5 x 1 x 1 cells bending 0.26-0.53 m: the two
  equilibria 3e-10 m apart for tet4, 3e-5 m for hex8, 5 mm for tet10.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla

from .body import FemBody
from .errors import InvalidInputError, SolverError
from .integrator import Constraints, DirectSystem
from .simulation import _gravity, body_solver, solve_static, static_load

ARMIJO = 1e-4  # the line search's sufficient decrease, relative to the slope
MODELS = ("warped", "energy")


def _step_length(body: FemBody, x: np.ndarray, dx: np.ndarray, f: np.ndarray, g: np.ndarray, slope: float) -> float:
    """Backtracking on Pi along dx from x (gradient g, zero on supports; slope g . dx < 0): the first of 1, 1/2, ...
    with sufficient decrease (ARMIJO); where the decrease asked is below Pi's round-off (near the solution), the first
    that lowers the residual instead."""
    work = float(np.vdot(f, x))
    psi = body.elastic_energy(x)
    pi0, noise = psi - work, 1e-12 * (psi + abs(work))
    free = g != 0.0
    r0 = float(np.linalg.norm(g))
    alpha = 1.0
    while alpha > 1e-6:
        xt = x + alpha * dx
        if abs(ARMIJO * alpha * slope) <= noise:  # below round-off: the residual decides
            if float(np.linalg.norm(np.where(free, body.energy_gradient(xt) - f, 0.0))) < r0:
                return alpha
        elif body.elastic_energy(xt) - float(np.vdot(f, xt)) - pi0 <= ARMIJO * alpha * slope:
            return alpha
        alpha *= 0.5
    return alpha


def _solve(body: FemBody, A: np.ndarray, g: np.ndarray, s, held: Constraints) -> tuple[np.ndarray, np.ndarray]:
    """A dx = -g with the supports held; a singular A (supports that leave a rigid mode free) said as bad input."""
    try:
        return DirectSystem(body, A, -g, s).solve(held)
    except (SolverError, np.linalg.LinAlgError, RuntimeError) as exc:
        raise InvalidInputError(f"solve_equilibrium: the system is singular ({exc}); the supports must remove all "
                                "rigid-body modes") from exc


def solve_equilibrium(body: FemBody, gravity=(0.0, 0.0, -9.81), forces: np.ndarray | None = None,
                      model: str | None = None, load_steps: int = 4, tol: float = 1e-8, max_iter: int = 40,
                      solver: str = "auto") -> np.ndarray:
    """Displacements u (N, 3) [m] of the static equilibrium under gravity [m/s^2] and ``forces`` (N, 3) [N] with the
    body's supports (fixed nodes u = 0, prescribed ones motion(0) - rest), of the warped model ("warped": where the
    default step comes to rest) or its energy ("energy": where scheme="newton" does); see the module doc. A body of a
    hyperelastic model (FemBody(model="neo-hookean") etc.) has only its energy's ("energy"); None: "warped" for the
    warped model, "energy" for the others. Each of
    ``load_steps`` load steps to a residual (the free components' unbalanced force) of ``tol`` times the load within
    ``max_iter`` Newton iterations, the warped model's last iteration within 5 max_iter; else SolverError with the
    last residuals. A body without warping is linear: solve_static's answer. InvalidInputError without supports
    (or with too few). Prescribed nodes move with the loads, to rest + k / load_steps (motion(0) - rest) in load step
    k, the free nodes following them by one linearised solve before the step's iterations (moved all at once, the
    elements next to them could be turned inside out, where a hyperelastic model may find an inverted equilibrium)."""
    if model is None:
        model = "energy" if body.law is not None else "warped"
    if model not in MODELS:
        raise InvalidInputError(f"model must be one of {MODELS}, got {model!r}")
    if model == "warped" and body.law is not None:
        raise InvalidInputError(f"model='warped' balances the warped force; this body's model is {body.model!r}, "
                                "whose equilibrium is its energy's minimum (model='energy')")
    if not isinstance(load_steps, (int, np.integer)) or load_steps < 1:
        raise InvalidInputError(f"load_steps must be a positive integer, got {load_steps!r}")
    if not (np.isfinite(tol) and tol > 0):
        raise InvalidInputError(f"tol must be a positive number, got {tol!r}")
    if not body.warping:
        return solve_static(body, gravity, solver, forces)
    f = static_load(body, _gravity(gravity), forces)
    nodes, _ = body.constrained_targets(0.0, 1.0)
    if not body.mesh.used_nodes()[nodes].any():
        raise InvalidInputError("solve_equilibrium needs supports: fix or prescribe nodes to remove the rigid-body "
                                "modes")
    x = np.array(body.rest, dtype=float)
    for ids, motion in body.prescribed:
        x[ids] = np.asarray(motion(0.0), float).reshape(-1, 3)
    shift = x - body.rest  # the prescribed displacements (zero elsewhere)
    free = np.ones(len(x), dtype=bool)
    free[nodes] = False
    held = Constraints.full(nodes, np.zeros((len(nodes), 3)))
    s = body_solver(body, solver)
    # the residual's scale: the loads or, with none, the forces of the prescribed displacements (a body held and moved)
    scale = float(np.linalg.norm(f[free]))
    if scale == 0.0:
        scale = max(float(np.linalg.norm(body.energy_gradient(x)[free])), 1e-300)
    x = x - shift
    moved = bool(np.any(shift))
    residuals: list[float] = []

    def fail(what: str, iterations: int):
        raise SolverError(f"solve_equilibrium: {what} did not converge to tol = {tol:g} in {iterations} iterations; "
                          f"residuals {[f'{r:.2e}' for r in residuals[-5:]]} (more load_steps, or a larger tol)")

    for k in range(1, load_steps + 1):
        fk = f * (k / load_steps)
        if moved:  # the prescribed nodes' increment, with the interior following it (one linearised solve, whole)
            g = body.energy_gradient(x) - fk
            g[~free] = 0.0
            dx, _ = _solve(body, body.energy_hessian_blocks(x), g, s,
                           Constraints.full(nodes, shift[nodes] / load_steps))
            x = x + dx
        for _ in range(max_iter + 1):
            g = body.energy_gradient(x) - fk
            g[~free] = 0.0
            residuals.append(float(np.linalg.norm(g)) / scale)
            if residuals[-1] <= tol:
                break
            dx, _ = _solve(body, body.energy_hessian_blocks(x), g, s, held)
            slope = float(np.vdot(g, dx))
            if not slope < 0:  # the projected Hessian gave no descent: round-off at the solution, or a failure
                if residuals[-1] > 100 * tol:
                    fail(f"load step {k} of {load_steps} (no descent direction)", len(residuals))
                break
            x = x + _step_length(body, x, dx, fk, g, slope) * dx
        else:
            fail(f"load step {k} of {load_steps}", max_iter)
    if model == "warped":  # Newton's method on the warped force balance, from the energy's equilibrium
        dofs = np.repeat(free, 3)

        def unbalance(y: np.ndarray) -> np.ndarray:  # minus the warped force and the load, on the free nodes
            r = -(body.scatter_nodal(body.element_forces(y, body.rotations(y))) + f)
            r[~free] = 0.0
            return r

        g = unbalance(x)
        for _ in range(max_iter + 1):
            residuals.append(float(np.linalg.norm(g)) / scale)
            if residuals[-1] <= tol:
                break
            J = body.pattern.to_csr(body.warped_force_jacobian_blocks(x))[dofs][:, dofs]
            dx = np.zeros(x.size)
            try:
                dx[dofs] = spla.spsolve(J.tocsc(), -g.reshape(-1)[dofs])
            except RuntimeError as exc:  # a singular Jacobian
                raise SolverError(f"solve_equilibrium: the warped force balance's Jacobian is singular ({exc})") \
                    from exc
            dx = dx.reshape(-1, 3)
            alpha = 1.0  # the residual's norm must fall (the warped force is not a gradient: no potential to watch)
            while alpha > 1e-4:
                trial = unbalance(x + alpha * dx)
                if np.linalg.norm(trial) < np.linalg.norm(g):
                    break
                alpha *= 0.5
            x, g = x + alpha * dx, trial
        else:
            fail("the warped force balance", max_iter)
    return x - body.rest
