"""A World's saved state: the soft side (softbody.state.SimulationState), pybullet's world, and what the coupling
carries from one step to the next (contact warm starts and friction states, the stacking of the soft bodies, the
reactions lagged to the next step, the last step's results), keyed by stable handles (a soft body by its index in
``World.bodies``, a stepped body by the indices of its members, an attachment by its index), so that a state
written to disk restores into the same scene built again in another process.

pybullet's part is the bytes of its ``saveBullet`` (restored with ``restoreState(fileName=...)``, in this process or
another). What pybullet does not save stays as it is: motor targets and gains set with
``setJointMotorControl2``, user constraints and changed dynamics (the scene, not its state).
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pybullet as p

from softbody.state import FORMAT, SimulationState, write_state


@dataclass
class WorldState:
    """What :meth:`integration.World.save_state` saved after the World's step ``sim.steps`` (time ``sim.t``).

    sim: the soft bodies' state; members: node counts of World.bodies; layout: the stepped bodies as tuples of
    member indices; bullet: pybullet's saveBullet bytes; the other fields: the coupling's state (see World).
    """

    sim: SimulationState
    members: list[int]
    attachments: int
    layout: list[tuple[int, ...]]
    dense_group: dict[int, int]
    restack_due: bool
    started: list[int]
    previous: dict[tuple, Any]
    lagged: list
    results: dict[str, Any]
    bullet: bytes
    format: int = FORMAT

    def write(self, path: str | Path) -> Path:
        """Write this state to ``path`` (pickle); ``World.restore_state(path)`` reads it back, also in a new process
        with the same scene built."""
        return write_state(self, path)


def bullet_bytes(client: int) -> bytes:
    """pybullet's whole world (saveBullet) as bytes."""
    fd, name = tempfile.mkstemp(suffix=".bullet")
    os.close(fd)
    try:
        p.saveBullet(name, physicsClientId=client)
        return Path(name).read_bytes()
    finally:
        os.unlink(name)


def restore_bullet(state: WorldState, client: int, fresh: bool) -> None:
    """Put pybullet's world of ``client`` back to ``state`` from its saveBullet bytes (``fresh``: the World never
    stepped, so pybullet has no contact pairs yet for the saved contact points to go into: a collision pass makes
    them first; without it a restored stack of boxes in a new process drifted 0.6 mm from the original in 1 s)."""
    fd, name = tempfile.mkstemp(suffix=".bullet")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(state.bullet)
        if fresh:
            p.performCollisionDetection(physicsClientId=client)
        p.restoreState(fileName=name, physicsClientId=client)
    finally:
        os.unlink(name)
