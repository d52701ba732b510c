"""Simulation: bodies, time, step and run; and the static solve."""
from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Mapping, MutableMapping
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from . import compilation, kernels
from .body import FemBody
from .errors import InvalidInputError, SimulationDiverged, finite_number
from .integrator import (Constraints, DirectSystem, IterativeSettings, LinearSystem, Timings, step_system,
                         support_constraints)
from .linearisation import RotationWatch
from .linsolve import BACKENDS, SpdSolver, choose_backend
from .newton import NewtonReport, NewtonSettings, NewtonStepper
from .schemes import SCHEMES, Scheme
from .solvers import BodySolvers
from .stack import BodyStack
from .state import SimulationState, copy_pairs, not_copyable, read_state

# A hook (bodies, their step systems, their supports, t_next) -> the bodies' new velocities (N_i, 3); the
# integration layer uses it to solve contacts and the coupling to rigid bodies for all bodies at once.
VelocitySolver = Callable[[list[FemBody], list[LinearSystem], list[Constraints], float], list[np.ndarray]]


METHODS = ("auto", "direct", "iterative")
# below this a direct factorisation per step is about as cheap; above it the iterative path is 3-7x
# faster without contact (benchmarks/step_no_contact.py) and faster over whole runs with contact
ITERATIVE_MIN_DOFS = 1500


def _gravity(gravity) -> np.ndarray:
    g = np.asarray(gravity, dtype=float)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise InvalidInputError(f"gravity must be three finite numbers [m/s^2], got {gravity!r}")
    return g


class ExternalForces(MutableMapping):
    """Extra loads per body, on top of gravity: ``sim.external_forces[body] = f`` with f (N, 3) [N] per node of that
    body (a body of the Simulation, or a member of one of its BodyStacks; in a World, one of ``world.bodies``),
    acting over every step until changed or deleted (``del sim.external_forces[body]``). Keyed by the body itself;
    checked when set: shape, finite values. The load is copied when set: change it by setting it again (or in place
    through ``sim.external_forces[body][:] = ...``)."""

    def __init__(self):
        self._loads: dict[int, tuple[FemBody, np.ndarray]] = {}

    def __setitem__(self, body: FemBody, force) -> None:
        if not isinstance(body, FemBody):
            raise InvalidInputError(f"external_forces is keyed by the body (a FemBody): sim.external_forces[body] = f, "
                                    f"got a key of type {type(body).__name__}")
        try:
            f = np.array(force, dtype=float)
        except (TypeError, ValueError):
            raise InvalidInputError(f"external force of a body of {body.n_nodes} nodes must be an ({body.n_nodes}, 3) "
                                    f"array [N], got {type(force).__name__}") from None
        if f.shape != (body.n_nodes, 3):
            raise InvalidInputError(f"external force of a body of {body.n_nodes} nodes must be an ({body.n_nodes}, 3) "
                                    f"array [N] (one force per node), got shape {f.shape}")
        if not np.isfinite(f).all():
            raise InvalidInputError(f"external force has non-finite entries (first at node "
                                    f"{int(np.flatnonzero(~np.isfinite(f).all(axis=1))[0])})")
        self._loads[id(body)] = (body, f)

    def _held(self, body) -> tuple[FemBody, np.ndarray] | None:
        held = self._loads.get(id(body))
        return held if held is not None and held[0] is body else None

    def __getitem__(self, body: FemBody) -> np.ndarray:
        held = self._held(body)
        if held is None:
            raise KeyError(body)
        return held[1]

    def __delitem__(self, body: FemBody) -> None:
        if self._held(body) is None:
            raise KeyError(body)
        del self._loads[id(body)]

    def __iter__(self):
        return iter([b for b, _ in self._loads.values()])

    def __len__(self) -> int:
        return len(self._loads)

    def __contains__(self, body) -> bool:
        return self._held(body) is not None


def body_solver(body: FemBody, backend: str = "auto") -> SpdSolver:
    """A new SPD solver on the body's pattern (solve_static's; a Simulation keeps its own per body, see
    softbody.solvers.BodySolvers). These solves are direct: for "amg" (a preconditioner only) "auto" chooses."""
    from .solvers import new_solver

    return new_solver(body, "auto" if backend == "amg" else backend)


