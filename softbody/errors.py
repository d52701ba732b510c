"""Exceptions raised by softbody.

Every error about user input derives from :class:`InvalidInputError`, itself a
``ValueError``, and names the offending value and what would be valid.
"""
from __future__ import annotations

import math


class InvalidInputError(ValueError):
    """A user-supplied value (material, mesh, scene, option) is invalid."""


def finite_number(value, name: str, minimum: float | None = None, strict: bool = True, unit: str = "") -> float:
    """``value`` as a float, or InvalidInputError naming ``name`` unless it is finite and
    > minimum (strict) / >= minimum. unit, e.g. "[s]", goes into the message."""
    bound = "" if minimum is None else f" {'>' if strict else '>='} {minimum:g}"
    message = f"{name} must be a finite number{bound}{' ' + unit if unit else ''}, got "
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InvalidInputError(message + repr(value)) from None
    if not math.isfinite(v) or (minimum is not None and (v <= minimum if strict else v < minimum)):
        raise InvalidInputError(message + repr(v))
    return v


class MeshError(InvalidInputError):
    """A mesh is malformed: bad coordinates, indices, node counts or inverted elements."""


class SolverError(RuntimeError):
    """The linear solver failed (e.g. the system matrix is not positive definite)."""


class SimulationDiverged(RuntimeError):
    """A step produced non-finite values or unbounded energy.

    The body state is left as it was before the failing step.
    """

    def __init__(self, message: str, step: int, time: float, element: int | None = None):
        super().__init__(message)
        self.step = step
        self.time = time
        self.element = element
