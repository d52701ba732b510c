"""Exceptions raised by softbody.

Every error about user input derives from :class:`InvalidInputError`, itself a
``ValueError``, and names the offending value and what would be valid.
"""
from __future__ import annotations


class InvalidInputError(ValueError):
    """A user-supplied value (material, mesh, scene, option) is invalid."""


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