class Simulation:
    """Steps one or more soft bodies with backward Euler or BDF2 (softbody.schemes).

    bodies: a FemBody or a list of them; dt: step [s] > 0; gravity [m/s^2]; solver: linear solver
    backend ("auto", "pardiso", "blocks", "superlu", or "amg": algebraic multigrid preconditioning the iterative
    path, the direct solves' backend then chosen as for "auto"; "auto" itself takes multigrid for bodies whose
    factor would be large, softbody.solvers.MULTIGRID_FACTOR_BYTES); max_energy: optional bound [J] on each
    body's kinetic plus elastic energy, above which a step raises SimulationDiverged; method: the linear solve ("auto",
    "direct", "iterative"), tol its relative tolerance on the iterative path; scheme: "warped" (the
    paper's step: rotations at the start of the step, one solve), "newton" (the nonlinear backward Euler
    step, softbody.newton: rotations re-evaluated, Newton iterations to the residual newton_tol, at most
    newton_max_iter solves; ``newton_report`` holds the last step's iterations and residuals) or "bdf2" (second
    order by the same Newton iterations: far less numerical damping of what it resolves, a spin and a swing kept;
    bodies without contact; softbody.schemes). ``scheme`` is read-only: a new Simulation takes another.
    ``external_forces[body] = f`` adds loads f (N, 3) [N] to a body's gravity for every step (ExternalForces);
    :meth:`save_state` / :meth:`restore_state` checkpoint the whole state (softbody.state).
    """

    def __init__(self, bodies: FemBody | Sequence[FemBody], dt: float, gravity=(0.0, 0.0, -9.81),
                 solver: str = "auto", max_energy: float | None = None, method: str = "auto",
                 tol: float = 1e-5, scheme: str = "warped", newton_tol: float = 1e-5, newton_max_iter: int = 25):
        bodies = [bodies] if isinstance(bodies, FemBody) else list(bodies)
        dt = finite_number(dt, "time step dt", 0.0, unit="[s]")
        if solver not in BACKENDS:  # also checked per body, but a world may start without bodies
            raise InvalidInputError(f"unknown solver backend {solver!r}; valid: {BACKENDS}")
        if max_energy is not None:
            if not (isinstance(max_energy, (int, float, np.number)) and math.isfinite(max_energy) and max_energy > 0):
                raise InvalidInputError(f"max_energy must be None or a finite number > 0 [J], got {max_energy!r}")
            max_energy = float(max_energy)
        self.bodies = bodies
        self.dt = dt
        self.gravity = _gravity(gravity)
        self.solver_backend = solver
        if method not in METHODS:
            raise InvalidInputError(f"method must be one of {METHODS}, got {method!r}")
        if solver == "amg" and method == "direct":
            raise InvalidInputError("solver 'amg' (algebraic multigrid) preconditions the iterative path: it needs "
                                    "method 'iterative' or 'auto', not 'direct'")
        if not (isinstance(tol, (int, float)) and 0 < tol < 1):
            raise InvalidInputError(f"tol must be a number in (0, 1), got {tol!r}")
        self.method = method
        self.settings = IterativeSettings(tol=float(tol))
        if scheme not in SCHEMES:
            raise InvalidInputError(f"scheme must be one of {tuple(SCHEMES)}, got {scheme!r}")
        self.stepper: Scheme = SCHEMES[scheme]()  # softbody.schemes: how a step advances the bodies
        for b in bodies:
            self.admit(b)
        self.newton = NewtonStepper(NewtonSettings(newton_tol, newton_max_iter))
        self.max_energy = max_energy
        self.t = 0.0
        self.steps = 0
        # seconds of the last step by phase: rotations, forces, assembly, factorize, solve
        self.timings: Timings = Timings()
        self._external_forces = ExternalForces()  # body -> (N, 3) extra loads [N], see ExternalForces
        self.solvers = BodySolvers()  # per body: the SPD solvers and preconditioners kept from step to step
        self.rotation_watch = RotationWatch()  # the warped step: bodies turning too fast for it, warned once each
        for b in bodies:
            self.solvers.solver(b, solver)  # fail early on a bad backend
        if solver == "amg":
            choose_backend(np.zeros(1, dtype=np.int32), np.zeros(0, dtype=np.int32), 0, "amg")  # pyamg installed?

    def admit(self, body) -> None:
        """Check that ``body`` is a FemBody the scheme can step (InvalidInputError saying why not)."""
        if not isinstance(body, FemBody):
            raise InvalidInputError(f"bodies must be FemBody instances, got {type(body).__name__}")
        why = self.stepper.refusal(body)
        if why is not None:
            raise InvalidInputError(f"scheme {self.stepper.name!r} cannot step this body: {why}")

    @property
    def external_forces(self) -> ExternalForces:
        """Extra loads per body, on top of gravity: ``sim.external_forces[body] = f`` (see ExternalForces)."""
        return self._external_forces

    @external_forces.setter
    def external_forces(self, loads) -> None:
        """Replace all extra loads by ``loads``, a mapping body -> (N, 3) [N] (each checked as when set one by one)."""
        if not isinstance(loads, Mapping):
            raise InvalidInputError(f"external_forces takes a mapping body -> (N, 3) forces [N], got {type(loads).__name__}")
        fresh = ExternalForces()
        for body, force in loads.items():
            fresh[body] = force
        self._external_forces = fresh

    def load(self, body: FemBody) -> np.ndarray:
        """The external load (N, 3) [N] on ``body``: gravity and its external_forces (a BodyStack: also its
        members')."""
        f_ext = body.node_mass[:, None] * self.gravity
        if not len(self.external_forces):
            return f_ext
        extra = self.external_forces.get(body)
        members = getattr(body, "members", ())  # a BodyStack: its members' loads, in their rows
        if any(m in self.external_forces for m in members):
            f_ext = f_ext.copy()
            for i, m in enumerate(members):
                if m in self.external_forces:
                    f_ext[body.rows(i)] += self.external_forces[m]
        return f_ext if extra is None else f_ext + extra

    def linear_method(self, body: FemBody) -> str:
        """"direct" or "iterative" for ``body`` (method "auto": iterative from ITERATIVE_MIN_DOFS on, and always
        with the "amg" backend, a preconditioner only)."""
        if self.method == "auto" and self.solver_backend == "amg":
            return "iterative"
        if self.method == "auto":
            return "iterative" if body.n_dofs >= ITERATIVE_MIN_DOFS else "direct"
        return self.method

    def system(self, body: FemBody) -> LinearSystem:
        """The warped backward Euler system of ``body`` for the next step (gravity and external_forces as loads)."""
        solver = self.solvers.solver(body, self.solver_backend)
        method = self.linear_method(body)
        return step_system(body, self.dt, self.load(body), solver, method, self.settings, self.timings,
                           None if method == "direct" else self.solvers.preconditioner(body, solver,
                                                                                       self.solver_backend))

    # ------------------------------------------------------------------ saved states
    def save_state(self) -> SimulationState:
        """Everything the next steps read, copied (softbody.state): continuing after :meth:`restore_state` of it is
        the same to the bit as continuing now. ``state.write(path)`` puts it on disk."""
        return SimulationState(
            self.t, self.steps, copy_pairs([(b.positions, b.velocities) for b in self.bodies]),
            self.solvers.save_state(self.bodies),
            {"cycled_steps": self.newton.cycled_steps, "report": copy.deepcopy(self.newton.report)},
            bool(kernels.ENABLED), scheme=self.stepper.save_state(), models=[b.model for b in self.bodies])

    def restore_state(self, state: SimulationState | str | Path) -> None:
        """Go back to a state of :meth:`save_state` (or one written to disk, read from its path): the bodies' positions
        and velocities, the time, the step count, the preconditioners, the Newton counters and what the scheme
        carries from step to step (BDF2's past steps). The bodies must be
        those it was saved from (the same meshes in the same order); loads and supports stay as they are now."""
        if isinstance(state, (str, Path)):
            state = read_state(state, SimulationState)
        if not isinstance(state, SimulationState):
            raise InvalidInputError(f"restore_state takes a SimulationState or its path, got {type(state).__name__}")
        state.check(self.bodies)
        for b, (x, v) in zip(self.bodies, copy_pairs(state.bodies)):
            b.positions, b.velocities = x, v
        self.t, self.steps = float(state.t), int(state.steps)
        self.solvers.load_state(self.bodies, state.preconditioners)
        self.newton.cycled_steps = int(state.newton["cycled_steps"])
        self.newton.report = copy.deepcopy(state.newton["report"])
        self.stepper.load_state(getattr(state, "scheme", None) or {}, self.bodies)
        if state.kernels != bool(kernels.ENABLED):
            warnings.warn(f"the state was saved with the compiled kernels {'on' if state.kernels else 'off'}, they are "
                          f"{'on' if kernels.ENABLED else 'off'} now: the continuation agrees with the original to "
                          "round-off, not to the bit", RuntimeWarning, stacklevel=2)

    __deepcopy__ = not_copyable("the bodies' solver factorisations (MKL PARDISO or compiled factors)", "Simulation")
    __reduce_ex__ = not_copyable("the bodies' solver factorisations (MKL PARDISO or compiled factors)", "Simulation")

    @property
    def scheme(self) -> str:
        """The time-stepping scheme's name ("warped", "newton", "bdf2"; softbody.schemes)."""
        return self.stepper.name

    @property
    def newton_report(self) -> NewtonReport:
        """The last Newton step's iterations and residuals (schemes "newton" and "bdf2")."""
        return self.newton.report

    def solve_step(self, solve_velocities: VelocitySolver | None = None,
                   timings: Timings | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """The new (positions, velocities) of every body after one step, checked (SimulationDiverged) but not
        yet applied: :meth:`commit` applies them. :meth:`step` is both.

        ``solve_velocities(bodies, systems, supports, t_next)`` -> velocities (N, 3) per body solves the step's
        systems in place of each system's own solve with its supports (a caller's contact solve: integration.World);
        ``timings`` collects the seconds by phase (a caller's, with its own phases around these; default a fresh
        :class:`Timings`, kept as ``self.timings``)."""
        if compilation.pending:  # a first run: switch to the compiled kernels once they are ready
            compilation.poll()
        t_next = self.t + self.dt
        self.timings = timings = Timings() if timings is None else timings
        for b in self.bodies:
            if isinstance(b, BodyStack):
                b.gather()  # members whose state the user assigned anew since the last step
        supports = [support_constraints(b, t_next, self.dt) for b in self.bodies]

        def solve(systems: list[LinearSystem], held: list[Constraints] | None = None) -> list[np.ndarray]:
            held = supports if held is None else held  # a scheme may hold the supported nodes by its own velocities
            if solve_velocities is not None:
                return solve_velocities(self.bodies, systems, held, t_next)
            return [system.solve(cons)[0] for system, cons in zip(systems, held)]

        advance = self.stepper.advance(self, solve, supports, t_next, timings, solve_velocities is not None)
        new = advance.states
        for i, (b, (x, v)) in enumerate(zip(self.bodies, new)):
            self._check(i, b, x, v)
        if advance.rotations is not None:  # the step is finite: did its elements turn too far for it?
            for i, (b, (_, v), rotations) in enumerate(zip(self.bodies, new, advance.rotations)):
                self.rotation_watch.check(i, b, v, self.dt, rotations)
        return new

    def commit(self, new: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Apply the states of :meth:`solve_step` and advance the time by dt."""
        for b, (x, v) in zip(self.bodies, new):
            b.positions, b.velocities = x, v
        self.t += self.dt
        self.steps += 1

    def step(self) -> None:
        """Advance every body by dt. On divergence raises SimulationDiverged and leaves the state untouched."""
        self.commit(self.solve_step())

    def _check(self, i: int, body: FemBody, x: np.ndarray, v: np.ndarray) -> None:
        # the sums are finite if every entry is (and short of 1e308): the usual case in two reductions
        finite = math.isfinite(float(np.add.reduce(x, axis=None))) and math.isfinite(float(np.add.reduce(v, axis=None)))
        bad = None if finite else ~(np.isfinite(x).all(axis=1) & np.isfinite(v).all(axis=1))
        worst = None
        if bad is not None and bad.any():
            node = int(np.flatnonzero(bad)[0])
            worst = int(np.flatnonzero((body.mesh.elements == node).any(axis=1))[0])
            msg = f"non-finite positions or velocities (first at node {node - self._first_node(body, node)})"
        elif self.max_energy is not None:
            energy = body.kinetic_energy(v) + body.elastic_energy(x)
            if energy <= self.max_energy:
                return
            u = body.local_displacements(x, body.rotations(x))
            worst = int(np.argmax(np.abs(u).max(axis=1)))
            msg = f"energy {energy:.3e} J exceeds the bound {self.max_energy:.3e} J"
        else:
            return
        what = f"body {i}"
        if isinstance(body, BodyStack):  # name the member the user knows, and number within it
            k = int(body.member_of(np.array([int(body.mesh.elements[worst, 0])]))[0])
            what = f"body {i} (a BodyStack): its member {k} (sim.bodies[{i}].members[{k}])"
            worst -= int(body.element_offsets[k])
        raise SimulationDiverged(
            f"{what} diverged at step {self.steps + 1} (t = {self.t + self.dt:.6g} s): {msg}; "
            f"worst element {worst}. State kept at t = {self.t:.6g} s; try a smaller dt or more damping.",
            step=self.steps + 1, time=self.t + self.dt, element=worst)

    @staticmethod
    def _first_node(body: FemBody, node: int) -> int:
        """The first node of the member of a BodyStack that holds ``node`` (0 for a plain body)."""
        if not isinstance(body, BodyStack):
            return 0
        return int(body.offsets[int(body.member_of(np.array([node]))[0])])

    def run(self, duration: float, callback: Callable[["Simulation"], object] | None = None,
            progress: bool = False) -> None:
        """Step for ``duration`` seconds (rounded to whole steps), calling ``callback(sim)`` after each step.

        progress=True shows a progress bar (tqdm).
        """
        run_steps(self.step, self.dt, duration, None if callback is None else lambda: callback(self), progress)


def run_steps(step: Callable[[], object], dt: float, duration: float,
              after_step: Callable[[], object] | None = None, progress: bool = False) -> None:
    """Call ``step()`` round(duration / dt) times, then ``after_step()`` each time; tqdm bar on request."""
    duration = finite_number(duration, "duration", 0.0, strict=False, unit="[s]")
    steps: Iterable[int] = range(int(round(duration / dt)))
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc="simulating", unit="step")
    for _ in steps:
        step()
        if after_step is not None:
            after_step()


def static_load(body: FemBody, g: np.ndarray, forces: np.ndarray | None = None) -> np.ndarray:
    """The static load (N, 3) [N]: gravity g (3,) [m/s^2] on the nodal masses plus ``forces`` (N, 3) [N], checked."""
    f = body.node_mass[:, None] * g
    if forces is not None:
        fx = np.asarray(forces, dtype=float)
        if fx.size != f.size or not np.all(np.isfinite(fx)):
            raise InvalidInputError(f"forces must be finite with shape {f.shape} [N], got shape {fx.shape}"
                                    + ("" if fx.size != f.size else " with non-finite entries"))
        f = f + fx.reshape(f.shape)
    return f


def solve_static(body: FemBody, gravity=(0.0, 0.0, -9.81), solver: str = "auto",
                 forces: np.ndarray | None = None) -> np.ndarray:
    """Small-strain static equilibrium K u = f_gravity (+ forces) with the body's supports.

    Fixed nodes get u = 0, prescribed nodes u = motion(0) - rest. Returns u (N, 3) [m]. Every model's small-strain
    limit (the same K): a hyperelastic body's large-deformation equilibrium is softbody.solve_equilibrium's.
    Raises InvalidInputError when the supports do not remove the rigid-body modes.
    """
    f = static_load(body, _gravity(gravity), forces)
    K = body.pattern.assemble(body.Ke)
    nodes, _ = body.constrained_targets(0.0, 1.0)
    u_c = np.zeros((len(nodes), 3))
    for ids, motion in body.prescribed:
        sel = np.searchsorted(nodes, ids)
        u_c[sel] = np.asarray(motion(0.0), float).reshape(-1, 3) - body.rest[ids]
    if not body.mesh.used_nodes()[nodes].any():
        raise InvalidInputError("solve_static needs supports: fix or prescribe nodes to remove the rigid-body modes")
    system = DirectSystem(body, K, f, body_solver(body, solver))
    try:
        u, _ = system.solve(Constraints.full(nodes, u_c))
    except Exception as exc:
        raise InvalidInputError(
            f"static problem is singular ({exc}); the supports must remove all rigid-body modes") from exc
    return u
