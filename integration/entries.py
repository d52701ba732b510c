"""What a World keeps for each soft body: one SoftEntry per body added (its handle: its index in ``World.bodies``)
and one SteppedEntry per body the Simulation steps (a member alone, or a BodyStack of members that share what the
entry holds; its handle: its index in ``sim.bodies``, which a restack renumbers).

The World reaches a body's settings, surface, place in a stack and contact group through these, by handle, in place of
parallel dicts keyed by ``id(body)``.
"""
from __future__ import annotations

from dataclasses import dataclass

from softbody import FemBody

from .rigid import RigidLink
from .softcontact import SoftSurface


def _ignores(skip: set | frozenset, rb: RigidLink) -> bool:
    """Whether ``skip`` holds rigid link rb: its own key, or its body's (body id, None)."""
    return rb.key in skip or (rb.id, None) in skip


@dataclass
class SoftEntry:
    """A soft body added to a World.

    friction: its Coulomb coefficient; ignore: what it does not collide with: rigid links as (body id, link) or
    (body id, None) for all of a body's links, soft bodies as ("soft", FemBody); self_contact: its surface is kept
    from passing through itself; surface: its surface (nodes, triangles, edges) for contact; place: (index of its
    stepped body in ``sim.bodies``, its first node there); group: the handle of the first member of its contact group
    (bodies in soft contact, or touching one movable rigid body, are stepped alone: World._group_dense), None: none;
    started: it took a step."""

    body: FemBody
    friction: float
    ignore: set
    self_contact: bool
    surface: SoftSurface
    place: tuple[int, int] = (-1, 0)
    group: int | None = None
    started: bool = False

    def rigid_ignore(self) -> frozenset:
        """The rigid links it ignores (soft pairs are searched per member, not per stepped body)."""
        return frozenset(k for k in self.ignore if k[0] != "soft")

    def ignores(self, rb: RigidLink) -> bool:
        """Whether it does not collide with rigid link ``rb``."""
        return _ignores(self.ignore, rb)

    def ignores_soft(self, other: FemBody) -> bool:
        return ("soft", other) in self.ignore


@dataclass
class SteppedEntry:
    """A body the Simulation steps: its members' handles (one: a body alone), the friction and ignored rigid links they
    share, and its surface (a stack's: all its members' in its numbering) for contact with rigid links."""

    body: FemBody
    members: list[int]
    friction: float
    ignore: set | frozenset  # a body alone: its member's own set (attach may add to it)
    surface: SoftSurface

    def ignores(self, rb: RigidLink) -> bool:
        """Whether it does not collide with rigid link ``rb``."""
        return _ignores(self.ignore, rb)
