"""Saved states: everything a Simulation carries from one step to the next, to continue from later (or in another
process) exactly as the original would have.

A step reads more than the bodies' positions and velocities: the iterative path's preconditioner (a factorisation
of an earlier step's matrix, its frames, its cached columns and the last velocities for the warm start), the
Newton scheme's counters, the time and the step count. :class:`SimulationState` holds copies of all of it, in
plain arrays (the factor as the values it was made from, made again on restore with the same analysis), so that it
pickles and can be written to disk: :meth:`SimulationState.write` and :func:`read_state`.

What a restore does not bring back: the loads a user set (``Simulation.external_forces``) and the bodies' supports
stay as they are now (they are inputs, not state); kernels compiled since the save (softbody.compilation) make the
continuation agree with the original to round-off rather than to the bit.
"""
from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InvalidInputError

FORMAT = 2  # bumped when the layout of a saved state changes


@dataclass
class SimulationState:
    """A Simulation's state after its step ``steps`` (time ``t`` [s]).

    bodies: per stepped body (Simulation.bodies, a BodyStack as one) its (positions (N, 3) [m], velocities (N, 3)
    [m/s]); preconditioners: softbody.solvers.BodySolvers.save_state; newton: the Newton stepper's counters and last
    report; kernels: whether the compiled kernels stepped when it was saved; scheme: what the time-stepping scheme
    carries across steps (softbody.schemes: a multistep scheme's past states; empty for the others); models: each
    stepped body's elastic model (FemBody.model).
    """

    t: float
    steps: int
    bodies: list[tuple[np.ndarray, np.ndarray]]
    preconditioners: dict
    newton: dict
    kernels: bool
    format: int = FORMAT
    scheme: dict | None = None
    models: list[str] | None = None  # each stepped body's elastic model (None: saved before models were recorded)

    def write(self, path: str | Path) -> Path:
        """Write this state to ``path`` (pickle); ``Simulation.restore_state(path)`` reads it back."""
        return write_state(self, path)

    def check(self, bodies: list) -> None:
        """Raise InvalidInputError unless ``bodies`` (the stepped bodies) are those this state was saved from (their
        number and node counts)."""
        have = [b.n_nodes for b in bodies]
        want = [len(x) for x, _ in self.bodies]
        if have != want:
            raise InvalidInputError(f"the saved state is of {len(want)} stepped bodies of {want} nodes, this one "
                                    f"steps {len(have)} of {have}: build the same scene (the same bodies, added in the "
                                    "same order) before restoring")
        models = [getattr(b, "model", None) for b in bodies]
        if self.models is not None and models != list(self.models):
            raise InvalidInputError(f"the saved state is of bodies of the models {list(self.models)}, these are "
                                    f"{models}: build the same scene (the same FemBody(model=...)) before restoring")


def write_state(state: Any, path: str | Path) -> Path:
    """Write a saved state (a SimulationState, or integration's WorldState) to ``path`` (pickle; parent folders
    made). Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        pickle.dump(state, f, protocol=pickle.HIGHEST_PROTOCOL)
    return path


def read_state(path: str | Path, kind: type | None = None) -> Any:
    """A saved state written by :func:`write_state`; ``kind`` the class it must be (else InvalidInputError). Only
    read files you wrote: a pickle can run code as it loads."""
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"no saved state at {path}")
    try:
        with open(path, "rb") as f:
            state = pickle.load(f)
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, ValueError) as exc:
        raise InvalidInputError(f"{path} is not a saved state of softbody ({exc})") from None
    if kind is not None and not isinstance(state, kind):
        raise InvalidInputError(f"{path} holds a {type(state).__name__}, not a {kind.__name__}")
    if getattr(state, "format", None) != FORMAT:
        raise InvalidInputError(f"{path} is a saved state of format {getattr(state, 'format', None)}, this softbody "
                                f"reads format {FORMAT}")
    return state


def copy_pairs(pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Copies of (positions, velocities) pairs."""
    return [(np.array(x, dtype=float), np.array(v, dtype=float)) for x, v in pairs]


def not_copyable(what: str, kind: str):
    """A __reduce_ex__ / __deepcopy__ that refuses with what to use instead."""
    def refuse(self, *args: Any, **kwargs: Any):
        raise TypeError(f"a {kind} cannot be copied or pickled: it holds {what}. Save and restore its state instead: "
                        f"state = obj.save_state(); obj.restore_state(state); state.write(path) and "
                        f"obj.restore_state(path) in a new process with the same scene built")
    return refuse


__all__ = ["SimulationState", "write_state", "read_state", "FORMAT"]
