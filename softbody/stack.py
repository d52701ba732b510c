"""Several soft bodies stepped as one: a block-diagonal system.

Bodies of one element kind, material, damping, mass kind and warping (the same ``stack_key``) have nothing
in their step that tells them apart but their nodes. :class:`BodyStack` is a FemBody whose mesh is the
disjoint union of theirs: its matrices are block-diagonal (no element joins two members), so one rotation
pass, one assembly, one factorisation (or one PCG) and one collision pass step all of them, with a cost that
grows with their total nodes rather than with their number, and the same answer as stepping each alone.

The members stay the user's bodies: between steps their ``positions`` and ``velocities`` are views of rows
of the stack's (:meth:`BodyStack.scatter`), and a member whose state was assigned anew, or whose supports
changed, is read back before the next step (:meth:`BodyStack.gather`, which softbody.Simulation and the World
call at the start of every step).
"""
from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np

from .body import FemBody
from .errors import InvalidInputError
from .locking import LockingWarning
from .material import Regions
from .mesh import Mesh


def stack_key(body: FemBody) -> tuple:
    """What must agree for bodies to share a stack: element kind, material, model (warping), damping, mass kind, hex rotation
    and volumetric form (everything a step reads apart from the mesh and the state); a body of Regions stacks with
    none."""
    m = body.material
    if isinstance(m, Regions) or body.fibres is not None:  # a body of regions or fibres stacks with none (its
        # labels and directions are its own mesh's)
        return ("own", body)
    return (body.mesh.kind, float(m.E), float(m.nu), float(m.density), body.model, body.damping,
            body.damp_rigid, body.mass_kind, body.hex_rotation, body.volumetric)


class BodyStack(FemBody):
    """The FemBody of ``members`` (two or more, one stack_key) side by side: nodes of member i are rows
    ``offsets[i]:offsets[i + 1]`` of the stack's arrays. Its state starts as the members' state."""

    def __init__(self, members: Sequence[FemBody]):
        members = list(members)
        if len(members) < 2:
            raise InvalidInputError(f"a BodyStack needs two or more bodies, got {len(members)}")
        if any(isinstance(b, BodyStack) for b in members):
            raise InvalidInputError("a BodyStack's members must be bodies, not stacks (stack their members instead)")
        if len({id(b) for b in members}) != len(members):
            raise InvalidInputError("a body appears twice among the members of a BodyStack")
        keys = {stack_key(b) for b in members}
        if len(keys) != 1:
            raise InvalidInputError(f"bodies of a stack must agree in element kind, material, warping, damping "
                                    f"and mass; got {sorted(map(str, keys))}")
        first = members[0]
        sizes = np.array([b.n_nodes for b in members])
        self.offsets = np.concatenate([[0], np.cumsum(sizes)])
        self._rows = [slice(int(a), int(b)) for a, b in zip(self.offsets[:-1], self.offsets[1:])]
        nodes = np.concatenate([b.mesh.nodes for b in members])
        elements = np.concatenate([b.mesh.elements + o for b, o in zip(members, self.offsets[:-1])])
        self.element_offsets = np.concatenate([[0], np.cumsum([b.mesh.n_elements for b in members])])
        with warnings.catch_warnings():  # the members have said it
            warnings.simplefilter("ignore", LockingWarning)
            super().__init__(Mesh(nodes, elements, first.mesh.kind), first.material, first.warping, first.damping,
                             first.mass_kind, first.hex_rotation, first.damp_rigid, first.volumetric,
                             first.model)
        self.members = members
        self._views: tuple[list, list] = ([], [])  # the members' positions and velocities as last made views
        self._supports_seen: tuple | None = None  # (members' fixed (N,), their prescriptions) as last read
        self.gather(force=True)

    def part_offsets(self) -> np.ndarray:
        """Each member a part of its own (FemBody.rigid_parts)."""
        return self.offsets

    def member_of(self, nodes: np.ndarray) -> np.ndarray:
        """The member index (m,) of each stack node (m,)."""
        return np.searchsorted(self.offsets, nodes, side="right") - 1

    def rows(self, i: int) -> slice:
        """The stack's rows of member i."""
        return self._rows[i]

    def gather(self, force: bool = False) -> None:
        """Read the members' state and supports where they changed since :meth:`scatter` (a member whose
        ``positions`` or ``velocities`` were assigned anew; in-place writes reach the stack through the views)."""
        xs, vs = self._views
        if force or len(xs) != len(self.members) or any(
                b._positions is not x or b._velocities is not v for b, x, v in zip(self.members, xs, vs)):
            for b, rows in zip(self.members, self._rows):
                self._positions[rows] = b._positions
                self._velocities[rows] = b._velocities
            self.scatter()
        self._gather_supports()

    def scatter(self, which: str | None = None) -> None:
        """Make the members' state views of the stack's rows (done whenever the stack's state is assigned): both,
        or only ``which`` ("positions" or "velocities", the one just assigned)."""
        if "members" not in self.__dict__ or "_velocities" not in self.__dict__:
            return  # FemBody.__init__ sets the state before the members are known
        xs, vs = self._views
        if which != "velocities" or len(xs) != len(self.members):
            xs = [self._positions[rows] for rows in self._rows]
        if which != "positions" or len(vs) != len(self.members):
            vs = [self._velocities[rows] for rows in self._rows]
        for b, x, v in zip(self.members, xs, vs):
            b._positions, b._velocities = x, v
        self._views = (xs, vs)

    def _set_positions(self, value) -> None:
        FemBody.positions.fset(self, value)
        self.scatter("positions")

    def _set_velocities(self, value) -> None:
        FemBody.velocities.fset(self, value)
        self.scatter("velocities")

    positions = property(FemBody.positions.fget, _set_positions, doc=FemBody.positions.__doc__)
    velocities = property(FemBody.velocities.fget, _set_velocities, doc=FemBody.velocities.__doc__)

    def _gather_supports(self) -> None:
        """The stack's fixed and prescribed nodes: the members', renumbered (re-read when a member's changed)."""
        fixed = np.concatenate([b.fixed for b in self.members])
        prescribed = [(k, ids.tobytes(), id(m)) for k, b in enumerate(self.members) for ids, m in b.prescribed]
        seen = self._supports_seen  # the members' supports as last read (the stack's own may add to them)
        if seen is not None and prescribed == seen[1] and np.array_equal(fixed, seen[0]):
            return
        self._supports_seen = (fixed, prescribed)
        self.fixed = fixed.copy()
        self.prescribed = [(ids + o, motion) for b, o in zip(self.members, self.offsets[:-1])
                           for ids, motion in b.prescribed]
