"""The time-stepping schemes of a Simulation: each turns one step's systems into the bodies' new states.

A scheme is a small object with ``advance(sim, solve, supports, t_next, timings, contacts) -> Advance``; the
Simulation picks it once, by name (``SCHEMES``), and its step reads: supports, ``advance``, check, commit.

- "warped" (:class:`Warped`): the paper's step, backward Euler with each element's rotation at the start of the
  step and one linear solve. First order; its numerical damping takes energy out of every vibration and slows a
  spin (docs/scheme_trade.md).
- "newton" (:class:`NewtonEuler`): exact backward Euler, Newton iterations on the incremental potential
  (softbody.newton). Keeps a spinning body's shape; first order and as dissipative as the warped step.
- "bdf2" (:class:`Bdf2`): the second-order backward differentiation formula, by the same Newton iterations:
  x_{n+1} = (4 x_n - x_{n-1}) / 3 + 2h/3 v_{n+1} and v_{n+1} = (4 v_n - v_{n-1}) / 3 + 2h/3 a_{n+1}, which is a
  backward Euler step of size 2h/3 from the state ((4 x_n - x_{n-1}) / 3, (4 v_n - v_{n-1}) / 3) (its damping
  measuring the strain rate (3 u_{n+1} - 4 u_n + u_{n-1}) / 2h alike, u the unrotated displacements). Second order:
  its numerical damping of a motion it resolves falls as (omega h)^3 rather than backward Euler's (omega h)^1, so it
  keeps a spin and a pendulum's swing where backward Euler slows them, yet it still damps the vibrations a step
  cannot resolve, and it is as stable as backward Euler at large steps (L-stable). It keeps linear momentum
  exactly, angular momentum to its order, and a spinning body's shape as the Newton scheme does. Its first step,
  and the first after the state was changed from outside (positions or velocities assigned, a step not
  committed), is a backward Euler step. The schemes that keep a linear body's energy exactly fail on a warped one:
  the implicit midpoint rule and the trapezoidal rule (Newmark's average acceleration) swap energy in and out of a
  spurious stretch every other step on a stiff cube spinning at 5 rev/s until their Newton iterations fail, within
  0.4 s at every step tried (docs/energy_schemes.md); a discrete gradient (Gonzalez) taken in node coordinates was
  tried too, and is not smooth where an element turns.
  Core bodies only: the coupled contact solve of integration.World is a backward Euler solve over dt, so World
  refuses it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from .body import FemBody
from .integrator import Constraints, Timings
from .newton import Start, rigid_prediction

if TYPE_CHECKING:
    from .simulation import Simulation

# solve(systems, held=None): the step systems' velocities under the supports (or under ``held``, per body the
# supported nodes held by other velocities) and, in a World, its contacts
Solve = Callable[..., list[np.ndarray]]


@dataclass
class Advance:
    """One step's outcome, before it is checked and committed: per body the new (positions (N, 3) [m],
    velocities (N, 3) [m/s]); ``rotations`` per body the element rotations the step's systems were built with
    (the warped step's, for softbody.linearisation.RotationWatch; None for schemes that iterate on them)."""

    states: list[tuple[np.ndarray, np.ndarray]]
    rotations: list[np.ndarray] | None = None


class Scheme(Protocol):
    """What a time-stepping scheme does: advance every body of ``sim`` by sim.dt. ``iterates``: whether its steps
    are Newton iterations (Simulation.newton_report reports them)."""

    name: str
    iterates: bool

    def advance(self, sim: "Simulation", solve: Solve, supports: list[Constraints], t_next: float,
                timings: Timings, contacts: bool) -> Advance:
        """The bodies' new states; ``solve`` solves step systems under the supports (and, with ``contacts``, the
        caller's contacts), ``supports`` per body hold the positions at t_next."""
        ...

    def save_state(self) -> dict:
        """What the scheme carries from step to step, copied (softbody.state)."""
        ...

    def refusal(self, body: FemBody) -> str | None:
        """Why the scheme cannot step ``body`` (None: it can)."""
        ...

    def load_state(self, saved: dict, bodies: list[FemBody]) -> None:
        """Take back what :meth:`save_state` gave, for ``bodies``."""
        ...


class _OneStep:
    """A one-step scheme: it carries nothing from step to step."""

    def refusal(self, body: FemBody) -> str | None:
        return None

    def save_state(self) -> dict:
        return {}

    def load_state(self, saved: dict, bodies: list[FemBody]) -> None:
        pass


def newton_velocities(sim: "Simulation", h: float, solve: Solve, t_next: float, timings: Timings, contacts: bool,
                      prediction: list[np.ndarray] | None = None,
                      starts: list[Start] | None = None) -> list[np.ndarray]:
    """The velocities (N_i, 3) [m/s] of a backward Euler step of size h [s] from the bodies' current states (or
    ``starts``), by the Simulation's Newton stepper (softbody.newton; prediction and starts as there)."""
    bodies = sim.bodies
    solvers = [sim.solvers.solver(b, sim.solver_backend) for b in bodies]
    methods = [sim.linear_method(b) for b in bodies]
    pres = [None if m == "direct" else sim.solvers.preconditioner(b, s, sim.solver_backend)
            for b, s, m in zip(bodies, solvers, methods)]
    return sim.newton.solve(bodies, h, [sim.load(b) for b in bodies], solvers, methods, sim.settings, timings, solve,
                            t_next, sim.steps + 1, contacts=contacts, preconditioners=pres, prediction=prediction,
                            starts=starts)


class Warped(_OneStep):
    """The paper's step (module doc)."""

    name = "warped"
    iterates = False

    def refusal(self, body: FemBody) -> str | None:
        if body.law is not None:
            return (f"the warped step linearises the warped and linear models only; model {body.model!r} is stepped "
                    "by Simulation(..., scheme='newton') or scheme='bdf2'")
        return None

    def advance(self, sim, solve, supports, t_next, timings, contacts) -> Advance:
        for b in sim.bodies:  # (Simulation.bodies is a list a caller may append to)
            sim.admit(b)
        systems = [sim.system(b) for b in sim.bodies]
        vs = solve(systems)
        return Advance([(b.positions + sim.dt * v, v) for b, v in zip(sim.bodies, vs)],
                       [s.rotations for s in systems])


class NewtonEuler(_OneStep):
    """Exact backward Euler by Newton iterations (module doc, softbody.newton)."""

    name = "newton"
    iterates = True

    def advance(self, sim, solve, supports, t_next, timings, contacts) -> Advance:
        if not sim.bodies:  # nothing to iterate on: the caller's solve still runs (a World's rigid coupling)
            return Warped().advance(sim, solve, supports, t_next, timings, contacts)
        vs = newton_velocities(sim, sim.dt, solve, t_next, timings, contacts)
        return Advance([(b.positions + sim.dt * v, v) for b, v in zip(sim.bodies, vs)])


@dataclass
class _Past:
    """A step a Bdf2 took: its size h [s], its bodies, their states at its start and the states it produced
    (copies: the bodies' own arrays may be changed in place)."""

    h: float
    bodies: list[FemBody]
    before: list[tuple[np.ndarray, np.ndarray]]
    after: list[tuple[np.ndarray, np.ndarray]]

    def continues(self, bodies: list[FemBody], h: float) -> bool:
        """Whether a step of h from the bodies' current states continues this one: the same step size and bodies,
        standing where it left them (it was committed, and nothing has moved them since)."""
        return (h == self.h and len(self.bodies) == len(bodies) and all(a is b for a, b in zip(self.bodies, bodies))
                and all(np.array_equal(b.positions, x) and np.array_equal(b.velocities, v)
                        for b, (x, v) in zip(bodies, self.after)))


def _copies(states: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(x.copy(), v.copy()) for x, v in states]


class Bdf2:
    """BDF2 (module doc). ``pasts`` is its state across steps: the last two steps it took (the latest last), so
    that a step solved but not committed (Simulation.solve_step without commit, a step refused by its checks)
    leaves the one before it to continue from."""

    name = "bdf2"
    iterates = True

    def refusal(self, body: FemBody) -> str | None:
        return None

    def __init__(self):
        self.pasts: list[_Past] = []

    def _past(self, bodies: list[FemBody], h: float) -> _Past | None:
        """The past step the current states continue, if any."""
        return next((p for p in reversed(self.pasts) if p.continues(bodies, h)), None)

    def advance(self, sim, solve, supports, t_next, timings, contacts) -> Advance:
        if not sim.bodies:
            return Warped().advance(sim, solve, supports, t_next, timings, contacts)
        h = sim.dt
        bodies = list(sim.bodies)
        now = _copies([(b.positions, b.velocities) for b in bodies])
        past = self._past(bodies, h)
        if past is not None:
            states = self._bdf2(sim, solve, supports, t_next, timings, contacts, now, past)
        else:  # the first step, or the state changed from outside: a backward Euler step
            vs = newton_velocities(sim, h, solve, t_next, timings, contacts)
            states = [(x + h * v, v) for (x, _), v in zip(now, vs)]
        self.pasts = [p for p in self.pasts if p is past][-1:] + [_Past(h, bodies, now, _copies(states))]
        return Advance(states)

    def _bdf2(self, sim, solve, supports, t_next, timings, contacts, now, past: _Past) -> list[tuple[np.ndarray, np.ndarray]]:
        """The BDF2 step's states: a backward Euler step of 2h/3 from the combination of the two past states."""
        h = sim.dt
        hb = 2.0 * h / 3.0
        starts = [Start((4.0 * x - xp) / 3.0, (4.0 * v - vp) / 3.0, (4.0 * _strain(b, x) - _strain(b, xp)) / 3.0)
                  for b, (x, v), (xp, vp) in zip(sim.bodies, now, past.before)]
        # supported nodes: the end velocity that puts them on their targets x_n + h w (w the supports' own)
        held = [_held(c, x, st.x, h, hb) for c, (x, _), st in zip(supports, now, starts)]
        prediction = [(x + h * rigid_prediction(b, h) - st.x) / hb for b, (x, _), st in zip(sim.bodies, now, starts)]
        vs = newton_velocities(sim, hb, lambda systems: solve(systems, held), t_next, timings, contacts,
                               prediction=prediction, starts=starts)
        return [(st.x + hb * v, v) for st, v in zip(starts, vs)]

    def save_state(self) -> dict:
        """The past steps, copied (softbody.state)."""
        return {"pasts": [(p.h, _copies(p.before), _copies(p.after)) for p in self.pasts]}

    def load_state(self, saved: dict, bodies: list[FemBody]) -> None:
        """Take back the past steps of :meth:`save_state` for ``bodies`` (those they were saved from)."""
        self.pasts = [_Past(h, list(bodies), _copies(before), _copies(after))
                      for h, before, after in saved.get("pasts", [])]


def _strain(body: FemBody, x: np.ndarray) -> np.ndarray:
    """The elements' unrotated displacements (E, 3k) [m] at positions x (N, 3) [m]."""
    return body.local_displacements(x, body.rotations(x))


def _held(c: Constraints, x: np.ndarray, start: np.ndarray, h: float, hb: float) -> Constraints:
    """The supports c of a step of h [s] from positions x (N, 3) [m] (their targets x + h w, w c's velocities),
    as velocities of a step of hb [s] from positions ``start`` (N, 3) [m] to the same targets; c's frames kept."""
    w = c.value if c.frames is None else np.einsum("mij,mj->mi", c.frames, c.value)  # global
    target = (x[c.nodes] + h * w - start[c.nodes]) / hb
    local = target if c.frames is None else np.einsum("mij,mi->mj", c.frames, target)
    return Constraints(c.nodes, c.mask, local, c.frames)


SCHEMES: dict[str, Callable[[], Scheme]] = {"warped": Warped, "newton": NewtonEuler, "bdf2": Bdf2}
