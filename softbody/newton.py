"""Exact backward Euler: Newton iterations on the warped step (``Simulation(..., scheme="newton")``).

The paper's step (scheme "warped") takes each element's rotation at the start of the step and solves once.
Over a step that turns elements far, that rotation is stale: a spinning body stretches. The Newton scheme
solves the nonlinear backward Euler step instead: with v the new velocities and x = x_n + h v, it minimises
the incremental potential

    Phi(v) = 1/2 (v - v_n)^T M (v - v_n) + h alpha/2 v^T M v - h (alpha M v_r)^T v + Psi(x_n + h v)
             + beta / (2h) sum_e |u_e(x_n + h v) - u_e(x_n)|^2_{K_e} - h f_ext^T v

(Psi the body's strain energy, FemBody.elastic_energy: the warped one with the rotations of x, or a hyperelastic
model's, softbody.constitutive; alpha M the mass-proportional
Rayleigh damping, less the rigid motion's share alpha M v_r it spares a free body; the beta term the
stiffness-proportional damping, the strain over the step measured from the elements' unrotated displacements
u_e = R_e^T x_e - X_e: zero for any rigid motion, however far it turns in a step, where beta K'_n v, the warped
step's form, damps the chord a turning node follows; f_ext gravity and loads) under the supports, and under the
contacts and attachments of the integration layer's velocity hook, exactly as the warped step's solve. A
multistep scheme (softbody.schemes' BDF2) starts the step elsewhere: x_n, v_n and u_e(x_n) become its Start.

Iteration k, from the rigid prediction v_0 (the body's rigid motion carried through the step, the rest of
its velocities as they are): the gradient g_k = dPhi/dv (the exact gradients of Psi and of the damping term,
rotations' derivatives included: FemBody.element_energy_gradients, rotations re-evaluated at x_k), the warped
tangent A_k = (1 + h alpha) M + (h beta + h^2) K'(x_k) (symmetric positive definite; the rotations' own
derivatives left out; a hyperelastic model's: its analytic Hessian, projected, in place of h^2 K'), and
one constrained solve of A_k v' = A_k v_k - g_k through the same machinery as a warped step (supports,
contacts, friction, coupling, the factorisations and the PCG preconditioner); the first solve takes its
whole step (it makes the iterate satisfy the constraints). Later steps are whole where they lower the residual;
else a line search along v' - v_k halves the step until Phi falls by the Armijo condition (the constrained
solve minimises the quadratic model over the constraints, so the direction descends; where friction makes it
not, the full step is taken); a direction along which no step down to ``min_step`` falls stops the step with
SimulationDiverged. The iteration stops when the
residual (the gradient less the constraint impulses of the last solve, relative to the step's loads) is
below ``tol`` after a full step (or, in absolute terms, below the round-off of the elastic forces' terms, or
stops falling within FLOOR x tol: a very stiff body's gradient is a small difference of large terms), and
raises SimulationDiverged with the residual history after ``max_iter`` solves. With contacts (the hook adds
them), the iterates may switch between active sets and stick/slip states: a residual within CYCLE tolerances
that cycles, or that the whole step raises, is accepted as the last solve taken whole (a RuntimeWarning at the
first such step; NewtonReport.cycled, NewtonStepper.cycled_steps).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np

from .body import FemBody
from .errors import InvalidInputError, SimulationDiverged, SolverError
from .integrator import IterativeSettings, LinearSystem, Timings, assembled_system, timed
from .linsolve import SpdSolver
from .preconditioner import Preconditioner


TANGENTS = ("auto", "warped", "exact")
# "auto": the warped tangent until an iteration reduces the residual by less than this factor, then the exact one
SLOW = 0.3
# a residual that stops falling within this many tolerances of it is at its round-off floor: accepted
FLOOR = 10.0
# relative round-off of the elastic forces' terms, below which an absolute residual is as good as zero
ROUNDOFF = 1e-12
# contacts and friction may make the iterates switch between active sets or stick/slip states (a contact at
# the edge of its cone), so that the residual cycles or no step along the direction lowers it: accepted
# within this many tolerances (the contact solve itself ends on its friction iteration; non-penetration
# holds exactly after every solve)
CYCLE = 1000.0
CYCLE_MAX = 1e-2  # ... and never above this relative residual, whatever the tolerance


@dataclass
class NewtonSettings:
    """tol: residual (relative to the step's loads) at which the iteration stops; max_iter: solves per step
    at most; armijo: the sufficient decrease of the line search; min_step: the smallest line-search step;
    tangent: "warped" (K' at the iterate: cheap, but blind to the rotations' own turning, so it converges
    slowly where elements are strained and turn), "exact" (the energy's Hessian, rotations' derivatives
    included, per element by central differences of the exact gradient and made positive semi-definite:
    FemBody.energy_hessian_blocks; several times the cost of an assembly) or "auto" (warped until an
    iteration reduces the residual by less than SLOW, then exact for the rest of the step). A body of a
    hyperelastic model (FemBody(model=...)) always takes its analytic Hessian."""

    tol: float = 1e-5
    max_iter: int = 25
    armijo: float = 1e-4
    min_step: float = 1.0 / 4096
    tangent: str = "auto"

    def __post_init__(self):
        if not (isinstance(self.tol, (int, float, np.floating)) and 0 < self.tol < 1):
            raise InvalidInputError(f"newton tol must be a number in (0, 1), got {self.tol!r}")
        if not (isinstance(self.armijo, (int, float, np.floating)) and 0 < self.armijo < 0.5):
            raise InvalidInputError(f"newton armijo (sufficient decrease) must be a number in (0, 0.5), got {self.armijo!r}")
        if not (isinstance(self.min_step, (int, float, np.floating)) and 0 < self.min_step < 1):
            raise InvalidInputError(f"newton min_step must be a number in (0, 1), got {self.min_step!r}")
        if not (isinstance(self.max_iter, (int, np.integer)) and self.max_iter >= 1):
            raise InvalidInputError(f"newton max_iter must be an integer >= 1, got {self.max_iter!r}")
        if self.tangent not in TANGENTS:
            raise InvalidInputError(f"newton tangent must be one of {TANGENTS}, got {self.tangent!r}")


@dataclass
class NewtonReport:
    """The last step's iterations: the number of solves, the residual before each solve and after the last
    (relative), the line-search step of each solve, and the tangent it ended with."""

    iterations: int = 0
    residuals: list[float] = field(default_factory=list)
    steps: list[float] = field(default_factory=list)
    tangent: str = "warped"
    cycled: bool = False  # accepted within CYCLE tolerances where contacts switching stall it, not at the tolerance

    @property
    def residual(self) -> float:
        return self.residuals[-1] if self.residuals else float("nan")


class Start(NamedTuple):
    """Where a Newton step starts: positions x (N, 3) [m] (x + h v at its end), velocities v (N, 3) [m/s] (the
    momentum change is M (v_new - v)), and the elements' unrotated displacements u (E, 3k) [m] from which its
    damping measures the strain over the step."""

    x: np.ndarray
    v: np.ndarray
    u: np.ndarray

    @classmethod
    def of(cls, body: FemBody) -> "Start":
        """The body's current state: a backward Euler step's start."""
        x = body.positions.copy()
        return cls(x, body.velocities.copy(), body.local_displacements(x, body.rotations(x)))


@dataclass
class _BodyStep:
    """One body's data over a Newton step: its start, loads, the rigid motion's damping relief, and the iterate's
    gradient and potential."""

    body: FemBody
    start: Start
    f_ext: np.ndarray
    spared: np.ndarray | float = 0.0  # alpha M v_r (N, 3) [N]: the damping force the rigid motion is spared

    @property
    def x0(self) -> np.ndarray:
        return self.start.x

    @property
    def v0(self) -> np.ndarray:
        return self.start.v

    def gradient(self, v: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        """(g (N, 3) [N s], dPsi/dx (N, 3) [N]) at the iterate v."""
        body = self.body
        alpha, beta = body.damping
        x = self.x0 + h * v
        R = body.rotations(x) if body.law is None or beta else None  # (a hyperelastic energy needs none)
        xe = x[body.mesh.elements]
        dpsi = body.scatter_nodal(body.element_energy_gradients(xe, R))
        g = body.mass_product(v - self.v0) + h * (alpha * body.mass_product(v) - self.spared) + h * (dpsi - self.f_ext)
        if beta:  # dD/dv (D = beta / (2h) sum_e |u_e(x) - u_e,start|^2_K, rotations' derivatives included), apart: the
            # strain over the step is small where the strain is large (a stiff body), and taken on its own it keeps
            # its digits (one pass over beta u_start / (h + beta) stalled a stiff cube's iteration at its round-off)
            g = g + beta * body.scatter_nodal(body.warped_energy_gradients(xe, R, offset=self.start.u))
        return g, dpsi

    def potential(self, v: np.ndarray, h: float) -> float:
        """Phi(v) [J]: the incremental potential of the module doc (units of energy)."""
        body = self.body
        alpha, beta = body.damping
        dv = v - self.v0
        x = self.x0 + h * v
        phi = (0.5 * np.sum(dv * body.mass_product(dv)) + 0.5 * h * alpha * np.sum(v * body.mass_product(v))
               + body.elastic_energy(x) - h * np.sum((self.f_ext + self.spared) * v))
        if beta:
            du = body.local_displacements(x, body.rotations(x)) - self.start.u
            phi += 0.5 * beta / h * np.sum(du * (body.Ke @ du[:, :, None])[:, :, 0])
        return float(phi)


def rigid_prediction(body: FemBody, h: float) -> np.ndarray:
    """A first Newton iterate (N, 3) [m/s]: the velocity that carries the body over the step h [s] with the
    rigid motion of its current velocities (centre of mass, and the angular velocity of its angular momentum,
    turned through the exact rotation) plus the rest of the velocity field as it is. A spinning body's
    prediction is turned, not stretched along its tangents, so the iteration starts near the solution. A
    BodyStack: each member's rigid motion apart."""
    offsets = getattr(body, "offsets", None)
    if offsets is not None:
        return np.concatenate([_rigid_prediction(body.positions[a:b], body.velocities[a:b], body.node_mass[a:b], h)
                               for a, b in zip(offsets[:-1].tolist(), offsets[1:].tolist())])
    return _rigid_prediction(body.positions, body.velocities, body.node_mass, h)


def _rigid_prediction(x: np.ndarray, v: np.ndarray, m: np.ndarray, h: float) -> np.ndarray:
    """rigid_prediction of nodes at x (N, 3) with velocities v (N, 3) and masses m (N,) [kg]."""
    mass = m.sum()
    c, vc = m @ x / mass, m @ v / mass
    r, vr = x - c, v - vc
    L = m @ np.cross(r, vr)
    inertia = np.eye(3) * (m @ np.einsum("ij,ij->i", r, r)) - np.einsum("i,ij,ik->jk", m, r, r)
    try:
        w = np.linalg.solve(inertia, L)
    except np.linalg.LinAlgError:  # a body of collinear nodes: no rotation to predict
        return v.copy()
    angle = float(np.linalg.norm(w)) * h
    if angle < 1e-12:
        return v.copy()
    k = w / np.linalg.norm(w)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    Q = np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K
    x_new = c + h * vc + r @ Q.T + h * (vr - np.cross(w, r))
    return (x_new - x) / h


def cycling(residuals: list[float], bound: float, period: int = 2, repeats: int = 2, rel: float = 0.02) -> bool:
    """Whether the last residuals repeat with ``period`` (each within ``rel`` of the one ``period`` solves
    before, ``repeats`` times over) at or below ``bound``: iterates alternating between friction states
    rather than converging."""
    n = period * repeats
    if len(residuals) < n + period or residuals[-1] > bound:
        return False
    tail = np.asarray(residuals[-(n + period):])
    return bool(np.all(np.abs(tail[period:] - tail[:-period]) <= rel * tail[period:]))


class NewtonStepper:
    """Newton iterations on the backward Euler step (module doc), owned by a Simulation; ``report`` holds the
    last step's iterations and residuals."""

    def __init__(self, settings: NewtonSettings | None = None):
        self.settings = settings or NewtonSettings()
        self.report = NewtonReport()
        self.cycled_steps = 0  # steps accepted on contact switching (NewtonReport.cycled), over the run

    def _accept_cycle(self, report: NewtonReport, step: int, time: float) -> None:
        """Count a step accepted on contact switching, and say so at the first."""
        report.cycled = True
        self.cycled_steps += 1
        if self.cycled_steps == 1:
            warnings.warn(
                f"Newton's step {step} (t = {time:.6g} s) stalled on contacts switching between iterates at residual "
                f"{report.residuals[-1]:.2e} (tolerance {self.settings.tol:g}): accepted, as later such steps are "
                "(counted in cycled_steps of the Simulation's newton); a smaller dt lets it converge",
                RuntimeWarning, stacklevel=4)

    def solve(self, bodies: list[FemBody], h: float, loads: list[np.ndarray], solvers: list[SpdSolver],
              methods: list[str], iterative: IterativeSettings, timings: Timings | None,
              solve: Callable[[list[LinearSystem]], list[np.ndarray]], time: float, step: int,
              contacts: bool = False, preconditioners: list[Preconditioner | None] | None = None,
              prediction: list[np.ndarray] | None = None,
              starts: list[Start] | None = None) -> list[np.ndarray]:
        """The new velocities (N_i, 3) of ``bodies`` after the step h [s], under loads (N_i, 3) [N]; ``solve``
        solves the step systems with every constraint (supports, contacts: the Simulation's); contacts: whether
        ``solve`` adds contacts and friction (then a residual within CYCLE tolerances that cycles, or that the
        whole step raises, is accepted: the active set and the stick/slip states switch between iterates);
        preconditioners: the bodies' for the iterative path, kept by the stepper (None: fresh ones); prediction: the
        first iterates (N_i, 3) [m/s] (None: rigid_prediction over h); starts: per body where the step starts
        (Start; None: the bodies' current states; a multistep scheme's combination of its past states,
        softbody.schemes)."""
        s = self.settings
        report = self.report = NewtonReport()
        states = [self._start(b, h, f, None if starts is None else starts[i]) for i, (b, f) in enumerate(zip(bodies, loads))]
        v = [rigid_prediction(b, h) for b in bodies] if prediction is None else [np.array(p, float) for p in prediction]
        # the residual's own round-off [N s]: the elastic forces are differences of terms of the size of
        # sum_e |K_e X_e|, which a stiff body at rest makes far larger than the step's impulses
        roundoff = ROUNDOFF * h * np.sqrt(sum(float(np.sum(b.rest_element_loads ** 2)) for b in bodies))
        scale = None
        impulses = None  # A v' - b of the last solve, per body: the constraints' impulses
        alpha = 1.0
        tangent = report.tangent = "warped" if s.tangent == "auto" else s.tangent
        if any(b.law is not None for b in bodies):
            report.tangent = "exact"  # a hyperelastic model's Hessian, whatever the setting
        grads = None
        for it in range(s.max_iter + 1):
            if grads is None:
                with timed(timings, "forces"):
                    grads = [st.gradient(vi, h) for st, vi in zip(states, v)]
            if impulses is not None:
                if scale is None:  # the step's impulses, for the residual: the momentum change, the elastic
                    # forces', the loads' and the constraints' (supports driven, contacts) after the first solve
                    scale = sum(np.linalg.norm(st.body.mass_product(vi - st.v0)) + h * np.linalg.norm(dpsi)
                                + h * np.linalg.norm(st.f_ext) + np.linalg.norm(r)
                                for st, vi, (_, dpsi), r in zip(states, v, grads, impulses)) or 1.0
                absolute = np.sqrt(sum(np.sum((g - r) ** 2) for (g, _), r in zip(grads, impulses)))
                residual = absolute / scale
                report.residuals.append(float(residual))
                if alpha == 1.0 and (residual <= s.tol or absolute <= roundoff or self._stalled(report.residuals)):
                    return v
                if alpha == 1.0 and contacts and cycling(report.residuals, min(CYCLE * s.tol, CYCLE_MAX)):
                    self._accept_cycle(report, step, time)
                    return v
                if tangent == "warped" and s.tangent == "auto" and len(report.residuals) > 1 \
                        and residual > SLOW * report.residuals[-2]:
                    tangent = report.tangent = "exact"  # the rotations' own turning matters: take it in
            if it == s.max_iter:
                break
            systems = []
            pres = preconditioners or [None] * len(states)
            for st, vi, (g, _), solver, method, pre in zip(states, v, grads, solvers, methods, pres):
                body = st.body
                x = st.x0 + h * vi
                with timed(timings, "assembly"):
                    alpha, beta = body.damping
                    # a hyperelastic model's Hessian is analytic and cheap: always its own
                    exact = tangent == "exact" or body.law is not None
                    if not exact or beta:  # the warped stiffness at the iterate (the damping's tangent)
                        with timed(timings, "rotations"):
                            R = body.rotations(x)
                        K, _ = body.warped_stiffness_upper(R)
                    if exact:
                        A = h * h * body.energy_hessian_blocks(x) + (
                            body.system_blocks(K, 1.0 + h * alpha, h * beta) if beta else (1.0 + h * alpha) * body.M_blocks)
                    else:
                        A = body.system_blocks(K, 1.0 + h * alpha, h * beta + h * h)
                    Av = (body.pattern.to_bsr(A) @ vi.reshape(-1)).reshape(-1, 3)
                b = Av - g
                systems.append(assembled_system(body, A, b, solver, method, iterative, timings, vi, (Av, g), pre=pre))
            try:
                new = solve(systems)
            except (SolverError, np.linalg.LinAlgError) as exc:  # a tangent no longer positive definite
                raise SimulationDiverged(
                    f"Newton's iteration failed at step {step} (t = {time:.6g} s), solve {it + 1}: {exc}; residuals "
                    f"{', '.join(f'{r:.2e}' for r in report.residuals)}. State kept; try a smaller dt.",
                    step=step, time=time) from exc
            impulses = [system.apply(vn) - system.b for system, vn in zip(systems, new)]
            d = [vn - vi for vn, vi in zip(new, v)]
            with timed(timings, "forces"):
                full = [st.gradient(vn, h) for st, vn in zip(states, new)]
            after = None if scale is None else np.sqrt(sum(np.sum((g - r) ** 2) for (g, _), r in zip(full, impulses)))
            if it == 0 or (after is not None and after < (1.0 - 1e-4) * report.residuals[-1] * scale):
                alpha = 1.0  # the whole step lowers the residual (with contacts, Phi alone does not tell)
            else:
                if contacts and report.residuals[-1] <= min(CYCLE * s.tol, CYCLE_MAX):
                    # near the tolerance, the whole step raises the residual: the contacts' switching between
                    # iterates sets the floor; the last solve is taken whole (its contacts, friction and rigid
                    # velocity changes belong to it: the contact hook keeps them), as a warped step from an
                    # iterate this close; the report gives its own residual
                    self._accept_cycle(report, step, time)
                    return self._take(report, new, it, after / scale)
                alpha = self._line_search(states, v, d, [g for g, _ in grads], h)
            if alpha is None and report.residuals and (report.residuals[-1] <= FLOOR * s.tol or absolute <= 10 * roundoff):
                # at the round-off floor the potential cannot fall measurably: as good as it gets. With contacts the
                # last solve is taken (the hook keeps its contacts and rigid velocity changes, which must match)
                return self._take(report, new, it, after / scale) if contacts else v
            if alpha is None and tangent == "warped" and s.tangent == "auto":
                alpha, tangent = 0.0, "exact"  # the warped tangent points nowhere useful: solve again, exactly
                report.tangent = tangent
            elif alpha is None:
                raise SimulationDiverged(
                    f"Newton's iteration found no descent at step {step} (t = {time:.6g} s), solve {it + 1}: the "
                    f"incremental potential does not fall along the step even at {self.settings.min_step:g} of it "
                    f"(elements turned inside out make it non-smooth); residuals "
                    f"{', '.join(f'{r:.2e}' for r in report.residuals)}. State kept; try a smaller dt.",
                    step=step, time=time)
            report.steps.append(alpha)
            v = [vi + alpha * di for vi, di in zip(v, d)]
            grads = full if alpha == 1.0 else None
            report.iterations = it + 1
        raise SimulationDiverged(
            f"Newton's iteration did not converge in {s.max_iter} solves at step {step} (t = {time:.6g} s): "
            f"residuals {', '.join(f'{r:.2e}' for r in report.residuals)} (tolerance {s.tol:g}). State kept; try a "
            "smaller dt, a looser tolerance (newton_tol) or more iterations (newton_max_iter).",
            step=step, time=time)

    @staticmethod
    def _take(report: NewtonReport, new: list[np.ndarray], it: int, residual: float) -> list[np.ndarray]:
        """Accept the last solve's velocities ``new`` whole, with their own relative residual in the report."""
        report.iterations = it + 1
        report.steps.append(1.0)
        report.residuals.append(float(residual))
        return new

    def _stalled(self, residuals: list[float]) -> bool:
        """Whether the residual has reached the round-off floor of the step just above the tolerance: within
        FLOOR x tol, and the last two solves took off less than a tenth of it (a stiff body's gradient is a
        small difference of large terms, which no iteration resolves further)."""
        tol = self.settings.tol
        return (len(residuals) >= 3 and residuals[-1] <= FLOOR * tol
                and min(residuals[-3:-1]) - residuals[-1] < 0.1 * residuals[-1])

    @staticmethod
    def _start(body: FemBody, h: float, f_ext: np.ndarray, start: Start | None = None) -> _BodyStep:
        start = Start.of(body) if start is None else start
        relief = body.rigid_damping_relief(h, body.mass_product(start.v))
        return _BodyStep(body, start, np.asarray(f_ext, float), 0.0 if relief is None else relief / h)

    def _line_search(self, states: list[_BodyStep], v: list[np.ndarray], d: list[np.ndarray], g: list[np.ndarray],
                     h: float) -> float | None:
        """The step along d from v: 1, halved until Phi falls by the Armijo condition (1 if d does not descend:
        friction or a contact made the direction; None if no step down to min_step falls)."""
        slope = sum(float(np.sum(gi * di)) for gi, di in zip(g, d))
        if slope >= 0:
            return 1.0
        phi0 = sum(st.potential(vi, h) for st, vi in zip(states, v))
        alpha = 1.0
        while alpha >= self.settings.min_step:
            phi = sum(st.potential(vi + alpha * di, h) for st, vi, di in zip(states, v, d))
            if phi <= phi0 + self.settings.armijo * alpha * slope:
                return alpha
            alpha *= 0.5
        return None
